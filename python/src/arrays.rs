//! Dense numpy arrays and volgrad's sparse grids. An array `a` of shape (nx, ny, nz) is the box of
//! voxels whose index-space corner is `origin`: a[i, j, k] is voxel origin + (i, j, k), the order
//! pyopenvdb's `copyToArray` uses (x slowest, z fastest; C order). A brick map's leaf stores its
//! 8³ voxels in that same order.

use anyhow::{bail, Result};
use glam::{DAffine3, IVec3};
use numpy::ndarray::{Array3, ArrayView3};
use rayon::prelude::*;
use volgrad::gradient::grid::GradientGrid;
use volgrad::volume::brickmap::{leaf_offset, BrickMap, Leaf, BRICK_VOXELS};
use volgrad::volume::transform::IndexTransform;

const BRICK: i32 = 8;

/// The most voxels of a dense array made from a sparse grid (2^30: 4 GiB of f32).
pub const MAX_DENSE_VOXELS: u64 = 1 << 30;

/// A box of voxels: its first voxel and its size per axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VoxelBox {
    pub origin: IVec3,
    pub shape: [usize; 3],
}

impl VoxelBox {
    pub const EMPTY: VoxelBox = VoxelBox {
        origin: IVec3::ZERO,
        shape: [0, 0, 0],
    };

    /// The bounding box of `grid`'s active voxels.
    pub fn active(grid: &BrickMap) -> Self {
        grid.active_bounds()
            .map_or(Self::EMPTY, |(lo, hi)| Self::spanning(lo, hi))
    }

    /// The inclusive box `[lo, hi]`.
    pub fn spanning(lo: IVec3, hi: IVec3) -> Self {
        // In i64: a box across the whole i32 range has more voxels per axis than i32 holds.
        let size = (hi.as_i64vec3() - lo.as_i64vec3() + 1).max(glam::I64Vec3::ZERO);
        VoxelBox {
            origin: lo,
            shape: [size.x as usize, size.y as usize, size.z as usize],
        }
    }

    /// Its voxel count, refused (naming `what`) above `MAX_DENSE_VOXELS` before anything is
    /// allocated: a sparse grid with two voxels far apart has a box of billions.
    pub fn checked_len(&self, what: &str) -> Result<usize> {
        let count = self.shape.iter().map(|&n| n as u128).product::<u128>();
        if count > u128::from(MAX_DENSE_VOXELS) {
            bail!(
                "{what}: its box of {} × {} × {} voxels is too large for a dense array (at most 2^30 = {MAX_DENSE_VOXELS} voxels, 4 GiB); the grid is sparse over a wide box",
                self.shape[0],
                self.shape[1],
                self.shape[2]
            );
        }
        Ok(count as usize)
    }

    /// The box at index 0 of an array of `shape`.
    pub fn of_array(shape: [usize; 3]) -> Self {
        VoxelBox {
            origin: IVec3::ZERO,
            shape,
        }
    }

    /// Its last voxel (inclusive).
    pub fn last(&self) -> IVec3 {
        self.origin
            + IVec3::new(
                self.shape[0] as i32,
                self.shape[1] as i32,
                self.shape[2] as i32,
            )
            - 1
    }

    pub fn is_empty(&self) -> bool {
        self.shape.contains(&0)
    }

    /// The offset of voxel `v` in the array, if it lies inside.
    fn offset(&self, v: IVec3) -> Option<usize> {
        let local = v - self.origin;
        let [nx, ny, nz] = self.shape.map(|n| n as i32);
        let inside = local.cmpge(IVec3::ZERO).all() && local.cmplt(IVec3::new(nx, ny, nz)).all();
        inside.then(|| {
            ((local.x as usize * self.shape[1]) + local.y as usize) * self.shape[2]
                + local.z as usize
        })
    }

    /// The map from array indices to world: the grid's `transform` after the shift to `origin`.
    pub fn array_to_world(&self, transform: &IndexTransform) -> DAffine3 {
        transform.index_to_world() * DAffine3::from_translation(self.origin.as_dvec3())
    }
}

/// A 4×4 row-major matrix (column vectors: world = M · [i, j, k, 1]) as an affine map; refused
/// unless its last row is [0, 0, 0, 1] and it is invertible and finite.
pub fn affine_from_rows(rows: &[f64; 16], argument: &str) -> Result<IndexTransform> {
    if rows[12..] != [0.0, 0.0, 0.0, 1.0] {
        bail!("{argument}: the last row of a 4×4 index-to-world matrix must be [0, 0, 0, 1] (got {:?})", &rows[12..]);
    }
    IndexTransform::from_rows(rows).map_err(|e| anyhow::anyhow!("{argument}: {e}"))
}

/// The rows of `map` as `affine_from_rows` reads them.
pub fn rows_of(map: DAffine3) -> [f64; 16] {
    IndexTransform::new(map)
        .map(|t| t.to_rows())
        .unwrap_or_else(|_| [f64::NAN; 16])
}

/// Refuses an array of densities (or other grid values) holding NaN, infinities or, unless
/// `signed`, negative values, naming `argument`.
pub fn check_values(values: &ArrayView3<f32>, argument: &str, signed: bool) -> Result<()> {
    // The dense arrays volgrad returns have the same bound: a larger one (a broadcast view of
    // a wide box holds no memory) would take hours to scan, and its bricks' list more memory
    // than the machine has.
    let (nx, ny, nz) = values.dim();
    if (nx as u128) * (ny as u128) * (nz as u128) > u128::from(MAX_DENSE_VOXELS) {
        bail!("{argument}: an array of {nx} × {ny} × {nz} voxels is more than volgrad takes (at most 2^30 = {MAX_DENSE_VOXELS} voxels, 4 GiB of float32)");
    }
    let (non_finite, negative) = values
        .as_slice()
        .map(|s| {
            s.par_iter()
                .fold(
                    || (0u64, 0u64),
                    |(n, m), v| (n + !v.is_finite() as u64, m + (*v < 0.0) as u64),
                )
                .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
        })
        .unwrap_or_else(|| {
            values.iter().fold((0, 0), |(n, m), v| {
                (n + !v.is_finite() as u64, m + (*v < 0.0) as u64)
            })
        });
    if non_finite > 0 {
        bail!("{argument}: {non_finite} values are NaN or infinite");
    }
    if negative > 0 && !signed {
        bail!("{argument}: {negative} values are negative (grid values must be ≥ 0)");
    }
    Ok(())
}

/// The most voxels the bricks of an array's box may hold: twice `MAX_DENSE_VOXELS`, so that
/// every array within that limit and at least a brick thick passes wherever its corner lies.
const MAX_BRICK_VOXELS: u64 = 2 * MAX_DENSE_VOXELS;

/// The voxels of `values` (placed at `origin`) as a brick map that stores only the 8³ bricks
/// holding a non-zero value; the non-zero voxels are active. Refused (naming `argument`) where
/// the bricks its box spans would hold more than `MAX_BRICK_VOXELS`: an array one voxel thin
/// takes 64 times its own memory as bricks, so the voxel limit alone does not bound it.
pub fn to_brickmap(values: &ArrayView3<f32>, origin: IVec3, argument: &str) -> Result<BrickMap> {
    let (nx, ny, nz) = values.dim();
    let place = VoxelBox {
        origin,
        shape: [nx, ny, nz],
    };
    if place.is_empty() {
        return Ok(BrickMap::new(Vec::new(), Vec::new()));
    }
    let (first, last): (IVec3, IVec3) = (origin >> 3i32, place.last() >> 3i32);
    let spanned = (last.as_i64vec3() - first.as_i64vec3() + 1).as_u64vec3();
    let brick_voxels = spanned.x * spanned.y * spanned.z * BRICK_VOXELS as u64;
    if brick_voxels > MAX_BRICK_VOXELS {
        bail!("{argument}: an array of {nx} × {ny} × {nz} voxels spans {} bricks of 8³ voxels, whose {brick_voxels} voxels are more than volgrad stores (at most 2^31); an array this thin takes far more memory as bricks than as an array", brick_voxels / BRICK_VOXELS as u64);
    }
    let bricks: Vec<IVec3> = (first.x..=last.x)
        .flat_map(|x| {
            (first.y..=last.y)
                .flat_map(move |y| (first.z..=last.z).map(move |z| IVec3::new(x, y, z)))
        })
        .collect();
    let leaves = bricks
        .par_iter()
        .filter_map(|&brick| {
            let mut leaf = Leaf {
                origin: brick * BRICK,
                values: [0.0; BRICK_VOXELS],
                active: [0; 8],
            };
            let mut any = false;
            for local in (0..BRICK_VOXELS as i32).map(|o| IVec3::new(o >> 6, (o >> 3) & 7, o & 7)) {
                let v = leaf.origin + local - origin;
                let inside = v.cmpge(IVec3::ZERO).all()
                    && (v.x as usize) < nx
                    && (v.y as usize) < ny
                    && (v.z as usize) < nz;
                let value = if inside {
                    values[[v.x as usize, v.y as usize, v.z as usize]]
                } else {
                    0.0
                };
                if value != 0.0 {
                    let o = leaf_offset(local);
                    leaf.values[o] = value;
                    leaf.active[o >> 6] |= 1 << (o & 63);
                    any = true;
                }
            }
            any.then_some(leaf)
        })
        .collect();
    Ok(BrickMap::new(leaves, Vec::new()))
}

/// The voxels of `grid` in `place`, dense; refused (naming `what`) when `place` is too large.
pub fn from_brickmap(grid: &BrickMap, place: VoxelBox, what: &str) -> Result<Array3<f32>> {
    place.checked_len(what)?;
    let [nx, ny, nz] = place.shape;
    let mut dense = Array3::<f32>::zeros((nx, ny, nz));
    if let Some(slice) = dense.as_slice_mut() {
        slice
            .par_chunks_mut((ny * nz).max(1))
            .enumerate()
            .for_each(|(i, plane)| {
                for (o, value) in plane.iter_mut().enumerate() {
                    let v = place.origin + IVec3::new(i as i32, (o / nz) as i32, (o % nz) as i32);
                    *value = grid.voxel(v);
                }
            });
    }
    Ok(dense)
}

/// The voxels of a gradient grid that lie in `place`, dense (0 where no path reached); refused
/// when `place` is too large.
pub fn gradient_in(gradient: &GradientGrid<f64>, place: VoxelBox) -> Result<Array3<f32>> {
    place.checked_len("the gradient")?;
    let mut dense = Array3::<f32>::zeros((place.shape[0], place.shape[1], place.shape[2]));
    if let Some(slice) = dense.as_slice_mut() {
        for (v, value) in gradient.voxels() {
            if let Some(o) = place.offset(v) {
                slice[o] = value as f32;
            }
        }
    }
    Ok(dense)
}

/// Argument `name` as a float32 array of `D`'s dimensions, or a `TypeError` that names it and says
/// what it got.
pub fn float32_argument<'py, D: numpy::ndarray::Dimension>(
    value: &pyo3::Bound<'py, pyo3::PyAny>,
    name: &str,
    shape: &str,
) -> pyo3::PyResult<numpy::PyReadonlyArray<'py, f32, D>> {
    use pyo3::types::{PyAnyMethods, PyTypeMethods};
    refuse_masked(value, name)?;
    value.extract().map_err(|_| {
        // A float32 array with the wrong number of axes has the right type and the wrong shape.
        let float32 = (value.getattr("dtype").and_then(|d| d.str())).is_ok_and(|d| d == "float32");
        let axes = value
            .getattr("ndim")
            .and_then(|n| n.extract::<usize>())
            .ok();
        if let (true, Some(want), Some(axes)) = (float32, D::NDIM, axes) {
            if want != axes {
                let got = value
                    .getattr("shape")
                    .map_or_else(|_| "?".into(), |s| s.to_string());
                return pyo3::exceptions::PyValueError::new_err(format!(
                    "{name} must have {want} axes, {shape} (got shape {got})"
                ));
            }
        }
        let got = match (value.getattr("dtype"), value.getattr("shape")) {
            (Ok(dtype), Ok(shape)) => format!("an array of {dtype} with shape {shape}"),
            _ => value
                .get_type()
                .name()
                .map_or_else(|_| "another type".into(), |n| n.to_string()),
        };
        pyo3::exceptions::PyTypeError::new_err(format!(
            "{name} must be a float32 numpy array {shape} (got {got})"
        ))
    })
}

/// Refuses a numpy masked array: its data would be read whole, the values under its mask with
/// the rest, and the mask ignored without a word.
fn refuse_masked(value: &pyo3::Bound<'_, pyo3::PyAny>, name: &str) -> pyo3::PyResult<()> {
    use pyo3::types::PyAnyMethods;
    let masked = value.py().import("numpy.ma")?.getattr("MaskedArray")?;
    if value.is_instance(&masked)? {
        return Err(pyo3::exceptions::PyTypeError::new_err(format!(
            "{name} is a masked array, whose mask volgrad would ignore: give `{name}.filled(x)`, x the value the masked entries stand for"
        )));
    }
    Ok(())
}

/// A 4×4 index-to-world matrix given as nested sequences (a numpy array of any float type, or
/// lists), as an affine map.
pub fn matrix_argument(
    value: &pyo3::Bound<'_, pyo3::PyAny>,
    name: &str,
) -> pyo3::PyResult<IndexTransform> {
    use pyo3::types::PyAnyMethods;
    refuse_masked(value, name)?;
    // Python converts a bool or a complex array's items to floats (1.0; the real part, with only a
    // warning): an array says what its items are.
    if value.hasattr("dtype")? {
        let dtype = value.getattr("dtype")?;
        let kind: String = dtype.getattr("kind")?.extract()?;
        if !matches!(kind.as_str(), "f" | "i" | "u") {
            return Err(pyo3::exceptions::PyTypeError::new_err(format!(
                "{name} must be a 4×4 matrix of real numbers (got an array of {})",
                dtype.str()?
            )));
        }
    }
    let rows: Vec<Vec<f64>> = value.extract().map_err(|_| {
        pyo3::exceptions::PyTypeError::new_err(format!("{name} must be a 4×4 matrix of numbers"))
    })?;
    if rows.len() != 4 || rows.iter().any(|r| r.len() != 4) {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "{name} must be a 4×4 matrix (got {} rows of {:?} values)",
            rows.len(),
            rows.iter().map(Vec::len).collect::<Vec<_>>()
        )));
    }
    let flat: Vec<f64> = rows.concat();
    let flat: [f64; 16] = flat.try_into().expect("4 rows of 4");
    affine_from_rows(&flat, name).map_err(crate::errors::to_py)
}
