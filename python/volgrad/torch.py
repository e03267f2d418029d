"""volgrad as a PyTorch autograd function: the density (and the albedo and emission grids) in,
images out, gradients back.

    import volgrad, volgrad.torch
    scene = volgrad.Scene.load("scenes/cloud.toml")
    density = torch.zeros(scene.density[0].shape, requires_grad=True)
    images = volgrad.torch.render(density, scene, cameras, spp=8, seed=i)
    loss = ((images - targets) ** 2).mean(); loss.backward()   # density.grad from Scene.grad
    images = volgrad.torch.render(None, scene, cameras, emission=emission, seed=i)  # or a flame's glow

The forward pass renders with ``seed``; the backward pass traces its gradient paths with the same
seed on volgrad's adjoint stream, which is independent of the render's: the adjoint (built from
the rendered image) and the gradient's paths do not share noise, so their product is unbiased.
Without ``seed``, each call draws one from PyTorch's generator (``torch.manual_seed`` makes a run
repeatable): a loop that leaves it out still gets new noise at every step.
Tensors are CPU float32; a contiguous tensor reaches volgrad without a copy.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import numpy as np
import torch

from volgrad import _checks
from volgrad._volgrad import Camera, Scene

__all__ = ["render"]


_ESTIMATORS = ("joint", "drt", "naive")


def _as_array(tensor: torch.Tensor, name: str) -> np.ndarray:
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor (got {type(tensor).__name__})")
    if tensor.layout != torch.strided:
        raise TypeError(f"{name} must be a dense tensor (got layout {tensor.layout})")
    if tensor.device.type != "cpu":
        raise ValueError(f"{name} must be a CPU tensor (got one on {tensor.device})")
    if tensor.dtype != torch.float32:
        raise TypeError(f"{name} must be float32 (got {tensor.dtype})")
    # .numpy() shares memory; only a non-contiguous tensor is copied.
    return tensor.detach().contiguous().numpy()


# The grids a render can take in place of the scene's, with the parameter of their gradient.
_GRIDS = (("density", "extinction"), ("albedo", "albedo"), ("emission", "emission"))


class _Render(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, albedo, emission, scene, cameras, estimator, spp, grad_spp, seed, max_depth, threads):
        tensors = (density, albedo, emission)
        grids = _grids(tensors)
        images = scene.render(cameras, spp=spp, seed=seed, max_depth=max_depth, threads=threads, **grids)
        ctx.save_for_backward(*tensors)
        ctx.settings = (scene, cameras, estimator, grad_spp, seed, max_depth, threads)
        ctx.density_changes = scene._density_changes
        return torch.from_numpy(images)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_output):
        scene, cameras, estimator, spp, seed, max_depth, threads = ctx.settings
        # Even with the density as a tensor: set_density may have moved the box the tensor's
        # voxels stand in, and the albedo and emission are rendered over that box too.
        if scene._density_changes != ctx.density_changes:
            raise RuntimeError(
                "the scene's density was replaced (set_density) between this render and its backward "
                "pass, which would differentiate another volume: call backward before set_density"
            )
        grids = _grids(ctx.saved_tensors)
        adjoint = _as_array(grad_output, "grad_output")
        # One gradient pass per grid that wants one, each with the same paths.
        gradients = tuple(
            torch.from_numpy(
                scene.grad(
                    adjoint, cameras, estimator=estimator, parameter=parameter, spp=spp, seed=seed,
                    max_depth=max_depth, threads=threads, **grids,
                )
            )
            if wanted
            else None
            for (_, parameter), wanted in zip(_GRIDS, ctx.needs_input_grad)
        )
        return gradients + (None,) * 8


def _grids(tensors) -> dict:
    return {name: _as_array(t, name) for (name, _), t in zip(_GRIDS, tensors) if t is not None}


def render(
    density: Optional[torch.Tensor],
    scene: Scene,
    cameras: Union[Camera, Sequence[Camera], None] = None,
    *,
    albedo: Optional[torch.Tensor] = None,
    emission: Optional[torch.Tensor] = None,
    spp: Optional[int] = None,
    grad_spp: Optional[int] = None,
    seed: Optional[int] = None,
    estimator: str = "joint",
    max_depth: Optional[int] = None,
    threads: Optional[int] = None,
) -> torch.Tensor:
    """Images of ``scene`` with ``density`` (shaped like ``scene.density[0]``; None for the
    scene's own), and ``albedo`` and ``emission`` if given (shaped as ``Scene.grad`` returns
    them), in place of its grids.

    Returns (H, W, 3) for the scene's camera or one camera, (N, H, W, 3) for a list of cameras.
    Its backward pass is ``Scene.grad`` with ``grad_output`` as the adjoint (``grad_spp`` paths
    per pixel, ``spp`` when not given), once for each of the three that requires a gradient.
    ``seed`` None draws one from PyTorch's generator. The scene is not changed.
    """
    cams = cameras if cameras is None or isinstance(cameras, Camera) else list(cameras)
    # Checked here, not when the backward pass first uses them: the render is paid for by then.
    if estimator not in _ESTIMATORS:
        raise ValueError(f'estimator must be "joint", "drt" or "naive" (got "{estimator}")')
    grad_spp = _checks.samples(spp, grad_spp)
    _checks.seed(seed)
    if seed is None:
        seed = int(torch.randint(0, 2**63 - 1, ()))
    return _Render.apply(
        density, albedo, emission, scene, cams, estimator, spp, grad_spp, seed, max_depth, threads
    )
