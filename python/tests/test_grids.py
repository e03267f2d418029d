"""read_grid and write_grid: axis order, transforms, sparsity, what they refuse."""

import pathlib

import numpy as np
import pytest

import volgrad
from conftest import ball, voxel_map


def test_the_axis_order_is_x_y_z(cli, tmp_path):
    # make-grid's slab is size × size × thickness voxels: thin along z, the array's last axis.
    path = tmp_path / "slab.vdb"
    cli("make-grid", "slab", "--size", 12, "--thickness", 3, "--output", path)
    values, index_to_world = volgrad.read_grid(path)
    assert values.shape == (12, 12, 3)
    assert values.dtype == np.float32 and index_to_world.shape == (4, 4)
    assert np.all(values > 0)


def test_a_grid_comes_back_as_written(tmp_path):
    values = ball()
    index_to_world = voxel_map()
    path = tmp_path / "ball.vdb"
    volgrad.write_grid(path, values, index_to_world, name="density")
    back, back_map = volgrad.read_grid(path, name="density")
    # read_grid returns the active box: the ball's non-zero voxels, shifted by its first corner.
    nonzero = np.argwhere(values != 0)
    lo, hi = nonzero.min(axis=0), nonzero.max(axis=0)
    assert back.shape == tuple(hi - lo + 1)
    np.testing.assert_array_equal(back, values[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1])
    # The same voxel lands on the same world point either way.
    corner = np.append(lo, 1.0)
    np.testing.assert_allclose(back_map @ np.array([0, 0, 0, 1.0]), index_to_world @ corner, atol=1e-12)
    np.testing.assert_allclose(back_map[:3, :3], index_to_world[:3, :3])


def test_only_bricks_with_values_are_stored(tmp_path):
    sparse = np.zeros((64, 64, 64), np.float32)
    sparse[3, 5, 7] = 2.0
    sparse[60, 60, 60] = 1.0
    # Values OpenVDB cannot prune into tiles: 512 leaves stored.
    dense = np.random.default_rng(1).uniform(0.5, 1.0, (64, 64, 64)).astype(np.float32)
    for name, values in [("sparse", sparse), ("dense", dense)]:
        volgrad.write_grid(tmp_path / f"{name}.vdb", values, np.eye(4))
    small, large = ((tmp_path / f"{n}.vdb").stat().st_size for n in ["sparse", "dense"])
    assert small * 50 < large  # 2 bricks of 512 against 512 bricks


def test_an_existing_file_is_kept_unless_asked(tmp_path):
    path = tmp_path / "a.vdb"
    volgrad.write_grid(path, ball(), voxel_map())
    with pytest.raises(FileExistsError, match="already exists: pass overwrite=True"):
        volgrad.write_grid(path, ball() * 2, voxel_map())
    assert volgrad.read_grid(path)[0].max() == ball().max()
    volgrad.write_grid(path, ball() * 2, voxel_map(), overwrite=True)
    assert volgrad.read_grid(path)[0].max() == 2 * ball().max()
    # A link to a file not yet there is the user's too; a folder is refused as one, overwrite or not.
    link = tmp_path / "link.vdb"
    link.symlink_to(tmp_path / "elsewhere.vdb")
    with pytest.raises(FileExistsError, match="already exists"):
        volgrad.write_grid(link, ball(), voxel_map())
    assert link.is_symlink()
    with pytest.raises(IsADirectoryError, match="it is a folder"):
        volgrad.write_grid(tmp_path, ball(), voxel_map(), overwrite=True)


@pytest.mark.parametrize(
    "array, matrix, error, message",
    [
        (ball().astype(np.float64), voxel_map(), TypeError, "array must be a float32"),
        (ball()[0], voxel_map(), ValueError, r"array must have 3 axes, of shape \(nx, ny, nz\) \(got shape \(16, 16\)\)"),
        (np.full((4, 4, 4), np.nan, np.float32), voxel_map(), ValueError, "NaN"),
        (ball(), np.eye(3), ValueError, "4×4"),
        (ball(), np.zeros((4, 4)), ValueError, "last row"),
        (ball(), np.diag([1.0, 0.0, 1.0, 1.0]), ValueError, "singular"),
    ],
)
def test_bad_arrays_are_refused_by_name(tmp_path, array, matrix, error, message):
    with pytest.raises(error, match=message):
        volgrad.write_grid(tmp_path / "x.vdb", array, matrix)
    assert not (tmp_path / "x.vdb").exists()


def test_a_vdb_file_is_named_so(tmp_path):
    with pytest.raises(ValueError, match="ends in .vdb"):
        volgrad.write_grid(tmp_path / "x.txt", ball(), voxel_map())
    assert not (tmp_path / "x.txt").exists()


def test_values_beyond_half_floats_are_not_written_as_half(tmp_path):
    with pytest.raises(ValueError, match="beyond half floats"):
        volgrad.write_grid(tmp_path / "h.vdb", ball() * 1e6, voxel_map(), half=True)
    assert not (tmp_path / "h.vdb").exists()


def test_missing_files_raise_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        volgrad.read_grid(tmp_path / "none.vdb")
    path = tmp_path / "ball.vdb"
    volgrad.write_grid(path, ball(), voxel_map())
    with pytest.raises(ValueError, match="nope"):
        volgrad.read_grid(path, name="nope")


def test_a_sparse_grid_over_a_wide_box_is_refused_before_allocating():
    # Two voxels 100,000 apart on each axis (written by the library's brick map builder): a dense
    # array of their box would be 10^15 voxels.
    path = pathlib.Path(__file__).parent / "data" / "two-voxels-far-apart.vdb"
    with pytest.raises(ValueError, match="too large for a dense array"):
        volgrad.read_grid(path)


def test_a_path_with_a_nul_is_refused(tmp_path):
    """The system's calls would cut the path at the NUL: `b\0.vdb` would overwrite `b`, past
    the checks made on the whole string."""
    precious = tmp_path / "b"
    precious.write_text("the user's data")
    with pytest.raises(ValueError, match="NUL"):
        volgrad.write_grid(str(precious) + "\0.vdb", ball(), voxel_map())
    assert precious.read_text() == "the user's data"
    with pytest.raises(ValueError, match="NUL"):
        volgrad.read_grid(str(precious) + "\0.vdb")


def test_an_array_beyond_the_dense_limit_is_refused_before_it_is_scanned(tmp_path):
    """A broadcast view holds no memory whatever its shape: scanned, (20000,)*3 would take hours
    and its bricks' list more memory than the machine has."""
    huge = np.broadcast_to(np.float32(0.5), (20000, 20000, 20000))
    with pytest.raises(ValueError, match="more than volgrad takes"):
        volgrad.write_grid(tmp_path / "x.vdb", huge, voxel_map())


def test_an_array_too_thin_for_its_bricks_is_refused():
    """Within the voxel limit, a line of 2^26 voxels spans 2^23 bricks of 8³: 17 GiB of them,
    which aborted the process when the allocation failed. Refused by name, before any brick."""
    thin = np.broadcast_to(np.float32(1), (2**26, 1, 1))
    with pytest.raises(ValueError, match=r"^array: .* spans 8388608 bricks"):
        volgrad.write_grid("/tmp/never-written.vdb", thin, voxel_map())
    with pytest.raises(ValueError, match=r"^density: .* spans 8388608 bricks"):
        volgrad.Scene.from_parts(thin, voxel_map())
