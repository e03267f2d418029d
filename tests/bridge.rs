//! Integration tests of the C++ bridge (`cpp/`) through `volgrad::io::bridge::ffi`: the facts
//! of the bundled OpenVDB assets, float-grid round trips, error messages, and images checked with
//! independent pure-Rust decoders (`exr`, `image`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use exr::prelude::f16;
use volgrad::io::bridge::ffi::{self, FloatGridData, GridSummary, ImageData, LeafData, MetaEntry};

fn asset(name: &str) -> String {
    format!("{}/scenes/assets/{}", env!("CARGO_MANIFEST_DIR"), name)
}

fn path_str(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

fn list(name: &str) -> Vec<GridSummary> {
    ffi::list_grids(&asset(name)).unwrap_or_else(|e| panic!("list_grids({name}): {e}"))
}

fn only_grid(name: &str) -> GridSummary {
    let mut grids = list(name);
    assert_eq!(grids.len(), 1, "{name} should hold one grid");
    grids.remove(0)
}

fn meta<'a>(entries: &'a [MetaEntry], name: &str) -> Option<&'a MetaEntry> {
    entries.iter().find(|e| e.name == name)
}

fn err_text<T>(r: Result<T, cxx::Exception>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.what().to_string(),
    }
}

/// Active voxels of a grid copy: set mask bits plus the voxels of every active tile.
fn active_voxels(g: &FloatGridData) -> u64 {
    let in_leaves: u64 = (g.leaves.iter().flat_map(|leaf| leaf.active))
        .map(|w| u64::from(w.count_ones()))
        .sum();
    let in_tiles: u64 = g.tile_sizes.iter().map(|&s| u64::from(s).pow(3)).sum();
    in_leaves + in_tiles
}

fn assert_close(a: f64, b: f64, tol: f64, what: &str) {
    assert!((a - b).abs() <= tol, "{what}: {a} vs {b} (tolerance {tol})");
}

/// Applies a column-vector, row-major 4x4 affine map to a point.
fn apply(m: &[f64; 16], p: [f64; 3]) -> [f64; 3] {
    let mut w = [0.0; 3];
    for (i, wi) in w.iter_mut().enumerate() {
        *wi = m[4 * i] * p[0] + m[4 * i + 1] * p[1] + m[4 * i + 2] * p[2] + m[4 * i + 3];
    }
    w
}

/// Leaves keyed by origin: (values, mask).
type LeafMap = BTreeMap<[i32; 3], (Vec<f32>, Vec<u64>)>;

fn leaves(g: &FloatGridData) -> LeafMap {
    (g.leaves.iter())
        .map(|leaf| (leaf.origin, (leaf.values.to_vec(), leaf.active.to_vec())))
        .collect()
}

/// Every leaf as (origin, mask, value bits): equal exactly when the leaves are bit for bit.
fn leaf_bits(g: &FloatGridData) -> Vec<([i32; 3], [u64; 8], Vec<u32>)> {
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
fn values(g: &FloatGridData) -> impl Iterator<Item = f32> + '_ {
    g.leaves.iter().flat_map(|leaf| leaf.values)
}

/// Active tiles keyed by origin: (edge, value bits).
fn tiles(g: &FloatGridData) -> BTreeMap<[i32; 3], (u32, u32)> {
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
fn user_meta(entries: &[MetaEntry]) -> Vec<MetaEntry> {
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

fn half(v: f32) -> f32 {
    f16::from_f32(v).to_f32()
}

fn read_cloud() -> FloatGridData {
    ffi::read_float_grid(&asset("wdas_cloud_sixteenth.vdb"), "density", -1, false, 2).unwrap()
}

// ------------------------------------------------------------------------------------------------
// list_grids: facts of the bundled assets

#[test]
fn list_cloud_facts() {
    let g = only_grid("wdas_cloud_sixteenth.vdb");
    assert_eq!(g.name, "density");
    assert_eq!(g.value_type, "float");
    assert_eq!(g.grid_class, "fog volume");
    assert_eq!(g.active_voxels, 415_642);
    assert_eq!(g.active_tiles, 130);
    assert_eq!(g.leaf_count, 1241);
    assert_eq!(g.index_min, [-66, -21, -90]);
    assert_eq!(g.index_max, [59, 64, 63]);
    assert!(g.linear && g.axis_aligned && !g.saved_as_half);
    let vs = g.voxel_size[0];
    assert_close(vs, 10.0 / 3.0, 1e-6, "voxel size");
    assert_eq!(g.voxel_size, [vs; 3]);
    assert_eq!(
        g.index_to_world,
        [vs, 0.0, 0.0, 0.0, 0.0, vs, 0.0, 0.0, 0.0, 0.0, vs, 0.0, 0.0, 0.0, 0.0, 1.0]
    );
    // World box: the index box grown by half a voxel, scaled (no translation).
    for i in 0..3 {
        assert_close(
            g.world_min[i],
            (g.index_min[i] as f64 - 0.5) * vs,
            1e-9,
            "world_min",
        );
        assert_close(
            g.world_max[i],
            (g.index_max[i] as f64 + 0.5) * vs,
            1e-9,
            "world_max",
        );
    }
    let class = meta(&g.metadata, "class").expect("class metadata");
    assert_eq!(
        (class.type_name.as_str(), class.value.as_str()),
        ("string", "fog volume")
    );
    let count = meta(&g.metadata, "file_voxel_count").expect("file_voxel_count");
    assert_eq!(
        (count.type_name.as_str(), count.value.as_str()),
        ("int64", "415642")
    );
    let bmin = meta(&g.metadata, "file_bbox_min").expect("file_bbox_min");
    assert_eq!(
        (bmin.type_name.as_str(), bmin.value.as_str()),
        ("vec3i", "[-66, -21, -90]")
    );
    let creator = meta(&g.metadata, "creator").expect("creator");
    assert!(creator.value.starts_with("Houdini"), "{creator:?}");
}

#[test]
fn list_smoke_is_half_with_translation() {
    let g = only_grid("smoke.vdb");
    assert_eq!(g.name, "density");
    assert!(g.saved_as_half);
    assert_eq!(g.active_voxels, 1_049_275);
    assert_eq!(g.index_min, [1, 2, 1]);
    assert_eq!(g.index_max, [111, 223, 112]);
    // Column-vector convention: the translation is the last column.
    let m = &g.index_to_world;
    assert_close(m[0], 10.0 / 21.0, 1e-9, "scale");
    assert_close(m[3], -34.047_619_047_619, 1e-6, "tx");
    assert_close(m[7], -13.095_238_095_238, 1e-6, "ty");
    assert!(m[12..15].iter().all(|&v| v == 0.0) && m[15] == 1.0);
    let p = apply(m, [1.0 - 0.5, 2.0 - 0.5, 1.0 - 0.5]);
    for (lo, pi) in g.world_min.iter().zip(p) {
        assert_close(*lo, pi, 1e-9, "world_min");
    }
    let roi = meta(&g.metadata, "roiMax").expect("roiMax");
    assert_eq!(
        (roi.type_name.as_str(), roi.value.as_str()),
        ("vec3i", "[112, 224, 113]")
    );
    let half_flag = meta(&g.metadata, "is_saved_as_half_float").expect("half flag");
    assert_eq!(half_flag.value, "true");
}

#[test]
fn list_torus_and_tiny_sphere() {
    let t = only_grid("torus01.vdb");
    assert_eq!(t.name, "voxel_fog_density");
    assert_eq!(t.active_voxels, 2450);
    assert_eq!((t.index_min, t.index_max), ([-25, -4, 1], [-4, 4, 22]));
    let idx = meta(&t.metadata, "_bifrost_volume_index").expect("bifrost index");
    assert_eq!(idx.value, "0");

    let s = only_grid("tiny_sphere.vdb");
    assert_eq!(s.active_voxels, 465);
    assert_eq!(s.leaf_count, 8);
    assert_eq!(s.active_tiles, 0);
    // Translation (0, 2, 0) sits in the last column, not the last row.
    assert_eq!(s.index_to_world[7], 2.0);
    assert_eq!(s.index_to_world[13], 0.0);
    assert_close(s.voxel_size[1], 0.2, 1e-6, "voxel size");
}

#[test]
fn list_dragon_is_rotated() {
    let g = only_grid("dragon_with_xform.vdb");
    assert!(g.linear);
    assert!(!g.axis_aligned, "a rotated transform is not axis-aligned");
    assert_eq!(g.active_voxels, 156_161);
    assert_eq!(g.active_tiles, 20);
    let m = &g.index_to_world;
    // vdb_print shows OpenVDB's row-vector matrix; its first ROW is our first COLUMN.
    assert_close(m[0], 0.0795, 5e-4, "m00");
    assert_close(m[4], 0.0742, 5e-4, "m10");
    assert_close(m[8], -0.0507, 5e-4, "m20");
    assert_close(m[1], -0.0548, 5e-4, "m01");
    assert_close(m[3], -0.2, 1e-6, "tx");
    assert_close(m[7], 0.2, 1e-6, "ty");
    assert_close(m[11], -0.2, 1e-6, "tz");
    // Rotation + uniform scale: every column has the voxel size as its length.
    for j in 0..3 {
        let len = (m[j] * m[j] + m[4 + j] * m[4 + j] + m[8 + j] * m[8 + j]).sqrt();
        assert_close(len, g.voxel_size[j], 1e-9, "column length");
        assert_close(len, 0.12, 1e-3, "voxel size");
    }
    // The world box holds every corner of the grown index box.
    for c in 0..8 {
        let pick = |bit: usize, i: usize| {
            if c & bit != 0 {
                g.index_max[i] as f64 + 0.5
            } else {
                g.index_min[i] as f64 - 0.5
            }
        };
        let w = apply(m, [pick(1, 0), pick(2, 1), pick(4, 2)]);
        for (i, wi) in w.iter().enumerate() {
            assert!(*wi >= g.world_min[i] - 1e-9 && *wi <= g.world_max[i] + 1e-9);
        }
    }
}

#[test]
fn list_grids_vdb_keeps_repeated_names_in_file_order() {
    let grids = list("grids.vdb");
    let names: Vec<&str> = grids.iter().map(|g| g.name.as_str()).collect();
    assert_eq!(names, ["density", "density", "density"]);
    let counts: Vec<u64> = grids.iter().map(|g| g.active_voxels).collect();
    assert_eq!(counts, [491, 2222, 803]);
}

#[test]
fn list_points_reports_non_float_grid() {
    let g = only_grid("points.vdb");
    assert_eq!(g.name, "points");
    assert_eq!(g.value_type, "ptdataidx32");
    assert_eq!(g.active_voxels, 5);
    assert_eq!(g.leaf_count, 4);
    assert_eq!((g.index_min, g.index_max), ([-1, -1, -1], [0, 1, 1]));
}

// ------------------------------------------------------------------------------------------------
// read_float_grid

#[test]
fn the_parallel_leaf_copy_is_the_same_at_any_thread_count() {
    let path = asset("wdas_cloud_sixteenth.vdb");
    let one = ffi::read_float_grid(&path, "density", -1, false, 1).unwrap();
    let two = read_cloud();
    let zero = ffi::read_float_grid(&path, "density", -1, false, 0).unwrap();
    for g in [&two, &zero] {
        assert_eq!(leaf_bits(g), leaf_bits(&one));
    }
}

/// Both readers' copies of grid `index` of `path`, which must agree field for field (leaves bit
/// for bit), or both fail with the same message.
fn assert_readers_agree(path: &str, index: i32) {
    let what = format!("grid {index} of {path}");
    let parallel = ffi::read_float_grid(path, "", index, false, 2);
    let reference = ffi::read_float_grid_through_openvdb(path, "", index, false, 2);
    let (parallel, reference) = match (parallel, reference) {
        (Ok(p), Ok(r)) => (p, r),
        (Err(p), Err(r)) => return assert_eq!(p.what(), r.what(), "{what}"),
        (p, r) => panic!("{what}: one reader failed: {:?} / {:?}", p.err(), r.err()),
    };
    assert_eq!(leaf_bits(&parallel), leaf_bits(&reference), "{what}");
    assert_eq!(tiles(&parallel), tiles(&reference), "{what}");
    assert_eq!(
        (&parallel.name, &parallel.grid_class, parallel.saved_as_half),
        (
            &reference.name,
            &reference.grid_class,
            reference.saved_as_half
        ),
        "{what}"
    );
    assert_eq!(parallel.index_to_world, reference.index_to_world, "{what}");
    assert_eq!(
        parallel.background.to_bits(),
        reference.background.to_bits(),
        "{what}"
    );
    assert_eq!(
        parallel.inactive_tiles_off_background, reference.inactive_tiles_off_background,
        "{what}"
    );
    assert_eq!(parallel.metadata, reference.metadata, "{what}");
}

#[test]
fn the_parallel_decoder_reads_every_asset_as_openvdb_does() {
    // Stored raw (the cloud), zip-compressed as half floats in format 222 (the smoke), with
    // blosc and active-value compression, several grids in one file, and a point grid (refused
    // alike by both).
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/assets");
    let mut files = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "vdb") {
            let p = path.to_str().unwrap();
            for index in 0..ffi::list_grid_names(p).unwrap().len() {
                assert_readers_agree(p, index as i32);
            }
            files += 1;
        }
    }
    assert!(files >= 7, "{files} assets");
}

#[test]
fn the_parallel_decoder_reads_grids_without_leaves() {
    // No leaves at all, and active tiles only: nothing to decode, and the walk over the buffers
    // must still end where the grid does.
    let dir = tempfile::tempdir().unwrap();
    let mut grid = hand_built();
    grid.leaves.clear();
    for (name, tiles) in [("tiles", true), ("empty", false)] {
        if !tiles {
            (grid.tile_origins, grid.tile_sizes, grid.tile_values) = (vec![], vec![], vec![]);
        }
        let out = dir.path().join(format!("{name}.vdb"));
        ffi::write_float_grids(path_str(&out), std::slice::from_ref(&grid), false).unwrap();
        assert_readers_agree(path_str(&out), 0);
        let back = ffi::read_float_grid(path_str(&out), "", 0, false, 2).unwrap();
        assert!(back.leaves.is_empty(), "{name}");
        assert_eq!(back.tile_values.len(), usize::from(tiles), "{name}");
    }
}

#[test]
fn the_parallel_decoder_restores_every_kind_of_inactive_values() {
    // OpenVDB stores a leaf's active values only, with one flag saying how its inactive ones
    // come back: all the background, all minus it, all one other value, a mask choosing between
    // two of those, or every value stored. One leaf per kind, written in full and as half.
    let b = 0.5f32;
    let inactive: [&dyn Fn(usize) -> f32; 8] = [
        &|_| b,                                     // every voxel active (below)
        &|_| b,                                     // all the background
        &|_| -b,                                    // all minus the background
        &|i| if i % 2 == 0 { b } else { -b },       // a mask between ± the background
        &|_| 0.25,                                  // one other value
        &|i| if i % 2 == 0 { b } else { 0.25 },     // a mask between it and the background
        &|i| if i % 2 == 0 { 0.125 } else { 0.25 }, // a mask between two other values
        &|i| [0.125, 0.25, 0.375][i % 3],           // all values stored
    ];
    let mut grid = hand_built();
    (grid.tile_origins, grid.tile_sizes, grid.tile_values) = (vec![], vec![], vec![]);
    grid.background = b;
    grid.leaves = (inactive.iter().enumerate())
        .map(|(k, value)| {
            let active = |i: usize| k == 0 || i.is_multiple_of(5);
            LeafData {
                origin: [8 * k as i32, 0, 0],
                values: std::array::from_fn(|i| {
                    if active(i) {
                        1.0 + (k * 512 + i) as f32 / 4096.0
                    } else {
                        value(i)
                    }
                }),
                active: std::array::from_fn(|w| {
                    (0..64)
                        .filter(|&j| active(64 * w + j))
                        .fold(0, |m, j| m | 1 << j)
                }),
            }
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    for save_half in [false, true] {
        let out = dir.path().join(format!("kinds-{save_half}.vdb"));
        ffi::write_float_grids(path_str(&out), std::slice::from_ref(&grid), save_half).unwrap();
        assert_readers_agree(path_str(&out), 0);
        if !save_half {
            let back = ffi::read_float_grid(path_str(&out), "", 0, false, 2).unwrap();
            assert_eq!(leaf_bits(&back), leaf_bits(&grid));
        }
    }
}

#[test]
fn read_cloud_copies_leaves_and_tiles() {
    let g = read_cloud();
    assert_eq!(g.name, "density");
    assert_eq!(g.grid_class, "fog volume");
    assert_eq!(g.background, 0.0);
    assert!(!g.saved_as_half);
    assert_eq!(g.leaves.len(), 1241);
    assert_eq!(g.tile_values.len(), 130);
    assert_eq!(active_voxels(&g), 415_642);
    assert!(g
        .leaves
        .iter()
        .all(|leaf| leaf.origin.iter().all(|o| o % 8 == 0)));
    for (o, (size, _)) in tiles(&g) {
        assert!([8, 128, 4096].contains(&size), "tile edge {size}");
        assert!(o.iter().all(|c| c % size as i32 == 0), "tile origin {o:?}");
    }
    // Values are densities in [0, 1]; every active voxel lies in the listed index box.
    assert!(values(&g).all(|v| (0.0..=1.0).contains(&v)));
    for (o, (_, mask)) in leaves(&g) {
        for off in 0..512 {
            if mask[off / 64] >> (off % 64) & 1 == 1 {
                let p = [
                    o[0] + (off >> 6) as i32,
                    o[1] + ((off >> 3) & 7) as i32,
                    o[2] + (off & 7) as i32,
                ];
                assert!((-66..=59).contains(&p[0]) && (-21..=64).contains(&p[1]));
                assert!((-90..=63).contains(&p[2]));
            }
        }
    }
    assert_eq!(
        meta(&g.metadata, "vector_type").map(|e| e.value.as_str()),
        Some("invariant")
    );
}

#[test]
fn read_by_index_selects_among_repeated_names() {
    let path = asset("grids.vdb");
    let grids: Vec<FloatGridData> = (0..3)
        .map(|i| ffi::read_float_grid(&path, "", i, false, 2).unwrap())
        .collect();
    let counts: Vec<u64> = grids.iter().map(active_voxels).collect();
    assert_eq!(counts, [491, 2222, 803]);
    assert!(grids.iter().all(|g| g.name == "density"));
    assert_ne!(leaves(&grids[0]), leaves(&grids[2]));
    // By name: the first grid with that name.
    let by_name = ffi::read_float_grid(&path, "density", -1, false, 2).unwrap();
    assert_eq!(leaves(&by_name), leaves(&grids[0]));
}

#[test]
fn read_half_grid() {
    let g = ffi::read_float_grid(&asset("smoke.vdb"), "density", -1, false, 2).unwrap();
    assert!(g.saved_as_half);
    assert_eq!(active_voxels(&g), 1_049_275);
    // Stored as half: every value is exactly representable in f16.
    assert!(values(&g).all(|v| half(v) == v));
    assert!(values(&g).any(|v| v > 1.0));
}

// ------------------------------------------------------------------------------------------------
// write_float_grids round trips

#[test]
fn round_trip_cloud() {
    let src = read_cloud();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cloud.vdb");
    ffi::write_float_grids(path_str(&out), std::slice::from_ref(&src), false).unwrap();
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["cloud.vdb"], "no temporary file is left behind");

    let back = ffi::read_float_grid(path_str(&out), "density", -1, false, 2).unwrap();
    assert_eq!(back.name, src.name);
    assert_eq!(back.grid_class, src.grid_class);
    assert_eq!(back.index_to_world, src.index_to_world);
    assert_eq!(back.background, src.background);
    assert!(!back.saved_as_half);
    assert_eq!(leaf_bits(&back), leaf_bits(&src));
    assert_eq!(tiles(&back), tiles(&src));
    assert_eq!(user_meta(&back.metadata), user_meta(&src.metadata));
    // OpenVDB regenerates its own statistics.
    let count = meta(&back.metadata, "file_voxel_count").expect("file_voxel_count");
    assert_eq!(count.value, "415642");

    let summary = ffi::list_grids(path_str(&out)).unwrap();
    assert_eq!(summary.len(), 1);
    assert_eq!(summary[0].active_voxels, 415_642);
    assert_eq!(summary[0].active_tiles, 130);
    assert_eq!(summary[0].index_min, [-66, -21, -90]);
}

#[test]
fn round_trip_cloud_as_half() {
    let src = read_cloud();
    let dir = tempfile::tempdir().unwrap();
    let full = dir.path().join("full.vdb");
    let halved = dir.path().join("half.vdb");
    ffi::write_float_grids(path_str(&full), std::slice::from_ref(&src), false).unwrap();
    ffi::write_float_grids(path_str(&halved), std::slice::from_ref(&src), true).unwrap();

    let back = ffi::read_float_grid(path_str(&halved), "", 0, false, 2).unwrap();
    assert!(back.saved_as_half);
    assert!(ffi::list_grids(path_str(&halved)).unwrap()[0].saved_as_half);
    let shape =
        |g: &FloatGridData| -> Vec<_> { g.leaves.iter().map(|l| (l.origin, l.active)).collect() };
    assert_eq!(shape(&back), shape(&src));
    let mut changed = 0;
    for (b, s) in values(&back).zip(values(&src)) {
        let expect = half(s);
        assert!(
            (b - expect).abs() <= 1e-3 * expect.abs(),
            "{s} stored as half read back as {b}, expected {expect}"
        );
        changed += usize::from(b != s);
    }
    assert!(changed > 0, "half storage should round some values");
    let size = |p: &PathBuf| std::fs::metadata(p).unwrap().len();
    assert!(size(&halved) < size(&full), "half file should be smaller");
}

/// Two non-constant leaves, a 128-voxel tile, a rotated and scaled transform, typed metadata.
fn hand_built() -> FloatGridData {
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

#[test]
fn round_trip_hand_built_grid() {
    let src = hand_built();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("hand.vdb");
    ffi::write_float_grids(path_str(&out), std::slice::from_ref(&src), false).unwrap();
    let back = ffi::read_float_grid(path_str(&out), "hand", -1, false, 2).unwrap();

    assert_eq!(back.name, "hand");
    assert_eq!(back.grid_class, "fog volume");
    for i in 0..16 {
        assert_close(
            back.index_to_world[i],
            src.index_to_world[i],
            1e-12,
            "transform",
        );
    }
    assert_eq!(leaves(&back), leaves(&src));
    assert_eq!(tiles(&back), tiles(&src));
    let mask_bits: u64 = (src.leaves.iter().flat_map(|leaf| leaf.active))
        .map(|w| w.count_ones() as u64)
        .sum();
    assert_eq!(mask_bits, 284);

    let m = |name: &str| {
        let e = meta(&back.metadata, name).unwrap_or_else(|| panic!("metadata {name}"));
        (e.type_name.clone(), e.value.clone())
    };
    let s = |a: &str, b: &str| (a.to_string(), b.to_string());
    assert_eq!(m("author"), s("string", "volgrad test, with spaces"));
    assert_eq!(m("sigma"), s("float", "0.1"));
    assert_eq!(m("samples"), s("int32", "64"));
    assert_eq!(m("seed"), s("int64", "12345678901"));
    assert_eq!(m("ratio"), s("double", "0.3333333333333333"));
    assert_eq!(m("flag"), s("bool", "true"));
    assert_eq!(m("offset"), s("vec3i", "[1, -2, 3]"));
    assert_eq!(m("name"), s("string", "hand"));
    assert_ne!(m("file_voxel_count").1, "999");

    let summary = &ffi::list_grids(path_str(&out)).unwrap()[0];
    assert!(summary.linear && !summary.axis_aligned);
    assert_eq!(summary.active_voxels, mask_bits + 128 * 128 * 128);
    assert_eq!(summary.leaf_count, 2);
    assert_eq!(summary.active_tiles, 1);
    assert_close(summary.voxel_size[0], 0.5, 1e-12, "voxel size");
}

#[test]
fn written_grids_keep_their_order_and_repeated_names() {
    let mut zeta = hand_built();
    zeta.name = "zeta".into();
    let mut alpha = hand_built();
    alpha.name = "alpha".into();
    alpha.tile_values = vec![0.25];
    let mut zeta2 = hand_built();
    zeta2.name = "zeta".into();
    zeta2.tile_values = vec![2.0];
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("order.vdb");
    let p = path_str(&out);
    ffi::write_float_grids(p, &[zeta, alpha, zeta2], false).unwrap();

    // File order, not OpenVDB's name-sorted order.
    let names: Vec<String> = ffi::list_grids(p)
        .unwrap()
        .into_iter()
        .map(|g| g.name)
        .collect();
    assert_eq!(names, ["zeta", "alpha", "zeta"]);
    let tile_value = |i: i32, name: &str| {
        ffi::read_float_grid(p, name, i, false, 2)
            .unwrap()
            .tile_values[0]
    };
    assert_eq!(tile_value(0, ""), 0.75);
    assert_eq!(tile_value(1, ""), 0.25);
    assert_eq!(tile_value(2, ""), 2.0);
    assert_eq!(tile_value(-1, "zeta"), 0.75);
    assert_eq!(tile_value(-1, "alpha"), 0.25);
}

#[test]
fn write_replaces_an_existing_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.vdb");
    std::fs::write(&out, b"old contents").unwrap();
    ffi::write_float_grids(path_str(&out), &[hand_built()], false).unwrap();
    assert_eq!(ffi::list_grids(path_str(&out)).unwrap()[0].name, "hand");
}

#[test]
fn vdb_print_reads_written_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cloud.vdb");
    ffi::write_float_grids(path_str(&out), &[read_cloud()], true).unwrap();
    let run = std::process::Command::new("vdb_print")
        .arg("-l")
        .arg(&out)
        .output();
    let Ok(run) = run else {
        eprintln!("vdb_print not installed (Debian: libopenvdb-tools); skipping this check");
        return;
    };
    let text = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "vdb_print failed: {text}");
    assert!(text.contains("415,642"), "{text}");
    assert!(text.contains("is_saved_as_half_float: true"), "{text}");
    assert!(text.contains("creator: volgrad"), "{text}");
}

// ------------------------------------------------------------------------------------------------
// Errors

#[test]
fn error_missing_file() {
    let e = err_text(ffi::list_grids("/no/such/dir/missing.vdb"));
    assert_eq!(e, "cannot open '/no/such/dir/missing.vdb': no such file");
    let e = err_text(ffi::read_float_grid("missing.vdb", "density", -1, false, 2));
    assert!(
        e.contains("'missing.vdb'") && e.contains("no such file"),
        "{e}"
    );
}

#[test]
fn error_a_corrupt_buffer_length_is_refused_by_both_readers() {
    // A one-leaf grid, blosc-compressed: its file ends with the leaf's compressed values, led by
    // their length. A length past the end of the file (or negative, as OpenVDB marks uncompressed
    // chunks, and past the start) is an error naming the file, from either reader.
    let mut grid = hand_built();
    grid.leaves.truncate(1);
    (grid.tile_origins, grid.tile_sizes, grid.tile_values) = (vec![], vec![], vec![]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("one.vdb");
    let ps = path_str(&p);
    ffi::write_float_grids(ps, std::slice::from_ref(&grid), false).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    let n = bytes.len();
    let at = (9..n.min(4096))
        .map(|len| n - len - 8)
        .find(|&at| {
            i64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) == (n - at - 8) as i64
        })
        .expect("the last chunk's length field");
    for length in [1i64 << 40, n as i64, -(1i64 << 40)] {
        let mut corrupt = bytes.clone();
        corrupt[at..at + 8].copy_from_slice(&length.to_le_bytes());
        std::fs::write(&p, &corrupt).unwrap();
        for e in [
            err_text(ffi::read_float_grid(ps, "", 0, false, 2)),
            err_text(ffi::read_float_grid_through_openvdb(ps, "", 0, false, 2)),
        ] {
            assert!(
                e.starts_with(&format!("'{ps}' is not a valid VDB file")),
                "length {length}: {e}"
            );
        }
    }
}

#[test]
fn error_truncated_and_garbage_files() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(asset("wdas_cloud_sixteenth.vdb")).unwrap();
    let p = dir.path().join("cut.vdb");
    let ps = path_str(&p);
    for len in [0, 7, 100, 400, bytes.len() / 2, bytes.len() - 1] {
        std::fs::write(&p, &bytes[..len]).unwrap();
        let e = err_text(ffi::list_grids(ps));
        assert!(
            e.starts_with(&format!(
                "'{ps}' is not a valid VDB file (truncated or corrupt): "
            )),
            "cut at {len}: {e}"
        );
        assert!(ffi::read_float_grid(ps, "density", -1, false, 2).is_err());
    }
    std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    let e = err_text(ffi::read_float_grid(ps, "density", -1, false, 2));
    assert!(e.contains("ends at byte"), "{e}");

    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let garbage: Vec<u8> = (0..10_000)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state as u8
        })
        .collect();
    std::fs::write(&p, &garbage).unwrap();
    let e = err_text(ffi::list_grids(ps));
    assert!(e.contains("not a VDB file"), "{e}");
    // The VDB magic number followed by garbage.
    let mut fake = bytes[..8].to_vec();
    fake.extend_from_slice(&garbage);
    std::fs::write(&p, &fake).unwrap();
    let e = err_text(ffi::read_float_grid(ps, "density", -1, false, 2));
    assert!(e.contains("is not a valid VDB file"), "{e}");
}

#[test]
fn error_unknown_grid_name_lists_names() {
    let p = asset("grids.vdb");
    let e = err_text(ffi::read_float_grid(&p, "temperature", -1, false, 2));
    assert_eq!(
        e,
        format!("no grid named 'temperature' in '{p}' (grids: density, density, density)")
    );
}

#[test]
fn error_index_out_of_range() {
    let p = asset("grids.vdb");
    let e = err_text(ffi::read_float_grid(&p, "density", 5, false, 2));
    assert_eq!(e, format!("grid index 5 out of range: '{p}' has 3 grids"));
    assert!(ffi::read_float_grid(&p, "density", 2, false, 2).is_ok());
}

#[test]
fn error_points_grid_is_not_float() {
    let p = asset("points.vdb");
    let e = err_text(ffi::read_float_grid(&p, "points", -1, false, 2));
    assert_eq!(
        e,
        format!("grid 'points' in '{p}' has value type ptdataidx32, not float")
    );
}

#[test]
fn error_unwritable_output() {
    let e = err_text(ffi::write_float_grids(
        "/nonexistent-dir/x.vdb",
        &[hand_built()],
        false,
    ));
    assert!(
        e.starts_with("cannot write '/nonexistent-dir/x.vdb'"),
        "{e}"
    );
    assert!(e.contains("does not exist"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    let e = err_text(ffi::write_float_grids(
        path_str(dir.path()),
        &[hand_built()],
        false,
    ));
    assert!(e.contains("is a directory"), "{e}");
}

#[test]
fn error_invalid_grid_data_is_rejected_before_writing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bad.vdb");
    let p = path_str(&out);

    let mut g = hand_built();
    g.metadata.push(MetaEntry {
        name: "m".into(),
        type_name: "mat4d".into(),
        value: "1".into(),
    });
    let e = err_text(ffi::write_float_grids(p, &[g], false));
    assert!(
        e.contains("'mat4d'") && e.contains("supported: string, float"),
        "{e}"
    );

    let mut g = hand_built();
    g.metadata[1].value = "abc".into();
    let e = err_text(ffi::write_float_grids(p, &[g], false));
    assert!(e.contains("'abc' is not a valid float value"), "{e}");

    let mut g = hand_built();
    g.tile_origins = vec![0, 0, 0]; // the 128-tile would swallow the leaf at the origin
    let e = err_text(ffi::write_float_grids(p, &[g], false));
    assert!(e.contains("lies inside the tile"), "{e}");

    let mut g = hand_built();
    g.tile_sizes = vec![64];
    let e = err_text(ffi::write_float_grids(p, &[g], false));
    assert!(e.contains("edge length 64"), "{e}");

    let mut g = hand_built();
    g.index_to_world[10] = 0.0;
    let e = err_text(ffi::write_float_grids(p, &[g], false));
    assert!(e.contains("singular"), "{e}");
    assert!(!out.exists(), "nothing is written for invalid input");
}

// ------------------------------------------------------------------------------------------------
// Images

fn test_image(width: u32, height: u32, channels: u32, unit: bool) -> ImageData {
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
    }
}

/// Reads an RGBA EXR with the pure-Rust `exr` crate: (width, height, interleaved RGBA).
fn exr_rgba(path: &Path) -> (usize, usize, Vec<f32>) {
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |size, _| (size.width(), vec![0f32; size.width() * size.height() * 4]),
        |(w, px): &mut (usize, Vec<f32>), pos, (r, g, b, a): (f32, f32, f32, f32)| {
            let i = 4 * (pos.y() * *w + pos.x());
            px[i..i + 4].copy_from_slice(&[r, g, b, a]);
        },
    )
    .unwrap();
    let size = image.layer_data.size;
    (
        size.width(),
        size.height(),
        image.layer_data.channel_data.pixels.1,
    )
}

fn exr_sample_types(path: &Path) -> Vec<exr::meta::attribute::SampleType> {
    let meta = exr::meta::MetaData::read_from_file(path, false).unwrap();
    meta.headers[0]
        .channels
        .list
        .iter()
        .map(|c| c.sample_type)
        .collect()
}

#[test]
fn exr_float_round_trip() {
    let img = test_image(7, 5, 4, false);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f.exr");
    ffi::write_image(path_str(&out), &img, "float").unwrap();

    let back = ffi::read_image(path_str(&out)).unwrap();
    assert_eq!((back.width, back.height, back.channels), (7, 5, 4));
    assert_eq!(back.pixels, img.pixels);

    let (w, h, px) = exr_rgba(&out);
    assert_eq!((w, h), (7, 5));
    assert_eq!(px, img.pixels);
    assert!(exr_sample_types(&out)
        .iter()
        .all(|t| *t == exr::meta::attribute::SampleType::F32));
    let meta = exr::meta::MetaData::read_from_file(&out, false).unwrap();
    assert_eq!(
        meta.headers[0].compression,
        exr::compression::Compression::ZIP16
    );
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["f.exr"], "no temporary file is left behind");
}

#[test]
fn exr_half_round_trip() {
    let img = test_image(6, 4, 4, false);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("h.exr");
    ffi::write_image(path_str(&out), &img, "half").unwrap();
    let expect: Vec<f32> = img.pixels.iter().map(|&v| half(v)).collect();
    assert_ne!(expect, img.pixels);

    assert_eq!(ffi::read_image(path_str(&out)).unwrap().pixels, expect);
    let (w, h, px) = exr_rgba(&out);
    assert_eq!((w, h), (6, 4));
    assert_eq!(px, expect);
    assert!(exr_sample_types(&out)
        .iter()
        .all(|t| *t == exr::meta::attribute::SampleType::F16));
}

#[test]
fn png_uint8_round_trip() {
    let mut img = test_image(5, 3, 4, true);
    // Exact halves and the ends of the range; alpha < 1 must not premultiply anything.
    img.pixels[..8].copy_from_slice(&[0.5, 0.0, 1.0, 0.5, 0.8, 2.0 / 255.0, 1.5 / 255.0, 0.25]);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("img.png");
    ffi::write_image(path_str(&out), &img, "uint8").unwrap();

    let decoded = image::open(&out).unwrap();
    assert_eq!(decoded.color(), image::ColorType::Rgba8);
    let bytes = decoded.to_rgba8().into_raw();
    let expect: Vec<u8> = img
        .pixels
        .iter()
        .map(|&v| (v * 255.0).round() as u8)
        .collect();
    assert_eq!(bytes, expect);
    // OIIO rounds to nearest with halves up: 0.5 -> 127.5 -> 128.
    assert_eq!(bytes[0], 128);
    assert_eq!(&bytes[4..8], &[204, 2, 2, 64]);

    let back = ffi::read_image(path_str(&out)).unwrap();
    assert_eq!((back.width, back.height, back.channels), (5, 3, 4));
    let expect_f: Vec<f32> = expect.iter().map(|&b| b as f32 / 255.0).collect();
    for (a, b) in back.pixels.iter().zip(&expect_f) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

#[test]
fn image_errors_name_the_file() {
    let e = err_text(ffi::read_image("/no/such/image.exr"));
    assert_eq!(e, "cannot open '/no/such/image.exr': no such file");

    let dir = tempfile::tempdir().unwrap();
    let text = dir.path().join("notes.png");
    std::fs::write(&text, b"this is not a png").unwrap();
    let e = err_text(ffi::read_image(path_str(&text)));
    assert!(
        e.starts_with(&format!("cannot read image '{}'", path_str(&text))),
        "{e}"
    );

    let img = test_image(2, 2, 3, true);
    let unknown = dir.path().join("x.unknownext");
    let e = err_text(ffi::write_image(path_str(&unknown), &img, "float"));
    assert!(
        e.contains("x.unknownext") && e.contains("unknown image format"),
        "{e}"
    );

    let e = err_text(ffi::write_image(
        path_str(&dir.path().join("y.exr")),
        &img,
        "int16",
    ));
    assert!(e.contains("unknown pixel type 'int16'"), "{e}");

    let mut short = img.clone();
    short.pixels.pop();
    let e = err_text(ffi::write_image(
        path_str(&dir.path().join("z.exr")),
        &short,
        "half",
    ));
    assert!(e.contains("11 values for 2x2x3"), "{e}");

    // PNG cannot hold floats: an error rather than a silent fallback to 8 bits.
    let png = dir.path().join("f.png");
    let e = err_text(ffi::write_image(path_str(&png), &img, "float"));
    assert!(
        e.contains("cannot store float pixels (it would store uint8)"),
        "{e}"
    );
    assert!(!png.exists());

    let e = err_text(ffi::write_image("/nonexistent-dir/a.exr", &img, "half"));
    assert!(e.contains("does not exist"), "{e}");
}
