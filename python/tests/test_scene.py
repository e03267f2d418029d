"""Scenes, renders and gradients: the same bits as the command line, at any thread count; the
gradient against finite differences; refusals by argument name; Ctrl-C."""

import select
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

import volgrad
from conftest import REPO, ball, read_exr, voxel_map

SPHERE = REPO / "scenes" / "sphere.toml"

LIGHTS = [
    {"type": "constant", "radiance": [0.4, 0.5, 0.6]},
    {"type": "directional", "direction": [-0.6, -1.0, -0.4], "irradiance": 4.0},
]


def small_scene(**parts):
    camera = volgrad.Camera((0.3, 0.5, 4.0), (0, 0, 0), fov_deg=40, width=24, height=24)
    args = dict(density_scale=4.0, albedo=0.8, phase_g=0.3, lights=LIGHTS, camera=camera)
    args.update(parts)
    return volgrad.Scene.from_parts(ball(), voxel_map(), **args)


def test_a_render_is_the_command_lines(cli, tmp_path):
    out = tmp_path / "sphere.exr"
    cli("render", SPHERE, "--spp", 4, "--seed", 3, "--output", out, "--quiet")
    image = volgrad.Scene.load(SPHERE).render(spp=4, seed=3)
    assert image.shape == (128, 128, 3) and image.dtype == np.float32
    np.testing.assert_array_equal(image, read_exr(out))


def test_a_gradient_is_the_command_lines(cli, tmp_path):
    target = tmp_path / "target.exr"
    cli("render", SPHERE, "--spp", 16, "--seed", 9, "--output", target, "--quiet")
    out = tmp_path / "g.vdb"
    cli("grad", SPHERE, "--loss", "l2", "--target", target, "--spp", 4, "--seed", 5, "--output", out, "--quiet")
    scene = volgrad.Scene.load(SPHERE)
    # The command line's adjoint: ∂/∂I of mean((I − T)²) over pixels and channels, from a render
    # with the gradient's seed and spp (on the forward stream; the gradient's paths are on the
    # adjoint stream).
    image = scene.render(spp=4, seed=5)
    adjoint = (np.float32(2) * (image - read_exr(target))) / np.float32(image.size)
    ours = scene.grad(adjoint, spp=4, seed=5)
    theirs, their_map = volgrad.read_grid(out)
    _, our_map = scene.density
    # The command line's grid also holds the ring of voxels around the density's box that
    # trilinear lookups reach; compare where both have values.
    shift = np.rint(np.linalg.inv(our_map) @ their_map @ [0, 0, 0, 1])[:3].astype(int)
    assert np.all(shift <= 0)
    lo = -shift
    window = theirs[lo[0] : lo[0] + ours.shape[0], lo[1] : lo[1] + ours.shape[1], lo[2] : lo[2] + ours.shape[2]]
    assert window.shape == ours.shape
    assert np.count_nonzero(ours) > 1000
    np.testing.assert_array_equal(ours, window)


def test_threads_do_not_change_a_bit():
    scene = small_scene()
    cameras = [scene.camera, volgrad.Camera((4, 0.5, 0), (0, 0, 0), width=24, height=24)]
    images = [scene.render(cameras, spp=8, seed=1, threads=t) for t in (1, 2)]
    np.testing.assert_array_equal(*images)
    adjoint = np.random.default_rng(0).normal(size=images[0].shape).astype(np.float32)
    grads = [scene.grad(adjoint, cameras, spp=4, seed=2, threads=t) for t in (1, 2)]
    np.testing.assert_array_equal(*grads)
    assert grads[0].shape == ball().shape


VIEW_STRIDE = 0x9E3779B97F4A7C15


def test_views_of_one_call_are_independent():
    scene = small_scene()
    two = scene.render([scene.camera, scene.camera], spp=2, seed=4)
    assert not np.array_equal(two[0], two[1])
    np.testing.assert_array_equal(two[0], scene.render(spp=2, seed=4))
    np.testing.assert_array_equal(two[1], scene.render(spp=2, seed=(4 + VIEW_STRIDE) % 2**64))


def test_consecutive_seeds_never_redraw_a_view():
    """A training loop passes the iteration as the seed and its batch's cameras as a list: a
    camera one place earlier in the next iteration's list must not draw the same paths (with
    view i at seed + i it did, and so did its gradient)."""
    scene = small_scene()
    cameras = [scene.camera] * 4
    first = scene.render(cameras, spp=2, seed=10)
    second = scene.render(cameras, spp=2, seed=11)
    for i in range(1, 4):
        assert not np.array_equal(first[i], second[i - 1])
    adjoint = np.ones((len(cameras),) + first.shape[1:], np.float32)
    g10 = scene.grad(adjoint[:2], cameras[:2], spp=2, seed=10)
    g11 = scene.grad(adjoint[:1], cameras[:1], spp=2, seed=11)
    g10_second = g10 - scene.grad(adjoint[:1], cameras[:1], spp=2, seed=10)
    assert not np.allclose(g10_second, g11)


def test_the_gradient_matches_finite_differences():
    """⟨grad, d⟩ for d = +x half of the ball (relative): against a central difference of the
    render with common random numbers, each the mean of four seeds, within 4 standard errors of
    their difference (one seed's spread is 6 % for the difference and 12 % for the gradient: a
    single pair is no test). This checks the binding (arrays, axes, weights), whose faults are
    gross, not the estimator, which the Rust tests resolve to a few percent: the margin is
    asserted below a third of the value, so that a factor of 2 or ½ fails. An array whose axes
    were swapped (x for z: the camera looks along z) gives another number, which the same margin
    rejects."""
    scene = small_scene()
    density, _ = scene.density
    weights = np.random.default_rng(3).uniform(0.5, 1.5, (24, 24, 3)).astype(np.float32)
    half = np.zeros_like(density)
    half[:8] = 1.0
    direction = half * density
    eps = 0.05

    def loss(values, seed):
        return float((weights * scene.render(spp=2048, seed=seed, density=values)).sum())

    def mean_se(samples):
        return np.mean(samples), np.std(samples, ddof=1) / np.sqrt(len(samples))

    seeds = range(11, 15)
    fd, fd_se = mean_se(
        [(loss(density + eps * direction, s) - loss(density - eps * direction, s)) / (2 * eps) for s in seeds]
    )
    grads = [scene.grad(weights, spp=512, seed=100 + s) for s in seeds]
    ours, ours_se = mean_se([float((g * direction).sum()) for g in grads])
    swapped, _ = mean_se([float((g.transpose(2, 1, 0) * direction).sum()) for g in grads])
    margin = 4 * np.hypot(fd_se, ours_se)
    print(f"finite differences {fd:.5g} ± {fd_se:.2g}, gradient {ours:.5g} ± {ours_se:.2g}, axes swapped {swapped:.5g}")
    assert margin < abs(fd) / 3, (fd, margin)
    assert abs(ours - fd) < margin, (ours, fd, margin)
    assert abs(swapped - fd) > margin, (swapped, fd, margin)


def test_the_scene_is_unchanged_by_a_density_argument():
    scene = small_scene()
    before = scene.render(spp=2, seed=1)
    other = scene.render(spp=2, seed=1, density=2 * scene.density[0])
    assert other.mean() != before.mean()
    np.testing.assert_array_equal(scene.render(spp=2, seed=1), before)
    scene.set_density(2 * scene.density[0])
    np.testing.assert_array_equal(scene.render(spp=2, seed=1), other)


def test_albedo_arrays_and_their_gradient():
    albedo = np.full(ball().shape + (3,), 0.8, np.float32)
    grid = small_scene(albedo=albedo)
    constant = small_scene(albedo=0.8)
    # A grid of 0.8 everywhere the ball is renders as the constant does (up to the lookups'
    # rounding).
    np.testing.assert_allclose(grid.render(spp=4, seed=1), constant.render(spp=4, seed=1), rtol=1e-4, atol=1e-6)
    adjoint = np.ones((24, 24, 3), np.float32)
    g = grid.grad(adjoint, parameter="albedo", spp=16, seed=2)
    assert g.shape[-1] == 3 and np.all(g.sum(axis=(0, 1, 2)) > 0)
    with pytest.raises(ValueError, match="albedo.*constant"):
        constant.grad(adjoint, parameter="albedo")


def test_an_emission_array_and_its_gradient():
    """The image is linear in the emission, so ⟨∂(w·image)/∂E, E⟩ = w · (image(E) − image(0)):
    the gradient's paths (the adjoint stream) against two renders' difference."""
    emission = (ball() > 0).astype(np.float32) * 0.5
    glowing = small_scene(emission=emission, emission_kind={"radiance": [1.0, 0.6, 0.2]})
    dark = small_scene(emission=np.zeros_like(emission), emission_kind={"radiance": [1.0, 0.6, 0.2]})
    weights = np.random.default_rng(5).uniform(0.5, 1.5, (24, 24, 3)).astype(np.float32)
    difference = float((weights * (glowing.render(spp=1024, seed=1) - dark.render(spp=1024, seed=1))).sum())
    g = glowing.grad(weights, parameter="emission", spp=256, seed=2)
    assert g.shape == emission.shape
    ours = float((g * emission).sum())
    assert difference > 0 and abs(ours - difference) < 0.05 * difference, (ours, difference)


def test_albedo_and_emission_arrays_stand_in_for_a_call():
    """`albedo=` and `emission=` render and differentiate the scene as if it had been built with
    them (the same bits), and leave it as it was."""
    rng = np.random.default_rng(6)
    first = rng.uniform(0.2, 0.9, ball().shape + (3,)).astype(np.float32)
    second = rng.uniform(0.2, 0.9, ball().shape + (3,)).astype(np.float32)
    kind = {"radiance": [1.0, 0.6, 0.2]}
    glow, other_glow = ((ball() > 0) * rng.uniform(0, 1, ball().shape)).astype(np.float32), ball() * 0.3
    scene = small_scene(albedo=first, emission=glow, emission_kind=kind)
    built = small_scene(albedo=second, emission=other_glow, emission_kind=kind)
    before = scene.render(spp=2, seed=1)
    arrays = dict(albedo=second, emission=other_glow)
    np.testing.assert_array_equal(scene.render(spp=2, seed=1, **arrays), built.render(spp=2, seed=1))
    adjoint = rng.normal(size=before.shape).astype(np.float32)
    for parameter in ("extinction", "albedo", "emission"):
        ours = scene.grad(adjoint, parameter=parameter, spp=2, seed=3, **arrays)
        np.testing.assert_array_equal(ours, built.grad(adjoint, parameter=parameter, spp=2, seed=3))
    np.testing.assert_array_equal(scene.render(spp=2, seed=1), before)


def bad_calls():
    scene = small_scene()
    density = scene.density[0]
    adjoint = np.zeros((24, 24, 3), np.float32)
    yield lambda: scene.render(spp=0), ValueError, "spp must be at least 1"
    yield lambda: scene.render(threads=0), ValueError, "threads must be at least 1"
    yield lambda: scene.render(threads=100_000), ValueError, "threads is at most 1024"
    # Each path's term finite, their sum beyond float32.
    yield lambda: scene.grad(np.full_like(adjoint, 3e38), estimator="drt"), ValueError, "overflowed float32"
    yield lambda: scene.render(cameras=[]), ValueError, "cameras: the list is empty"
    yield lambda: scene.render(density=density.astype(np.float64)), TypeError, "density must be a float32"
    yield lambda: scene.render(density=density[:4]), ValueError, "density has shape"
    yield lambda: scene.render(density=density[None]), ValueError, r"density must have 3 axes, .* \(got shape \(1, "
    yield lambda: scene.render(density=-density), ValueError, "density: .* negative"
    yield lambda: scene.render(density=density * np.nan), ValueError, "density: .* NaN"
    yield lambda: scene.grad(adjoint[:3]), ValueError, "adjoint has shape"
    yield lambda: scene.grad(np.full_like(adjoint, np.inf)), ValueError, "adjoint holds non-finite"
    yield lambda: scene.grad(adjoint, estimator="fast"), ValueError, "estimator must be"
    yield lambda: scene.grad(adjoint, parameter="emission"), ValueError, "no emission"
    yield lambda: volgrad.Camera((0, 0, 0), (0, 0, 0)), ValueError, "camera"
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), width=0), ValueError, "width"
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), fx=-1.0), ValueError, "focal length fx"
    # fy alone stands for both; the error names it, not fx.
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), fy=-5.0), ValueError, "focal length fy"
    yield lambda: small_scene(lights=[{"type": "sun"}]), ValueError, "sun"
    yield lambda: small_scene(lights=["x"]), ValueError, r"light\[0\] must be a table of keys \(a dict, from Python\)"
    yield lambda: small_scene(phase_g=1.5), ValueError, "phase_g"
    yield lambda: small_scene(phase_g=float("nan")), ValueError, "phase_g must be a finite number"
    yield lambda: small_scene(density_scale=float("inf")), ValueError, "density_scale must be a finite"
    yield lambda: small_scene(albedo=float("nan")), ValueError, "albedo and the lights: values must be finite"
    yield lambda: small_scene(lights=[{"type": "constant", "radiance": {1, 2}}]), TypeError, "lights: values must be numbers"
    yield lambda: small_scene(camera=None).render(), ValueError, "no camera of its own"
    yield lambda: small_scene(albedo=np.ones((2, 2, 2), np.float32)), ValueError, "albedo has shape"
    yield lambda: volgrad.Scene.load(REPO / "none.toml"), FileNotFoundError, "does not exist"
    # Items Python would turn into floats (True as 1.0, a complex number's real part).
    for dtype in (bool, np.complex128):
        yield lambda: small_scene().set_density(ball(), np.eye(4, dtype=dtype)), TypeError, "index_to_world must be a 4×4 matrix of real numbers"
    # A NUL would end the name or the path where the C++ side reads it.
    yield lambda: volgrad.write_grid(REPO / "no-such-folder" / "x.vdb", ball(), voxel_map(), name="a\0b"), ValueError, "grid name .* NUL"
    yield lambda: small_scene(lights=[{"type": "envmap", "file": str(REPO / "scenes" / "sky.exr") + "\0.png"}]), ValueError, "NUL"
    # What the file system says, from the C++ side too: OSError, not ValueError.
    yield lambda: volgrad.read_grid(REPO), OSError, "is a directory"
    # Read, but not text: its contents are wrong, not the file system.
    yield lambda: volgrad.Scene.load(REPO / "scenes" / "assets" / "smoke.vdb"), ValueError, "UTF-8"
    yield lambda: small_scene(emission=-ball()), ValueError, "emission: .* negative"
    yield lambda: small_scene(emission=ball()[:4]), ValueError, "emission has shape"
    yield lambda: small_scene(emission=ball(), emission_kind={"radiance": [1e30, 1, 1]}), ValueError, "at most"
    yield lambda: small_scene(emission=ball(), emission_kind={"colour": 1}), ValueError, "emission_kind: unknown key 'colour'"
    yield lambda: small_scene(emission=ball(), emission_kind={"vdb": "x"}), ValueError, "emission_kind: unknown key 'vdb'"
    yield lambda: small_scene(emission_kind={"radiance": 2.0}), ValueError, "give the array as emission="
    yield lambda: scene.render(density=density[:4]), ValueError, r"scene.set_density\(array, index_to_world\)"
    yield lambda: scene.render(albedo=np.full_like(density, 0.5)), ValueError, "albedo: the scene's albedo is a constant"
    yield lambda: scene.render(emission=density), ValueError, "emission: the scene's medium has no emission"
    yield lambda: small_scene(albedo=np.full_like(density, 0.5)).render(albedo=np.full_like(density, 2.0)), ValueError, "albedo: every value"
    yield lambda: scene.render(albedo=density[:3]), ValueError, "albedo"
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), fov_deg=30, fx=20.0), ValueError, "not both"
    # An orbit's cameras pass a listed camera's checks: 2³² − 1 of them asked for 300 GB (an abort),
    # a NaN centre or a distance lost beside the centre put cameras where they see nothing.
    yield lambda: volgrad.Camera.orbit(2**32 - 1, 4.0), ValueError, "count must be from 1 to 10000"
    yield lambda: volgrad.Camera.orbit(1, 4.0, centre=(float("nan"), 0, 0)), ValueError, "centre"
    yield lambda: volgrad.Camera.orbit(1, 1e-3, centre=(1e9, 1e9, 1e9)), ValueError, "distance is too small"
    # A masked array's data would be read whole, its mask ignored.
    masked = np.ma.masked_less(density, 0.5)
    yield lambda: scene.render(density=masked), TypeError, r"density is a masked array.*density.filled"
    yield lambda: volgrad.write_grid(REPO / "no-such-folder" / "x.vdb", masked, voxel_map()), TypeError, "array is a masked array"
    yield lambda: small_scene().set_density(ball(), np.ma.masked_equal(voxel_map(), 0.0)), TypeError, "index_to_world is a masked array"
    # Python's floats are f64: past f32's range a number would become 0 or inf without a word (a
    # density_scale of 1e-46, an empty medium).
    yield lambda: small_scene(density_scale=1e-46), ValueError, r"density_scale must be .* 32-bit float's range.*got 1e-46"
    yield lambda: small_scene(phase_g=1e300), ValueError, "phase_g must be"
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), fov_deg=1e-50), ValueError, r"fov_deg must be .*got 1e-50"
    # Within f32's range, but a focal length beyond it.
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), fov_deg=1e-44), ValueError, "fov_deg = .* is too narrow"
    yield lambda: volgrad.Camera((0, 0, 1), (0, 0, 0), cx=1e39), ValueError, "cx must be"
    yield lambda: volgrad.Camera.orbit(1, 1e40), ValueError, "distance must be"
    # Inside the light dicts and emission_kind too: a sun of 1e-300 would be dark.
    yield lambda: small_scene(lights=[{"type": "constant", "radiance": [1.0, 1e-300, 1.0]}]), ValueError, r"albedo and the lights: light\[0\].radiance\[1\] = 1e-300 is beyond"
    yield lambda: small_scene(emission=ball(), emission_kind={"radiance": 1e39}), ValueError, "emission_kind: radiance = 1e39 is beyond"
    # Seeds as volgrad.torch and volgrad.jax take them: whole numbers in [0, 2**64), not bools.
    seed_range = r"^seed must be a whole number in \[0, 2\*\*64\)"
    for seed in (-1, 2**64, 1.5, True):
        yield lambda seed=seed: scene.render(seed=seed), ValueError, seed_range
    yield lambda: scene.grad(adjoint, seed=-1), ValueError, seed_range
    yield lambda: small_scene(seed=2**64), ValueError, seed_range


@pytest.mark.skipif(sys.version_info < (3, 11), reason="exception notes are Python 3.11's")
def test_an_argument_of_another_python_type_is_named():
    """PyO3 converts the arguments: a str where a number goes is its TypeError, whose message names
    the type, and the note it adds (printed with the traceback) names the argument."""
    for call, name in [
        (lambda: volgrad.Camera.orbit(4, 5.0, width="a"), "width"),
        (lambda: small_scene().render(spp="8"), "spp"),
        (lambda: volgrad.Camera((0, 0, 1), 5), "target"),
    ]:
        with pytest.raises(TypeError) as raised:
            call()
        assert f"while processing '{name}'" in getattr(raised.value, "__notes__", []), raised.value


def test_numpy_values_stand_for_numbers_in_the_parts():
    lights = [
        {"type": "constant", "radiance": np.array([0.4, 0.5, 0.6], np.float32)},
        {"type": "directional", "direction": np.array([-0.6, -1.0, -0.4]), "irradiance": np.float64(4.0)},
    ]
    np.testing.assert_array_equal(small_scene(lights=lights).render(spp=2, seed=1), small_scene().render(spp=2, seed=1))
    # The albedo too: a numpy number or triple is the constant a Python one is.
    for albedo, same in [(np.float64(0.8), 0.8), (np.array([0.8, 0.5, 0.2], np.float32), [0.8, 0.5, 0.2])]:
        np.testing.assert_array_equal(small_scene(albedo=albedo).render(spp=2, seed=1), small_scene(albedo=same).render(spp=2, seed=1))
    # And a numpy integer is a seed.
    np.testing.assert_array_equal(small_scene().render(spp=2, seed=np.uint64(2**64 - 1)), small_scene().render(spp=2, seed=2**64 - 1))


def test_a_gradient_does_not_depend_on_the_units():
    """The gradient is summed in whole quanta (exact, so any thread count gives the same bits); the
    quantum follows the scene's units, so that grid values of 1e12 under a density_scale of
    4e-12, or lights 1e-10 as bright, give the gradient scaled (all zeros, from a quantum sized by
    the adjoint alone), and values of 1e-10 under 4e10 do not saturate it."""
    adjoint = np.ones((24, 24, 3), np.float32)
    expected = small_scene().grad(adjoint, spp=4, seed=1)
    assert np.abs(expected).max() > 0
    dim = [{**light, **{k: np.float32(v) * 1e-10 for k, v in light.items() if k in ("radiance", "irradiance")}} for light in LIGHTS]
    for scene, factor in [
        (small_scene(lights=dim), 1e-10),
        (volgrad.Scene.from_parts(ball() * np.float32(1e12), voxel_map(), density_scale=4e-12, albedo=0.8, phase_g=0.3, lights=LIGHTS, camera=small_scene().camera), 1e-12),
        (volgrad.Scene.from_parts(ball() * np.float32(1e-10), voxel_map(), density_scale=4e10, albedo=0.8, phase_g=0.3, lights=LIGHTS, camera=small_scene().camera), 1e10),
    ]:
        gradient = scene.grad(adjoint, spp=4, seed=1) / factor
        np.testing.assert_allclose(gradient.sum(), expected.sum(), rtol=1e-3)
        np.testing.assert_allclose(gradient, expected, rtol=1e-3, atol=1e-4 * np.abs(expected).max())


def test_a_hot_adjoint_pixel_on_the_sky_leaves_the_gradient_as_it_was():
    """An adjoint pixel 1e12 to 1e30 times the others where the camera sees only sky adds nothing,
    and the others keep their gradient bit for bit: it gets a quantum of its own. With one
    quantum sized for it, the others' gradient was exactly 0 from 1e10 on."""
    scene = small_scene()
    corner_only = np.zeros((24, 24, 3), np.float32)
    corner_only[0, 0] = 1.0
    assert not scene.grad(corner_only, spp=4, seed=1).any(), "the corner sees only sky"
    adjoint = np.ones((24, 24, 3), np.float32)
    adjoint[0, 0] = 0.0
    expected = scene.grad(adjoint, spp=4, seed=1)
    assert np.abs(expected).max() > 0
    for hot in [1e12, 1e20, 1e30]:
        adjoint[0, 0] = hot
        assert np.array_equal(scene.grad(adjoint, spp=4, seed=1), expected), hot


def test_an_emission_gradient_does_not_depend_on_the_units():
    """An emission grid's samples carry dLe/dv: with the radiance 1e-10 (or 1e10) as large, its
    gradient is the usual one scaled, not rounded to 0 (or stopped at a ceiling) by a quantum
    sized for other units."""
    adjoint = np.ones((24, 24, 3), np.float32)

    def gradient(radiance):
        scene = small_scene(emission=ball(), emission_kind={"radiance": [radiance, 0.6 * radiance, 0.2 * radiance]})
        return scene.grad(adjoint, parameter="emission", spp=4, seed=1)

    expected = gradient(1.0)
    assert np.abs(expected).max() > 0
    for factor in (1e-10, 1e10):
        scaled = gradient(factor) / factor
        np.testing.assert_allclose(scaled.sum(), expected.sum(), rtol=1e-3)
        np.testing.assert_allclose(scaled, expected, rtol=1e-3, atol=1e-4 * np.abs(expected).max())


def test_one_camera_gives_one_image():
    scene = small_scene()
    other = volgrad.Camera((4, 0.5, 0), (0, 0, 0), width=24, height=24)
    image = scene.render(other, spp=2, seed=3)
    assert image.shape == (24, 24, 3)
    np.testing.assert_array_equal(image, scene.render([other], spp=2, seed=3)[0])
    adjoint = np.random.default_rng(0).normal(size=image.shape).astype(np.float32)
    np.testing.assert_array_equal(scene.grad(adjoint, other, spp=2, seed=3), scene.grad(adjoint[None], [other], spp=2, seed=3))


def test_a_busy_scene_says_so():
    """A second call on a Scene while another thread's call runs is refused with a message that
    says what to do (PyO3's own says "Already borrowed")."""
    scene = small_scene()

    def long_render():
        while True:  # until this thread's call is the one that runs (not the main thread's)
            try:
                return scene.render(spp=3000, threads=1)
            except RuntimeError:
                time.sleep(0.001)

    thread = threading.Thread(target=long_render)
    thread.start()
    refused = {"render": [], "density": []}
    while thread.is_alive():
        for name, call in (("render", lambda: scene.render(spp=1)), ("density", lambda: scene.density)):
            try:
                call()
            except RuntimeError as e:
                refused[name].append(str(e))
        time.sleep(0.01)
    thread.join()
    for said in refused.values():
        assert said and "a Scene of its own" in said[0], refused


def test_bad_arguments_raise_by_name():
    for call, error, message in bad_calls():
        with pytest.raises(error, match=message):
            call()


def test_ctrl_c_interrupts_a_render_within_a_second():
    """SIGINT during a long render raises KeyboardInterrupt within a second, in the main thread's
    call and in another thread's (whose pixels the interrupt skipped too: no silent partial
    image)."""
    script = textwrap.dedent(
        f"""
        import signal, sys, threading, volgrad
        # Python turns SIGINT into KeyboardInterrupt only if it was not ignored when it started,
        # and a shell's background job starts with it ignored: restore it, as a terminal has it.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        camera = volgrad.Camera((0, 2, 12), (0, 0, 0), width=512, height=512)
        other = []
        started = threading.Event()

        def render_in_a_thread():
            try:
                scene = volgrad.Scene.load({str(SPHERE)!r})
                started.set()
                # A pool of its own: calls on rayon's global pool would queue behind each other.
                scene.render([camera], spp=100000, threads=1)
                other.append("finished")
            except KeyboardInterrupt:
                other.append("interrupted")

        thread = threading.Thread(target=render_in_a_thread)
        thread.start()
        scene = volgrad.Scene.load({str(SPHERE)!r})
        started.wait()  # both renders are under way (or about to be) when the signal comes
        print("rendering", flush=True)
        try:
            scene.render([camera], spp=100000)
        except KeyboardInterrupt:
            thread.join()
            print("interrupted", other[0], flush=True)
            sys.exit(3)
        """
    )
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([child.stdout], [], [], 60)
        assert ready and child.stdout.readline().strip() == "rendering"
    except AssertionError:
        child.kill()
        raise
    time.sleep(0.5)
    sent = time.monotonic()
    child.send_signal(signal.SIGINT)
    try:
        code = child.wait(timeout=10)
    finally:
        child.kill()
    elapsed = time.monotonic() - sent
    assert code == 3 and child.stdout.read().strip() == "interrupted interrupted"
    assert elapsed < 1.0, elapsed


def test_ctrl_c_that_ends_the_main_thread_stops_another_threads_call():
    """SIGINT while the main thread does other work (here: sleeps) ends it with KeyboardInterrupt;
    the interpreter then waits for its other threads, and a volgrad call in one of them raises
    KeyboardInterrupt within a second instead of running to its end (minutes here)."""
    script = textwrap.dedent(
        f"""
        import signal, threading, time, volgrad
        signal.signal(signal.SIGINT, signal.default_int_handler)
        camera = volgrad.Camera((0, 2, 12), (0, 0, 0), width=512, height=512)
        scene = volgrad.Scene.load({str(SPHERE)!r})
        started = threading.Event()

        def render_in_a_thread():
            try:
                started.set()
                scene.render([camera], spp=100000, threads=1)
                print("finished", flush=True)
            except KeyboardInterrupt:
                print("interrupted", flush=True)

        threading.Thread(target=render_in_a_thread).start()
        started.wait()
        print("rendering", flush=True)
        time.sleep(600)
        """
    )
    child = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        ready, _, _ = select.select([child.stdout], [], [], 60)
        assert ready and child.stdout.readline().strip() == "rendering"
        time.sleep(0.5)
        sent = time.monotonic()
        child.send_signal(signal.SIGINT)
        child.wait(timeout=10)
        elapsed = time.monotonic() - sent
    finally:
        child.kill()
    assert child.stdout.read().strip() == "interrupted"
    assert elapsed < 1.0, elapsed


def test_a_forked_child_renders():
    """A child forked after the parent rendered (multiprocessing's default on Linux, a
    DataLoader's workers) renders the same image instead of waiting forever on the parent's
    thread pool, whose threads it does not have. In a fresh interpreter: this one has other
    libraries' threads (JAX's), which a fork does not take either."""
    script = textwrap.dedent(
        f"""
        import os, sys, time
        import numpy as np
        import volgrad
        scene = volgrad.Scene.load({str(SPHERE)!r})
        # Large enough to be cut into several tasks: one alone would run on the calling thread.
        camera = volgrad.Camera((0, 2, 12), (0, 0, 0), width=64, height=64)
        image = scene.render([camera], spp=2, seed=1)
        pid = os.fork()
        if pid == 0:
            # The scene the parent loaded, and one loaded in the child (OpenVDB's reader and its
            # threads too).
            again = volgrad.Scene.load({str(SPHERE)!r})
            same = [np.array_equal(s.render([camera], spp=2, seed=1), image) for s in (scene, again)]
            os._exit(0 if all(same) else 1)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                print("child", os.waitstatus_to_exitcode(status))
                sys.exit(0)
            time.sleep(0.05)
        os.kill(pid, 9)
        print("child hung")
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "child 0", result.stdout + result.stderr
