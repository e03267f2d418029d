"""read_picture: pictures from elsewhere decoded to linear radiance and alpha, as `optimize` reads
a view set's pictures."""

import subprocess
import sys

import numpy as np
import pytest

import volgrad
from conftest import REPO

PLUME = REPO / "scenes" / "capture" / "plume"


def test_an_srgb_png_with_alpha_is_the_linear_exr_of_the_same_render():
    # Cycles saved each picture of the worked example twice from the same samples: an 8-bit sRGB
    # PNG with straight alpha, and a linear half-float EXR, premultiplied. Read as linear, the PNG
    # would be 1.5 times too bright here; left straight, too bright where alpha is partial.
    png, png_alpha = volgrad.read_picture(PLUME / "test" / "r_000.png")
    exr, exr_alpha = volgrad.read_picture(PLUME / "exr" / "test" / "r_000.exr")
    assert png.shape == exr.shape == (96, 96, 3) and png.dtype == np.float32
    assert png_alpha.shape == exr_alpha.shape == (96, 96) and png_alpha.dtype == np.float32
    assert np.abs(png_alpha - exr_alpha).max() <= 0.6 / 255  # half an 8-bit step
    ratio = png.sum(axis=(0, 1)) / exr.sum(axis=(0, 1))
    assert np.all(np.abs(ratio - 1) < 0.005), ratio
    assert np.abs(png - exr).max() < 0.01  # 8-bit steps of values up to 0.8


def test_an_exr_is_read_as_stored():
    import OpenEXR

    path = PLUME / "exr" / "test" / "r_000.exr"
    colour, alpha = volgrad.read_picture(path)
    with OpenEXR.File(str(path)) as f:
        stored = np.asarray(f.channels()["RGBA"].pixels, dtype=np.float32)
    np.testing.assert_array_equal(colour, stored[..., :3])
    np.testing.assert_array_equal(alpha, stored[..., 3])


def test_color_space_overrides_the_decoding():
    path = PLUME / "test" / "r_000.png"
    default, _ = volgrad.read_picture(path)
    srgb, _ = volgrad.read_picture(path, color_space="srgb")
    linear, _ = volgrad.read_picture(path, color_space="linear")
    np.testing.assert_array_equal(srgb, default)
    assert linear.mean() > 1.3 * default.mean()
    with pytest.raises(ValueError, match='"linear" or "srgb"'):
        volgrad.read_picture(path, color_space="rec709")


def test_a_picture_without_alpha_and_unreadable_files(cli, tmp_path):
    exr = tmp_path / "ball.exr"
    cli("render", REPO / "scenes" / "sphere.toml", "--spp", 4, "--output", exr)
    colour, alpha = volgrad.read_picture(tmp_path / "ball.png")  # written beside the EXR, 8-bit sRGB
    assert alpha is None
    linear, _ = volgrad.read_picture(exr)
    inside = linear < 1  # the PNG clips above 1
    assert np.abs(colour - linear)[inside].max() < 0.01
    with pytest.raises(FileNotFoundError, match="does not exist"):
        volgrad.read_picture(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="cannot read image"):
        volgrad.read_picture(REPO / "scenes" / "sphere.toml")


def test_the_pytorch_and_jax_modules_after_a_plain_import():
    # In a fresh interpreter: here another test may have imported them already, which would make
    # them the package's attributes whatever `volgrad.__getattr__` does.
    script = """
import sys, volgrad
assert "torch" not in sys.modules and "jax" not in sys.modules, "import volgrad imported them"
assert callable(volgrad.torch.render)
assert callable(volgrad.jax.renderer)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    with pytest.raises(AttributeError, match="no attribute 'tourch'"):
        volgrad.tourch
