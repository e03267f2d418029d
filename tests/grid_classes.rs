//! What a grid must be to render as a density: level sets (refused, or converted by OpenVDB's
//! sdfToFogVolume), backgrounds and inactive tiles that are not 0 (refused), files without grids.
//! Through the bridge (`volgrad::io::bridge::ffi`) and end to end through the binary.

use std::path::{Path, PathBuf};

use volgrad::io::bridge::ffi::{self, FloatGridData, LeafData};

mod common;
use common::*;

fn assets() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/assets")
}

fn asset(name: &str) -> String {
    assets().join(name).to_str().unwrap().to_string()
}

fn path_str(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

fn err_text<T>(r: Result<T, cxx::Exception>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.what().to_string(),
    }
}

/// A fog volume of one active leaf at the origin (values 0 to 1, so that it is not pruned to a
/// tile), unit voxels, background 0.
fn fog(name: &str) -> FloatGridData {
    FloatGridData {
        name: name.into(),
        grid_class: "fog volume".into(),
        index_to_world: [
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ],
        background: 0.0,
        saved_as_half: false,
        leaves: vec![LeafData {
            origin: [0, 0, 0],
            values: std::array::from_fn(|i| i as f32 / 511.0),
            active: [u64::MAX; 8],
        }],
        tile_origins: vec![],
        tile_sizes: vec![],
        tile_values: vec![],
        inactive_tiles_off_background: 0,
        metadata: vec![],
    }
}

// ------------------------------------------------------------------------------------------------
// Through the bridge

/// A level set of a ball of radius 5 voxels (voxel 0.5), written as OpenVDB level sets are:
/// signed world distances in a band of 3 voxels each side, background 1.5 (the half-width). Only
/// the band's leaves are given: the writer flood-fills the inside.
fn level_set_ball(path: &Path) {
    let (voxel, radius, half_width) = (0.5f32, 5.0f32, 1.5f32);
    let mut d = fog("hand");
    d.name = "ls_ball".into();
    d.grid_class = "level set".into();
    d.background = half_width;
    d.metadata.clear();
    d.index_to_world = [
        0.5, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 1.0,
    ];
    d.leaves.clear();
    (d.tile_origins, d.tile_sizes, d.tile_values) = (vec![], vec![], vec![]);
    for ox in [-16, -8, 0, 8] {
        for oy in [-16, -8, 0, 8] {
            for oz in [-16, -8, 0, 8] {
                let mut values = [half_width; 512];
                let mut active = [0u64; 8];
                for i in 0..512 {
                    let (x, y, z) = (ox + i as i32 / 64, oy + i as i32 / 8 % 8, oz + i as i32 % 8);
                    let r = ((x * x + y * y + z * z) as f32).sqrt();
                    let dist = (r - radius) * voxel;
                    values[i] = dist.clamp(-half_width, half_width);
                    if dist.abs() < half_width {
                        active[i / 64] |= 1 << (i % 64);
                    }
                }
                if active.iter().any(|&w| w != 0) {
                    d.leaves.push(LeafData {
                        origin: [ox, oy, oz],
                        values,
                        active,
                    });
                }
            }
        }
    }
    ffi::write_float_grids(path_str(path), std::slice::from_ref(&d), false).unwrap();
}

/// The value at index `v` of a grid copy: its leaf's value, an active tile's, else the background.
fn value_at(g: &FloatGridData, v: [i32; 3]) -> f32 {
    for leaf in &g.leaves {
        let o = leaf.origin;
        if (0..3).all(|k| v[k] - o[k] >= 0 && v[k] - o[k] < 8) {
            let i = ((v[0] - o[0]) * 64 + (v[1] - o[1]) * 8 + (v[2] - o[2])) as usize;
            return leaf.values[i];
        }
    }
    for (t, o) in g.tile_origins.chunks(3).enumerate() {
        let s = g.tile_sizes[t] as i32;
        if (0..3).all(|k| v[k] - o[k] >= 0 && v[k] - o[k] < s) {
            return g.tile_values[t];
        }
    }
    g.background
}

#[test]
fn level_sets_round_trip_and_convert_with_sdf_to_fog_volume() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("ls.vdb");
    level_set_ball(&p);
    let ps = path_str(&p);
    let summary = &ffi::list_grids(ps).unwrap()[0];
    assert_eq!(summary.grid_class, "level set");

    // As stored: distances, the background the band's half-width.
    let raw = ffi::read_float_grid(ps, "ls_ball", -1, false, 2).unwrap();
    assert_eq!(raw.grid_class, "level set");
    assert_eq!(raw.background, 1.5);
    assert_eq!(value_at(&raw, [5, 0, 0]), 0.0);
    assert_eq!(
        value_at(&raw, [0, 0, 0]),
        -1.5,
        "the inside is flood-filled"
    );

    // Converted: 0 outside, a ramp over the interior half-band (1.5 world units = 3 voxels), 1
    // inside; background 0, class fog volume.
    let fog = ffi::read_float_grid(ps, "ls_ball", -1, true, 2).unwrap();
    assert_eq!(fog.grid_class, "fog volume");
    assert_eq!(fog.background, 0.0);
    assert_eq!(value_at(&fog, [0, 0, 0]), 1.0);
    assert_eq!(value_at(&fog, [7, 0, 0]), 0.0);
    assert!((value_at(&fog, [4, 0, 0]) - 1.0 / 3.0).abs() < 1e-6);
    assert!(fog
        .leaves
        .iter()
        .all(|leaf| leaf.values.iter().all(|v| (0.0..=1.0).contains(v))));
    // Fog volumes are unaffected by the flag.
    let cloud = asset("wdas_cloud_sixteenth.vdb");
    let a = ffi::read_float_grid(&cloud, "density", -1, true, 2).unwrap();
    let b = ffi::read_float_grid(&cloud, "density", -1, false, 2).unwrap();
    assert_eq!(a.leaves.len(), b.leaves.len());
    assert!(a
        .leaves
        .iter()
        .zip(&b.leaves)
        .all(|(x, y)| x.values == y.values));
}

#[test]
fn error_level_set_needs_a_positive_background() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.vdb");
    let mut d = fog("hand");
    d.grid_class = "level set".into();
    d.background = 0.0;
    let e = err_text(ffi::write_float_grids(
        path_str(&p),
        std::slice::from_ref(&d),
        false,
    ));
    assert!(
        e.contains("narrow-band half-width") && e.contains("> 0"),
        "{e}"
    );
    d.grid_class = "fog volume".into();
    d.background = f32::NAN;
    let e = err_text(ffi::write_float_grids(
        path_str(&p),
        std::slice::from_ref(&d),
        false,
    ));
    assert!(e.contains("background") && e.contains("not finite"), "{e}");
}

#[test]
fn inactive_tiles_off_the_background_are_counted() {
    // A uniform leaf with no active voxel is pruned to an inactive tile of its value on write.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("off.vdb");
    let mut d = fog("hand");
    assert_eq!(d.inactive_tiles_off_background, 0);
    d.leaves.push(LeafData {
        origin: [64, 64, 64],
        values: [0.7; 512],
        active: [0; 8],
    });
    ffi::write_float_grids(path_str(&p), std::slice::from_ref(&d), false).unwrap();
    let back = ffi::read_float_grid(path_str(&p), "hand", -1, false, 2).unwrap();
    assert_eq!(back.inactive_tiles_off_background, 1);
    assert_eq!(back.leaves.len(), 1, "the inactive tile is not copied");
}

#[test]
fn backgrounds_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bg.vdb");
    let mut d = fog("hand");
    d.background = 0.25;
    ffi::write_float_grids(path_str(&p), std::slice::from_ref(&d), false).unwrap();
    let back = ffi::read_float_grid(path_str(&p), "hand", -1, false, 2).unwrap();
    assert_eq!(back.background, 0.25);
}

#[test]
fn error_a_file_without_grids() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("empty.vdb");
    ffi::write_float_grids(path_str(&p), &[], false).unwrap();
    assert!(ffi::list_grids(path_str(&p)).unwrap().is_empty());
    let holds_none = format!("'{}' holds no grids", path_str(&p));
    for (name, index) in [("density", -1), ("", 0)] {
        assert_eq!(
            err_text(ffi::read_float_grid(path_str(&p), name, index, false, 2)),
            holds_none
        );
    }
}

/// A name several grids share picks none of them: `grids.vdb` holds three grids named `density`.
/// By that name, or by default (which looks for `density`), the read is refused with their
/// positions; by position each grid reads.
#[test]
fn a_name_several_grids_share_is_refused() {
    use volgrad::io::vdb::{read_grid, GridSelector};
    let p = assets().join("grids.vdb");
    for selector in [GridSelector::Name("density".into()), GridSelector::Default] {
        let Err(e) = read_grid(&p, &selector) else {
            panic!("{selector:?} read one of three grids named density");
        };
        let e = e.to_string();
        assert!(
            e.contains("3 grids named 'density'")
                && e.contains("[0, 1, 2]")
                && e.contains("grid_index"),
            "{e}"
        );
    }
    for i in 0..3 {
        assert!(read_grid(&p, &GridSelector::Index(i)).is_ok());
    }
    // An albedo or colour grid by a shared name too (it took the first).
    let Err(e) = volgrad::io::vdb::read_components(&p, "density") else {
        panic!("read_components read one of three grids named density");
    };
    let e = e.to_string();
    assert!(
        e.contains("3 grids named 'density'") && !e.contains("grid_index"),
        "{e}"
    );
}

// ------------------------------------------------------------------------------------------------
// End to end

#[test]
fn grid_classes_backgrounds_and_empty_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("o.exr");
    let (ls, bg, empty) = (d.join("ls.vdb"), d.join("bg.vdb"), d.join("empty.vdb"));
    let path = |p: &Path| p.to_str().unwrap().to_string();
    ok(volgrad(&[
        "make-grid",
        "sphere",
        "--class",
        "levelset",
        "--size",
        "12",
        "--voxel-size",
        "0.5",
        "--name",
        "ls_sphere",
        "-o",
        &path(&ls),
    ]));
    let class = &volgrad::io::vdb::list_grids(&ls).unwrap()[0].grid_class;
    assert_eq!(class, "level set");
    assert_clean_error(
        &volgrad(&["make-grid", "box", "--class", "levelset", "-o", &path(&bg)]),
        &["--class levelset", "spheres only"],
    );
    assert_clean_error(
        &volgrad(&[
            "make-grid",
            "sphere",
            "--class",
            "levelset",
            "--voxel-size",
            "1,2,1",
            "-o",
            &path(&bg),
        ]),
        &["--class levelset", "cubic voxels"],
    );
    // A fog grid with background 0.5, written through the library.
    let tiny = assets().join("tiny_sphere.vdb");
    let mut grid =
        volgrad::io::vdb::read_grid(&tiny, &volgrad::io::vdb::GridSelector::Default).unwrap();
    grid.background = 0.5;
    volgrad::io::vdb::write_grids(&bg, &[&grid], false, false).unwrap();
    // Background 0 but an inactive tile of 0.7: the writer prunes a uniform, all-inactive leaf
    // into one, which OpenVDB reads as 0.7 and the brick map would read as 0. (The active voxel
    // beyond keeps the leaf inside the active bounds, where the brick map keeps leaves.)
    let off = d.join("off.vdb");
    grid.background = 0.0;
    let mut leaves = grid.bricks.leaves().to_vec();
    let leaf = |x: i32, value: f32, active: u64| volgrad::volume::brickmap::Leaf {
        origin: glam::IVec3::new(x, 0, 0),
        values: [value; 512],
        active: [active, 0, 0, 0, 0, 0, 0, 0],
    };
    leaves.extend([leaf(64, 0.7, 0), leaf(72, 0.0, 1)]);
    grid.bricks = volgrad::volume::brickmap::BrickMap::new(leaves, grid.bricks.tiles().to_vec());
    volgrad::io::vdb::write_grids(&off, &[&grid], false, false).unwrap();
    // Signed distances without the level-set class: refused for their negative values.
    let neg = d.join("neg.vdb");
    grid.grid_class = "unknown".into();
    grid.bricks = volgrad::volume::brickmap::BrickMap::new(vec![leaf(0, -1.0, u64::MAX)], vec![]);
    volgrad::io::vdb::write_grids(&neg, &[&grid], false, false).unwrap();
    volgrad::io::vdb::write_grids(&empty, &[], false, false).unwrap();

    let scene = |vdb: &Path, medium: &str| {
        let p = d.join("s.toml");
        std::fs::write(&p, format!(
            "[camera]\nposition = [0, 0, 1e-30]\ntarget = [0, 0, -1]\nup = [0, 1e-30, 0]\nfov_deg = 40\n\
             width = 8\nheight = 8\n[medium]\nvdb = {:?}\n{medium}\n[[light]]\n\
             type = \"directional\"\ndirection = [0, -1e-30, 0]\nirradiance = 1\n[render]\nspp = 1\n",
            path(vdb))).unwrap();
        volgrad(&["render", &path(&p), "-o", &path(&out), "--quiet", "--force"])
    };
    // Level sets: refused naming the class and the option, or converted on request.
    assert_clean_error(
        &scene(&ls, ""),
        &[
            "grid 'ls_sphere'",
            "ls.vdb",
            "is a level set",
            "medium.levelset = \"fog\"",
            "sdfToFogVolume",
        ],
    );
    ok(scene(&ls, "levelset = \"fog\""));
    assert_clean_error(&scene(&ls, "levelset = \"yes\""), &["yes", "refuse", "fog"]);
    // Non-zero backgrounds: refused, and info says so.
    assert_clean_error(
        &scene(&bg, ""),
        &["bg.vdb", "background 0.5", "rewrite it with background 0"],
    );
    assert_clean_error(
        &scene(&off, ""),
        &[
            "off.vdb",
            "1 inactive tiles whose value is not its background 0",
        ],
    );
    // As an albedo grid too (its brick map would read the background there, OpenVDB 0.7).
    let as_albedo = format!(
        "albedo = {{ grid = {:?}, vdb = {:?} }}",
        grid.name,
        path(&off)
    );
    assert_clean_error(
        &scene(&tiny, &as_albedo),
        &[
            "off.vdb",
            "1 inactive tiles whose value is not its background 0",
            "volgrad reads the background",
        ],
    );
    assert_clean_error(
        &scene(&neg, ""),
        &["neg.vdb", "negative values", "class \"level set\""],
    );
    let info = stdout(&ok(volgrad(&["info", &path(&bg)])));
    assert!(
        info.contains("background     0.5  (not 0: render refuses it)"),
        "{info}"
    );
    let info = stdout(&ok(volgrad(&["info", &path(&ls)])));
    assert!(info.contains("level set  (signed distances"), "{info}");
    // Files without grids: an error for render and grad, "no grids" for info.
    assert_clean_error(&scene(&empty, ""), &["empty.vdb", "holds no grids"]);
    assert_clean_error(
        &scene(&empty, "grid_index = 0"),
        &["empty.vdb", "holds no grids"],
    );
    let grad = volgrad(&[
        "grad",
        &path(&d.join("s.toml")),
        "-o",
        &path(&d.join("g.vdb")),
    ]);
    assert_clean_error(&grad, &["empty.vdb", "holds no grids"]);
    assert_eq!(
        stdout(&ok(volgrad(&["info", &path(&empty)]))).trim(),
        format!("{}: no grids", path(&empty))
    );
}
