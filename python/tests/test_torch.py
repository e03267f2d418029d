"""volgrad.torch: the autograd function's backward is Scene.grad of grad_output; tensors reach
volgrad without a copy; a short reconstruction in PyTorch gets close to the truth."""

import importlib.util

import numpy as np
import pytest
import torch

import volgrad
import volgrad.torch
from conftest import REPO
from test_scene import small_scene


def test_backward_is_the_vector_jacobian_product():
    scene = small_scene()
    density = torch.from_numpy(scene.density[0]).requires_grad_(True)
    cameras = [scene.camera, volgrad.Camera((4, 0.5, 0), (0, 0, 0), width=24, height=24)]
    weights = torch.from_numpy(np.random.default_rng(0).normal(size=(2, 24, 24, 3)).astype(np.float32))
    images = volgrad.torch.render(density, scene, cameras, spp=4, grad_spp=8, seed=7)
    np.testing.assert_array_equal(images.detach().numpy(), scene.render(cameras, spp=4, seed=7))
    (images * weights).sum().backward(retain_graph=True)
    expected = scene.grad(weights.numpy(), cameras, spp=8, seed=7)
    np.testing.assert_array_equal(density.grad.numpy(), expected)
    # A loss of twice the images has twice the gradient: the function is linear in grad_output.
    density.grad = None
    (2 * images * weights).sum().backward()
    np.testing.assert_allclose(density.grad.numpy(), 2 * expected, rtol=1e-6, atol=1e-12)


def test_a_contiguous_tensor_is_not_copied():
    tensor = torch.rand(8, 8, 8)
    assert volgrad.torch._as_array(tensor, "density").ctypes.data == tensor.data_ptr()


def test_tensors_of_another_type_are_refused_by_name():
    scene = small_scene()
    with pytest.raises(TypeError, match="density must be float32"):
        volgrad.torch.render(torch.zeros(16, 16, 16, dtype=torch.float64), scene)


def test_the_example_reconstructs_the_ball():
    path = REPO / "examples" / "python" / "reconstruct.py"
    spec = importlib.util.spec_from_file_location("reconstruct", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    # 40 steps: from an empty start (about 10 dB) to above 24 dB held-out; a wrong sign or a
    # gradient that misses its voxels stays near the start.
    density, held_out_psnr = example.reconstruct(iterations=40, log=lambda line: None)
    assert held_out_psnr > 24.0, held_out_psnr
    assert density.max() > 0
