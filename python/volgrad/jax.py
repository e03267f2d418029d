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

import numbers
import threading
from typing import Optional, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np

from volgrad import _checks
from volgrad._volgrad import Camera, Scene

__all__ = ["renderer"]

# Every volgrad call already uses all its threads: callbacks run one after another.
_ONE_AT_A_TIME = threading.Lock()


def renderer(
    scene: Scene,
    cameras: Union[Camera, Sequence[Camera], None] = None,
    *,
    spp: Optional[int] = None,
    grad_spp: Optional[int] = None,
    estimator: str = "joint",
    parameter: str = "extinction",
    max_depth: Optional[int] = None,
    threads: Optional[int] = None,
):
    """A function ``render(values, seed)`` of ``scene`` with ``values`` in place of its density
    (shaped like ``scene.density[0]``), differentiable in ``values`` with ``jax.grad``; with
    ``parameter="albedo"`` or ``"emission"``, in place of that grid instead (shaped as
    ``Scene.grad`` returns its gradient). The images and the gradient come back in the values'
    dtype (float32, or float64 under ``jax_enable_x64``; volgrad computes in float32). Under
    ``jax.vmap`` the batch's members are rendered one after another."""
    one = cameras is None or isinstance(cameras, Camera)
    cams = cameras if one else list(cameras)
    if one:
        first = scene.camera if cameras is None else cameras
        if first is None:
            raise ValueError("the scene has no camera of its own (Scene.from_parts without camera=): give cameras")
        shape = (first.height, first.width, 3)
    elif cams:
        shape = (len(cams), cams[0].height, cams[0].width, 3)
        # Errors inside the callback reach the caller as JAX's runtime errors, their type lost:
        # what can be checked before is checked here and while tracing.
        sizes = {(c.width, c.height) for c in cams}
        if len(sizes) > 1:
            raise ValueError(f"cameras: one call's images share a size (got {sorted(sizes)})")
    else:
        raise ValueError("cameras: the list is empty (give None for the scene's own camera)")

    grid = {"extinction": "density", "albedo": "albedo", "emission": "emission"}.get(parameter)
    if grid is None:
        raise ValueError(f'parameter must be "extinction", "albedo" or "emission" (got "{parameter}")')
    if estimator not in ("joint", "drt", "naive"):
        raise ValueError(f'estimator must be "joint", "drt" or "naive" (got "{estimator}")')
    grad_spp = _checks.samples(spp, grad_spp)
    # A ValueError now where the scene has no such grid.
    values_shape = tuple(scene._values_shape(parameter))

    def images(values, seed):
        return scene.render(
            cams, spp=spp, seed=int(seed), max_depth=max_depth, threads=threads,
            **{grid: np.asarray(values, np.float32)},
        )

    def density_changes():
        # How many times set_density has replaced the scene's density (mod 2³², a uint32 for
        # JAX without x64): the gradient refuses a render of another volume.
        return scene._density_changes % 2**32

    def vjp(values, seed, changes, adjoint):
        if int(changes) != density_changes():
            raise RuntimeError(
                "the scene's density was replaced (set_density) between this render and its "
                "gradient, which would differentiate another volume: take the gradient first"
            )
        return scene.grad(
            np.asarray(adjoint, np.float32), cams, estimator=estimator, parameter=parameter,
            spp=grad_spp, seed=int(seed), max_depth=max_depth, threads=threads,
            **{grid: np.asarray(values, np.float32)},
        )

    def call(function, out, *args):
        def one_at_a_time(*values):
            # XLA may run independent callbacks at once, and a Scene takes one call at a time.
            with _ONE_AT_A_TIME:
                return function(*values)

        return jax.pure_callback(one_at_a_time, out, *args, vmap_method="sequential")

    def typed(function, dtype):
        return lambda *values: np.asarray(function(*values), dtype)

    def checked(values, seed):
        # Refused while tracing, as volgrad.torch refuses them, rather than cast in the callback.
        if values.dtype not in (jnp.float32, jnp.float64):
            raise TypeError(f"{grid} must be float32 or float64 (got {values.dtype})")
        if tuple(values.shape) != values_shape:
            raise ValueError(f"{grid} has shape {tuple(values.shape)}: the scene's is {values_shape}")
        if not jnp.issubdtype(jnp.result_type(seed), jnp.integer):
            raise TypeError(f"seed must be an integer (got {jnp.result_type(seed)})")
        if isinstance(seed, numbers.Integral):
            _checks.seed(seed)
        return jax.ShapeDtypeStruct(shape, values.dtype)

    @jax.custom_vjp
    def render(values, seed):
        out = checked(values, seed)
        return call(typed(images, values.dtype), out, values, seed)

    def forward(values, seed):
        out = (checked(values, seed), jax.ShapeDtypeStruct((), jnp.uint32))

        def render_and_count(v, s):
            return np.asarray(images(v, s), values.dtype), np.uint32(density_changes())

        image, changes = call(render_and_count, out, values, seed)
        return image, (values, seed, changes)

    def backward(saved, adjoint):
        values, seed, changes = saved
        out = jax.ShapeDtypeStruct(values.shape, values.dtype)
        return call(typed(vjp, values.dtype), out, values, seed, changes, adjoint), None

    render.defvjp(forward, backward)
    return render
