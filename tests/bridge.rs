//! Integration tests of the C++ bridge (`cpp/`) through `volgrad::io::bridge::ffi`: the facts
//! of the bundled OpenVDB assets, reading float grids (in parallel and through OpenVDB), and the
//! error messages. Writing is in `bridge_write.rs`, images in `bridge_images.rs`.

mod bridge_common;

use std::path::Path;

use bridge_common::*;
use volgrad::io::bridge::ffi::{self, FloatGridData, LeafData, MetaEntry};

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

/// A file another program rewrites in place while it is read (truncated, then written again):
/// each read gives the whole grid or an error, never a fault. The parallel decoder once read the
/// file mapped into memory, where a page beyond a truncation is a SIGBUS that kills the process.
#[test]
fn a_file_rewritten_in_place_while_it_is_read_gives_the_grid_or_an_error() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(asset("wdas_cloud_sixteenth.vdb")).unwrap();
    let p = dir.path().join("rewritten.vdb");
    std::fs::write(&p, &bytes).unwrap();
    let stop = AtomicBool::new(false);
    let (mut whole, mut refused) = (0, 0);
    std::thread::scope(|scope| {
        scope.spawn(|| {
            while !stop.load(Ordering::Relaxed) {
                std::fs::write(&p, &bytes).unwrap(); // truncates, then writes
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
        });
        for _ in 0..400 {
            match ffi::read_float_grid(path_str(&p), "density", -1, false, 2) {
                Ok(g) => {
                    assert_eq!(active_voxels(&g), 415_642);
                    whole += 1;
                }
                Err(_) => refused += 1,
            }
        }
        stop.store(true, Ordering::Relaxed);
    });
    println!("{whole} whole reads, {refused} refused");
    assert_eq!(whole + refused, 400);
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
