"""volgrad as a JAX function with a custom vector-Jacobian product: the density in, images out.

    import volgrad, volgrad.jax
    render = volgrad.jax.renderer(scene, cameras, spp=16, grad_spp=8)
    loss = lambda density, seed: jnp.mean((render(density, seed) - targets) ** 2)
    value, gradient = jax.value_and_grad(loss)(density, seed)

The render and its gradient run on the CPU through ``jax.pure_callback``; the backward pass is
``Scene.grad`` with the cotangent as the adjoint, on volgrad's adjoint stream (independent of the
render's at the same seed, as in ``volgrad.torch``).
"""

from __future__ import annotations

from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from volgrad._volgrad import Camera, Scene

__all__ = ["renderer"]


def renderer(
    scene: Scene,
    cameras: Optional[Sequence[Camera]] = None,
    *,
    spp: Optional[int] = None,
    grad_spp: Optional[int] = None,
    estimator: str = "joint",
    max_depth: Optional[int] = None,
    threads: Optional[int] = None,
):
    """A function ``render(density, seed)`` of ``scene`` with ``density`` (float32, shaped like
    ``scene.density[0]``) in place of its own, differentiable in ``density`` with ``jax.grad``."""
    cams = list(cameras) if cameras is not None else None
    first = cams[0] if cams else scene.camera
    if first is None:
        raise ValueError("the scene has no camera of its own (Scene.from_parts without camera=): give cameras")
    shape = (first.height, first.width, 3) if cams is None else (len(cams), first.height, first.width, 3)

    def images(density, seed):
        return scene.render(
            cams, spp=spp, seed=int(seed), max_depth=max_depth, threads=threads,
            density=np.asarray(density, np.float32),
        )

    def vjp(density, seed, adjoint):
        return scene.grad(
            np.asarray(adjoint, np.float32), cams, estimator=estimator, spp=grad_spp or spp,
            seed=int(seed), max_depth=max_depth, threads=threads,
            density=np.asarray(density, np.float32),
        )

    @jax.custom_vjp
    def render(density, seed):
        return jax.pure_callback(images, jax.ShapeDtypeStruct(shape, jnp.float32), density, seed)

    def forward(density, seed):
        return render(density, seed), (density, seed)

    def backward(saved, adjoint):
        density, seed = saved
        out = jax.ShapeDtypeStruct(density.shape, jnp.float32)
        return jax.pure_callback(vjp, out, density, seed, adjoint), None

    render.defvjp(forward, backward)
    return render
