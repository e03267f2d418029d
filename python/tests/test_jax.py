"""volgrad.jax: jax.grad through the custom VJP is Scene.grad of the cotangent; vmap and float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volgrad
import volgrad.jax
from conftest import ball
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


def test_a_density_replaced_between_the_render_and_its_gradient_is_refused():
    """set_density after the render moves the box the values stand in (here by one world unit):
    the gradient would be of the moved volume."""
    scene = small_scene()
    render = volgrad.jax.renderer(scene, spp=2, grad_spp=2)
    values, index_to_world = scene.density
    weights = jnp.ones((24, 24, 3))
    _, vjp = jax.vjp(lambda d: render(d, 3), jnp.asarray(values))
    index_to_world[:3, 3] += 1.0
    scene.set_density(values, index_to_world)
    # Raised inside JAX's callback, which keeps the message but not the type.
    with pytest.raises(Exception, match="set_density"):
        jax.block_until_ready(vjp(weights))
    # A render after it is differentiated as the scene now is.
    gradient = jax.grad(lambda d: jnp.sum(render(d, 3) * weights))(jnp.asarray(values))
    np.testing.assert_array_equal(np.asarray(gradient), scene.grad(np.asarray(weights, np.float32), spp=2, seed=3))


def test_vmap_over_seeds_renders_each():
    scene = small_scene()
    render = volgrad.jax.renderer(scene, scene.camera, spp=2, grad_spp=2)
    density = jnp.asarray(scene.density[0])
    images = jax.vmap(lambda s: render(density, s))(jnp.arange(2))
    assert images.shape == (2, 24, 24, 3)
    for s in range(2):
        np.testing.assert_array_equal(np.asarray(images[s]), scene.render(spp=2, seed=s))


def test_a_float64_density_gets_float64_results():
    scene = small_scene()
    render = volgrad.jax.renderer(scene, spp=2, grad_spp=2)
    weights = np.random.default_rng(2).normal(size=(24, 24, 3))
    with jax.enable_x64(True):
        density = jnp.asarray(scene.density[0], jnp.float64)
        image = render(density, 3)
        gradient = jax.grad(lambda d: jnp.sum(render(d, 3) * weights))(density)
        assert image.dtype == jnp.float64 and gradient.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(image), scene.render(spp=2, seed=3))
    expected = scene.grad(weights.astype(np.float32), spp=2, seed=3)
    np.testing.assert_allclose(np.asarray(gradient), expected, rtol=1e-6, atol=1e-9)


def test_the_emission_as_the_argument():
    kind = {"radiance": [1.0, 0.6, 0.2]}
    emission = ((ball() > 0) * 0.4).astype(np.float32)
    scene = small_scene(emission=emission, emission_kind=kind)
    weights = np.random.default_rng(4).normal(size=(24, 24, 3)).astype(np.float32)
    render = volgrad.jax.renderer(scene, spp=2, grad_spp=4, parameter="emission")
    values = jnp.asarray(emission * 2)
    np.testing.assert_array_equal(np.asarray(render(values, 5)), scene.render(spp=2, seed=5, emission=emission * 2))
    gradient = jax.grad(lambda v: jnp.sum(render(v, 5) * weights))(values)
    expected = scene.grad(weights, parameter="emission", spp=4, seed=5, emission=emission * 2)
    np.testing.assert_array_equal(np.asarray(gradient), expected)


def test_arguments_of_another_type_are_refused_while_tracing():
    scene = small_scene()
    render = volgrad.jax.renderer(scene, spp=2)
    density = scene.density[0]
    with pytest.raises(TypeError, match="density must be float32 or float64"):
        render(jnp.asarray(density).astype(jnp.int32), 1)
    with pytest.raises(TypeError, match="seed must be an integer"):
        render(jnp.asarray(density), 1.7)
    with pytest.raises(ValueError, match="estimator must be"):
        volgrad.jax.renderer(scene, estimator="fast")
    with pytest.raises(ValueError, match="^spp must be a whole number"):
        volgrad.jax.renderer(scene, spp=0)
    # Checked before the callback, whose errors lose their type on the way out of JAX.
    with pytest.raises(ValueError, match="density has shape"):
        render(jnp.asarray(density[:4]), 1)
    with pytest.raises(ValueError, match="albedo is a constant"):
        volgrad.jax.renderer(scene, parameter="albedo")
    with pytest.raises(ValueError, match=r"seed must be a whole number in \[0, 2\*\*64\)"):
        render(jnp.asarray(density), -1)
    mixed = [scene.camera, volgrad.Camera((4, 0.5, 0), (0, 0, 0), width=8, height=8)]
    with pytest.raises(ValueError, match="share a size"):
        volgrad.jax.renderer(scene, mixed)


def test_renderers_of_one_scene_take_turns():
    """Two renderers of one scene called at once (here from two threads; XLA may also run the
    callbacks of one jitted function at once): a Scene takes one call at a time, and the
    callbacks take turns rather than fail with "busy"."""
    import threading

    scene = small_scene()
    small = volgrad.Camera((0.3, 0.5, 4.0), (0, 0, 0), fov_deg=40, width=8, height=8)
    wide, narrow = volgrad.jax.renderer(scene, spp=64), volgrad.jax.renderer(scene, small, spp=64)
    density = jnp.asarray(scene.density[0])
    errors = []

    def calls(render, seed):
        try:
            for _ in range(4):
                render(density, seed).block_until_ready()
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=calls, args=(r, s)) for r, s in ((wide, 3), (narrow, 4))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    np.testing.assert_array_equal(np.asarray(narrow(density, 4)), scene.render(small, spp=64, seed=4))
