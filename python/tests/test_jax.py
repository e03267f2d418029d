"""volgrad.jax: jax.grad through the custom VJP is Scene.grad of the cotangent."""

import jax
import jax.numpy as jnp
import numpy as np

import volgrad
import volgrad.jax
from test_scene import small_scene


def test_jax_grad_is_the_vector_jacobian_product():
    scene = small_scene()
    cameras = [scene.camera, volgrad.Camera((4, 0.5, 0), (0, 0, 0), width=24, height=24)]
    weights = np.random.default_rng(1).normal(size=(2, 24, 24, 3)).astype(np.float32)
    render = volgrad.jax.renderer(scene, cameras, spp=4, grad_spp=8)
    density = jnp.asarray(scene.density[0])
    np.testing.assert_array_equal(np.asarray(render(density, 7)), scene.render(cameras, spp=4, seed=7))
    gradient = jax.grad(lambda d: jnp.sum(render(d, 7) * weights))(density)
    np.testing.assert_array_equal(np.asarray(gradient), scene.grad(weights, cameras, spp=8, seed=7))
    # Under jit, with the seed a traced argument: the same numbers.
    jitted = jax.jit(jax.grad(lambda d, s: jnp.sum(render(d, s) * weights)))
    np.testing.assert_array_equal(np.asarray(jitted(density, 7)), np.asarray(gradient))
