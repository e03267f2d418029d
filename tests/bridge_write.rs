//! The C++ bridge writing float grids (`write_float_grids`): round trips of the bundled cloud (as
//! float and as half), a hand-built rotated grid with typed metadata, order and repeated names,
//! replacement, and `vdb_print` reading what is written.

mod bridge_common;

use std::path::PathBuf;

use bridge_common::*;
use volgrad::io::bridge::ffi::{self, FloatGridData};

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
    let run = run.expect("vdb_print is installed (Debian: libopenvdb-tools; scripts/setup.sh)");
    let text = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "vdb_print failed: {text}");
    assert!(text.contains("415,642"), "{text}");
    assert!(text.contains("is_saved_as_half_float: true"), "{text}");
    assert!(text.contains("creator: volgrad"), "{text}");
}

/// `volgrad info` lists every grid of a file even when one cannot be read (here a grid holding a
/// NaN, which render refuses): that grid's values line says why, and the grids after it are
/// listed. It stopped at the unreadable grid with an error.
#[test]
fn info_goes_on_past_a_grid_it_cannot_read() {
    let dir = tempfile::tempdir().unwrap();
    let mut broken = hand_built();
    broken.name = "broken".into();
    broken.leaves[0].values[3] = f32::NAN;
    let mut good = hand_built();
    good.name = "fine".into();
    let path = dir.path().join("two.vdb");
    ffi::write_float_grids(path_str(&path), &[broken, good], false).unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .args(["info", path_str(&path)])
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("not readable") && out.contains("NaN"), "{out}");
    assert!(
        out.contains("[1] fine") && out.contains("values         0 .. "),
        "{out}"
    );
}
