"""volgrad as a PyTorch autograd function: the density in, images out, gradients back.

    import volgrad, volgrad.torch
    scene = volgrad.Scene.load("scenes/cloud.toml")
    density = torch.zeros(scene.density[0].shape, requires_grad=True)
    images = volgrad.torch.render(density, scene, cameras, spp=8, seed=i)
    loss = ((images - targets) ** 2).mean(); loss.backward()   # density.grad from Scene.grad

The forward pass renders with ``seed``; the backward pass traces its gradient paths with the same
seed on volgrad's adjoint stream, which is independent of the render's: the adjoint (built from
the rendered image) and the gradient's paths do not share noise, so their product is unbiased.
Tensors are CPU float32; a contiguous tensor reaches volgrad without a copy.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch

from volgrad._volgrad import Camera, Scene

__all__ = ["render"]


def _as_array(tensor: torch.Tensor, name: str) -> np.ndarray:
    if tensor.device.type != "cpu":
        raise ValueError(f"{name} must be a CPU tensor (got one on {tensor.device})")
    if tensor.dtype != torch.float32:
        raise TypeError(f"{name} must be float32 (got {tensor.dtype})")
    # .numpy() shares memory; only a non-contiguous tensor is copied.
    return tensor.detach().contiguous().numpy()


class _Render(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, scene, cameras, estimator, spp, grad_spp, seed, max_depth, threads):
        values = _as_array(density, "density")
        images = scene.render(
            cameras, spp=spp, seed=seed, max_depth=max_depth, threads=threads, density=values
        )
        ctx.save_for_backward(density)
        ctx.settings = (scene, cameras, estimator, grad_spp, seed, max_depth, threads)
        return torch.from_numpy(images)

    @staticmethod
    def backward(ctx, grad_output):
        (density,) = ctx.saved_tensors
        scene, cameras, estimator, spp, seed, max_depth, threads = ctx.settings
        adjoint = _as_array(grad_output, "grad_output")
        gradient = scene.grad(
            adjoint,
            cameras,
            estimator=estimator,
            spp=spp,
            seed=seed,
            max_depth=max_depth,
            threads=threads,
            density=_as_array(density, "density"),
        )
        return (torch.from_numpy(gradient),) + (None,) * 8


def render(
    density: torch.Tensor,
    scene: Scene,
    cameras: Optional[Sequence[Camera]] = None,
    *,
    spp: Optional[int] = None,
    grad_spp: Optional[int] = None,
    seed: Optional[int] = None,
    estimator: str = "joint",
    max_depth: Optional[int] = None,
    threads: Optional[int] = None,
) -> torch.Tensor:
    """Images of ``scene`` with ``density`` (shaped like ``scene.density[0]``) in place of its own.

    Returns (H, W, 3) for the scene's camera, (N, H, W, 3) for a list of cameras. Its backward
    pass is ``Scene.grad`` with ``grad_output`` as the adjoint (``grad_spp`` paths per pixel,
    ``spp`` when not given). The scene is not changed.
    """
    cams = list(cameras) if cameras is not None else None
    return _Render.apply(
        density, scene, cams, estimator, spp, grad_spp or spp, seed, max_depth, threads
    )
