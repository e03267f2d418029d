"""Shared fixtures: the repository, the `volgrad` command line built beside the package, and small
scenes written into a temporary folder."""

import os
import pathlib
import subprocess

import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def cli():
    """Runs the command line (target/release/volgrad, or $VOLGRAD) and returns its stderr."""
    exe = os.environ.get("VOLGRAD", str(REPO / "target" / "release" / "volgrad"))
    if not pathlib.Path(exe).exists():
        pytest.fail(f"{exe} not found: build the command line first (cargo build --release)")

    def run(*args):
        done = subprocess.run([exe, *map(str, args)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stderr

    return run


def read_exr(path):
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        rgb = f.channels()["RGB"].pixels
    return np.asarray(rgb, dtype=np.float32)


def ball(n=16, radius=0.4):
    """A lopsided ball of n³ voxels: denser towards +x, so that no axis swap leaves it unchanged."""
    i = (np.arange(n, dtype=np.float32) + 0.5) / n - 0.5
    x, y, z = np.meshgrid(i, i, i, indexing="ij")
    inside = (x * x + y * y + z * z) < radius * radius
    return np.where(inside, 1.0 + 2.0 * (x + 0.5), 0.0).astype(np.float32)


def voxel_map(n=16, size=2.0):
    """index_to_world putting an n³ array's voxels in a cube of edge `size` centred on the origin."""
    edge = size / n
    m = np.diag([edge, edge, edge, 1.0])
    m[:3, 3] = -size / 2 + edge / 2
    return m
