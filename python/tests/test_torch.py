"""volgrad.torch: the autograd function's backward is Scene.grad of grad_output; tensors reach
volgrad without a copy; a short reconstruction in PyTorch gets close to the truth."""

import importlib.util

import numpy as np
import pytest
import torch

import volgrad
import volgrad.torch
from conftest import REPO, ball
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


def test_each_grid_that_wants_a_gradient_gets_its_own():
    """Albedo and emission tensors in place of the scene's grids: the backward pass gives each one
    that requires a gradient Scene.grad with its parameter, and the density (the scene's own,
    given as None) none."""
    kind = {"radiance": [1.0, 0.6, 0.2]}
    albedo = np.full(ball().shape, 0.7, np.float32)
    emission = ((ball() > 0) * 0.4).astype(np.float32)
    scene = small_scene(albedo=albedo, emission=emission, emission_kind=kind)
    a = torch.from_numpy(albedo * 0.9).requires_grad_(True)
    e = torch.from_numpy(emission * 1.5).requires_grad_(True)
    weights = torch.from_numpy(np.random.default_rng(3).normal(size=(24, 24, 3)).astype(np.float32))
    images = volgrad.torch.render(None, scene, albedo=a, emission=e, spp=2, grad_spp=4, seed=9)
    (images * weights).sum().backward()
    arrays = dict(albedo=a.detach().numpy(), emission=e.detach().numpy())
    for tensor, parameter in ((a, "albedo"), (e, "emission")):
        expected = scene.grad(weights.numpy(), parameter=parameter, spp=4, seed=9, **arrays)
        np.testing.assert_array_equal(tensor.grad.numpy(), expected)

    # The scene's own density replaced between the render and its backward pass: refused, not a
    # gradient of another volume.
    images = volgrad.torch.render(None, scene, albedo=a, spp=2, seed=9)
    scene.set_density(ball() * 2)
    with pytest.raises(RuntimeError, match="set_density"):
        (images * weights).sum().backward()
    # With the density as a tensor too: set_density may move the box its voxels stand in (here
    # by one world unit), and the backward pass would differentiate the moved volume.
    density = torch.from_numpy(ball()).requires_grad_(True)
    images = volgrad.torch.render(density, scene, spp=2, seed=9)
    values, index_to_world = scene.density
    index_to_world[:3, 3] += 1.0
    scene.set_density(values, index_to_world)
    with pytest.raises(RuntimeError, match="set_density"):
        (images * weights).sum().backward()


def test_without_a_seed_each_call_draws_one_from_torch():
    """A loop that leaves out seed= gets new noise at every step (not the scene's one seed), and
    torch.manual_seed repeats a run."""
    scene = small_scene()
    density = torch.from_numpy(scene.density[0])
    torch.manual_seed(5)
    first, second = (volgrad.torch.render(density, scene, spp=2) for _ in range(2))
    assert not torch.equal(first, second)
    torch.manual_seed(5)
    assert torch.equal(volgrad.torch.render(density, scene, spp=2), first)


def test_a_contiguous_tensor_is_not_copied():
    tensor = torch.rand(8, 8, 8)
    assert volgrad.torch._as_array(tensor, "density").ctypes.data == tensor.data_ptr()


def test_tensors_of_another_type_are_refused_by_name():
    scene = small_scene()
    with pytest.raises(TypeError, match="^density must be a torch.Tensor"):
        volgrad.torch.render(scene.density[0], scene)
    with pytest.raises(TypeError, match="density must be float32"):
        volgrad.torch.render(torch.zeros(16, 16, 16, dtype=torch.float64), scene)
    density = torch.from_numpy(scene.density[0])
    with pytest.raises(TypeError, match="density must be a dense tensor"):
        volgrad.torch.render(density.to_sparse(), scene, seed=1)
    # Settings only the backward pass uses are checked before the render is paid for.
    with pytest.raises(ValueError, match="estimator must be"):
        volgrad.torch.render(density, scene, estimator="fast", seed=1)
    for spp, grad_spp, name in [(2, 0, "grad_spp"), (2, 2.5, "grad_spp"), (2, "4", "grad_spp"), (0, None, "spp"), (-1, 2, "spp")]:
        with pytest.raises(ValueError, match=f"^{name} must be a whole number ≥ 1"):
            volgrad.torch.render(density, scene, spp=spp, grad_spp=grad_spp, seed=1)
    for seed in (-1, 2**64, 1.5, True):
        with pytest.raises(ValueError, match=r"^seed must be a whole number in \[0, 2\*\*64\)"):
            volgrad.torch.render(density, scene, seed=seed)


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
