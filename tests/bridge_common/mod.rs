//! What the bridge's tests share: the bundled assets, the grids' plain data taken apart
//! (leaves, tiles, metadata), and error text.
#![allow(dead_code)] // not every test file uses every helper

use std::collections::BTreeMap;
use std::path::Path;

use exr::prelude::f16;
use volgrad::io::bridge::ffi::{self, FloatGridData, GridSummary, ImageData, LeafData, MetaEntry};

pub fn asset(name: &str) -> String {
    format!("{}/scenes/assets/{}", env!("CARGO_MANIFEST_DIR"), name)
}

pub fn path_str(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

pub fn list(name: &str) -> Vec<GridSummary> {
    ffi::list_grids(&asset(name)).unwrap_or_else(|e| panic!("list_grids({name}): {e}"))
}

pub fn only_grid(name: &str) -> GridSummary {
    let mut grids = list(name);
    assert_eq!(grids.len(), 1, "{name} should hold one grid");
    grids.remove(0)
}

pub fn meta<'a>(entries: &'a [MetaEntry], name: &str) -> Option<&'a MetaEntry> {
    entries.iter().find(|e| e.name == name)
}

pub fn err_text<T>(r: Result<T, cxx::Exception>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.what().to_string(),
    }
}

/// Active voxels of a grid copy: set mask bits plus the voxels of every active tile.
pub fn active_voxels(g: &FloatGridData) -> u64 {
    let in_leaves: u64 = (g.leaves.iter().flat_map(|leaf| leaf.active))
        .map(|w| u64::from(w.count_ones()))
        .sum();
    let in_tiles: u64 = g.tile_sizes.iter().map(|&s| u64::from(s).pow(3)).sum();
    in_leaves + in_tiles
}

pub fn assert_close(a: f64, b: f64, tol: f64, what: &str) {
    assert!((a - b).abs() <= tol, "{what}: {a} vs {b} (tolerance {tol})");
}

/// Applies a column-vector, row-major 4x4 affine map to a point.
pub fn apply(m: &[f64; 16], p: [f64; 3]) -> [f64; 3] {
    let mut w = [0.0; 3];
    for (i, wi) in w.iter_mut().enumerate() {
        *wi = m[4 * i] * p[0] + m[4 * i + 1] * p[1] + m[4 * i + 2] * p[2] + m[4 * i + 3];
    }
    w
}

/// Leaves keyed by origin: (values, mask).
pub type LeafMap = BTreeMap<[i32; 3], (Vec<f32>, Vec<u64>)>;

pub fn leaves(g: &FloatGridData) -> LeafMap {
    (g.leaves.iter())
        .map(|leaf| (leaf.origin, (leaf.values.to_vec(), leaf.active.to_vec())))
        .collect()
}

/// Every leaf as (origin, mask, value bits): equal exactly when the leaves are bit for bit.
pub fn leaf_bits(g: &FloatGridData) -> Vec<([i32; 3], [u64; 8], Vec<u32>)> {
    (g.leaves.iter())
        .map(|leaf| {
            (
                leaf.origin,
                leaf.active,
                leaf.values.map(f32::to_bits).to_vec(),
            )
        })
        .collect()
}

/// Every leaf value, leaf after leaf.
pub fn values(g: &FloatGridData) -> impl Iterator<Item = f32> + '_ {
    g.leaves.iter().flat_map(|leaf| leaf.values)
}

/// Active tiles keyed by origin: (edge, value bits).
pub fn tiles(g: &FloatGridData) -> BTreeMap<[i32; 3], (u32, u32)> {
    let n = g.tile_values.len();
    assert_eq!(g.tile_origins.len(), 3 * n);
    assert_eq!(g.tile_sizes.len(), n);
    (0..n)
        .map(|i| {
            let o = [
                g.tile_origins[3 * i],
                g.tile_origins[3 * i + 1],
                g.tile_origins[3 * i + 2],
            ];
            (o, (g.tile_sizes[i], g.tile_values[i].to_bits()))
        })
        .collect()
}

/// Metadata that write_float_grids writes back (it skips what OpenVDB or the fields manage).
pub fn user_meta(entries: &[MetaEntry]) -> Vec<MetaEntry> {
    entries
        .iter()
        .filter(|e| {
            !e.name.starts_with("file_")
                && e.name != "is_saved_as_half_float"
                && e.name != "name"
                && e.name != "class"
        })
        .cloned()
        .collect()
}

pub fn half(v: f32) -> f32 {
    f16::from_f32(v).to_f32()
}

pub fn read_cloud() -> FloatGridData {
    ffi::read_float_grid(&asset("wdas_cloud_sixteenth.vdb"), "density", -1, false, 2).unwrap()
}

/// Two non-constant leaves, a 128-voxel tile, a rotated and scaled transform, typed metadata.
pub fn hand_built() -> FloatGridData {
    let (s, c) = (30f64.to_radians().sin(), 30f64.to_radians().cos());
    let k = 0.5;
    let index_to_world = [
        k * c,
        -k * s,
        0.0,
        1.0, //
        k * s,
        k * c,
        0.0,
        2.0, //
        0.0,
        0.0,
        k,
        3.0, //
        0.0,
        0.0,
        0.0,
        1.0,
    ];
    let leaf = |l: usize, origin: [i32; 3], active: [u64; 8]| LeafData {
        origin,
        values: std::array::from_fn(|i| l as f32 + i as f32 / 512.0),
        active,
    };
    let leaves = vec![
        leaf(
            0,
            [0, 0, 0],
            [
                u64::MAX,
                0x0123_4567_89ab_cdef,
                0,
                1,
                1 << 63,
                0xffff_0000_ffff_0000,
                42,
                u64::MAX - 1,
            ],
        ),
        leaf(1, [-8, 16, 24], [0xdead_beef, 0, 0, 0, 0, 0, 0, u64::MAX]),
    ];
    let entry = |name: &str, type_name: &str, value: &str| MetaEntry {
        name: name.into(),
        type_name: type_name.into(),
        value: value.into(),
    };
    FloatGridData {
        name: "hand".into(),
        grid_class: "fog volume".into(),
        index_to_world,
        background: 0.0,
        saved_as_half: false,
        leaves,
        tile_origins: vec![128, -128, 256],
        tile_sizes: vec![128],
        tile_values: vec![0.75],
        inactive_tiles_off_background: 0,
        metadata: vec![
            entry("author", "string", "volgrad test, with spaces"),
            entry("sigma", "float", "0.1"),
            entry("samples", "int", "64"),
            entry("seed", "int64", "12345678901"),
            entry("ratio", "double", "0.3333333333333333"),
            entry("flag", "bool", "true"),
            entry("offset", "vec3i", "[1, -2, 3]"),
            // Managed by OpenVDB or the fields: skipped on write.
            entry("file_voxel_count", "int64", "999"),
            entry("name", "string", "ignored"),
        ],
    }
}

/// An image of `channels` interleaved values per pixel from a fixed sequence: in [0, 1) with
/// `unit`, else spread over [−2.25, 5.25).
pub fn test_image(width: u32, height: u32, channels: u32, unit: bool) -> ImageData {
    let pixels = (0..width * height * channels)
        .map(|i| {
            let v = (i as f32 * 0.618_034).fract();
            if unit {
                v
            } else {
                (v - 0.3) * 7.5
            }
        })
        .collect();
    ImageData {
        width,
        height,
        channels,
        pixels,
        color_space: String::new(),
        stored_type: String::new(),
        alpha_channel: -1,
        alpha_unassociated: false,
        channel_names: Vec::new(),
        chromaticities: Vec::new(),
    }
}
