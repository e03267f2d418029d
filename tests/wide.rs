//! Sparse grids whose bounding box is far wider than their data (debris, cloudscapes): memory must
//! follow the active voxels, and rendering, differentiation and `volgrad info` must work on them.

mod common;

use common::*;
use glam::{DVec3, IVec3, Vec3};
use volgrad::gradient::adjoint::Estimator;
use volgrad::gradient::fd;
use volgrad::gradient::grid::GradientGrid;
use volgrad::gradient::loss::Loss;
use volgrad::gradient::passes::{gradient, GradOptions};
use volgrad::io::vdb::{self, Grid, GridSelector};
use volgrad::render::image::{render, RenderOptions};
use volgrad::volume::brickmap::{BrickMap, BrickMapBuilder, Tile};
use volgrad::volume::majorant::{Majorant, MajorantGrid};
use volgrad::volume::medium::Filter;
use volgrad::volume::transform::IndexTransform;

/// Gap between the two blobs, in voxels: far beyond what a dense table over the box could hold
/// (24,000³ slots of 4 bytes would be 55 GB for the old brick table, 864 MB of majorant cells).
const GAP: i32 = 24_000;

/// Two lumpy 6³ blobs, one around the origin and one `GAP` voxels further down −z.
fn two_blobs() -> BrickMap {
    let mut b = BrickMapBuilder::new();
    for z0 in [0, -GAP] {
        for x in 0..6 {
            for y in 0..6 {
                for z in 0..6 {
                    let value = 0.5 + 0.1 * ((x * 7 + y * 3 + z) % 5) as f32;
                    b.set(IVec3::new(x, y, z0 + z), value, true);
                }
            }
        }
    }
    b.build()
}

#[test]
fn blobs_far_apart_render_and_differentiate_in_little_memory() {
    let grid = two_blobs();
    assert_eq!(grid.active_voxel_count(), 2 * 216);
    let leaf_bytes = std::mem::size_of_val(grid.leaves());
    println!(
        "two blobs {GAP} voxels apart: brick map {} bytes for {leaf_bytes} bytes of leaves",
        grid.memory_bytes()
    );
    assert!(
        grid.memory_bytes() < leaf_bytes + 64 * 1024,
        "brick map {} bytes for {leaf_bytes} bytes of leaves",
        grid.memory_bytes()
    );
    // Camera on +z with a narrow field of view: every ray crosses the near blob, then the empty
    // gap, then the far blob (which fills the view 24,000 voxels further).
    let transform = IndexTransform::uniform(1.0, DVec3::splat(-2.5));
    let scene = SceneBuilder::new(30.0, 0.008, 12)
        .constant_light(Vec3::ONE)
        .build(
            grid,
            transform,
            0.2,
            Vec3::splat(0.8),
            0.0,
            Filter::Trilinear,
            Majorant::grid(4),
        );
    println!(
        "two blobs: majorant {} bytes",
        scene.medium.majorant.memory_bytes()
    );
    assert!(
        scene.medium.majorant.memory_bytes() < 256 * 1024,
        "majorant {} bytes",
        scene.medium.majorant.memory_bytes()
    );
    // A box of cells per blob: a walk crosses the gap between them in one jump, not node by node.
    assert_eq!(scene.medium.majorant.flat_boxes(), 2);
    let options = RenderOptions {
        spp: 8,
        seed: 3,
        max_depth: 8,
        progress: false,
    };
    let (image, stats) = render(&scene, &options);
    assert!(stats.paths > 0);
    assert!(image.pixels.iter().all(|p| p.is_finite()));
    // The blobs absorb: the image is darker than the sky.
    let mean = image.pixels.iter().map(|p| p.x).sum::<f32>() / image.pixels.len() as f32;
    assert!(mean < 0.95, "mean pixel {mean}");

    let adjoint = Loss::Mean.adjoint(&image, None);
    let run = gradient(
        &scene,
        &adjoint,
        &GradOptions::new(Estimator::Joint, 8, 5, 8),
    );
    let g = &run.values();
    assert!(g.voxels().all(|(_, v)| v.is_finite()));
    println!("two blobs: {} gradient blocks", g.block_count());
    let near = g.sum_in_box(IVec3::splat(-1), IVec3::splat(6));
    let far = g.sum_in_box(IVec3::new(-1, -1, -GAP - 1), IVec3::new(6, 6, -GAP + 6));
    // More density makes the sky-lit blob darker: the mean's gradient is negative on both blobs
    // (the far one is seen through the near one).
    assert!(near < 0.0, "near blob gradient {near}");
    assert!(far != 0.0, "no gradient reached the far blob");
    // Blocks only where gradient arrived: the blobs and the empty voxels the rays crossed between
    // them (they are parameters too), at most a 3×3-block column (4³ blocks, apron included)
    // along the gap.
    let column = 9 * (GAP as usize / 4 + 8);
    assert!(
        g.block_count() <= column,
        "{} gradient blocks",
        g.block_count()
    );
}

/// A fog volume of unit voxels at `voxels` (value 1, voxel size 1, index = world) as a .vdb.
fn write_voxels(path: &std::path::Path, voxels: &[IVec3]) {
    let mut b = BrickMapBuilder::new();
    for &v in voxels {
        b.set(v, 1.0, true);
    }
    let grid = Grid {
        transform: IndexTransform::uniform(1.0, DVec3::ZERO),
        bricks: b.build(),
        name: "density".into(),
        grid_class: "fog volume".into(),
        saved_as_half: false,
        background: 0.0,
        metadata: Vec::new(),
    };
    vdb::write_grids(path, &[&grid], false, false).unwrap();
}

#[test]
fn two_voxels_a_million_apart_load_render_and_stay_small() {
    let dir = tempfile::tempdir().unwrap();
    let vdb_path = dir.path().join("apart.vdb");
    write_voxels(&vdb_path, &[IVec3::ZERO, IVec3::new(1_000_000, 0, 0)]);

    let o = ok(volgrad(&["info", vdb_path.to_str().unwrap()]));
    assert!(stdout(&o).contains("brick map"), "{}", stdout(&o));

    let read = vdb::read_grid(&vdb_path, &GridSelector::Index(0)).unwrap();
    assert_eq!(read.bricks.active_voxel_count(), 2);
    assert_eq!(read.bricks.voxel(IVec3::new(1_000_000, 0, 0)), 1.0);
    println!(
        "two voxels 10⁶ apart: brick map {} bytes",
        read.bricks.memory_bytes()
    );
    assert!(
        read.bricks.memory_bytes() < 64 * 1024,
        "brick map {} bytes",
        read.bricks.memory_bytes()
    );
    for cell in [1, 4, 16] {
        let bounds = (Vec3::splat(-0.5), Vec3::new(1_000_000.5, 0.5, 0.5));
        let m = MajorantGrid::build(&read.bricks, bounds, 1.0, Majorant::grid(cell));
        println!(
            "two voxels 10⁶ apart: majorant ({cell}³ cells) {} bytes",
            m.memory_bytes()
        );
        assert!(
            m.memory_bytes() < 256 * 1024,
            "majorant {} bytes",
            m.memory_bytes()
        );
    }
    let g = GradientGrid::<f32>::for_grid(&read.bricks);
    assert_eq!(g.block_count(), 0);

    let scene = dir.path().join("apart.toml");
    std::fs::write(
        &scene,
        "[camera]\nposition = [-20, 2, 3]\ntarget = [500000, 0, 0]\nfov_deg = 30\nwidth = 16\nheight = 16\n\
         [medium]\nvdb = \"apart.vdb\"\ndensity_scale = 2.0\n\
         [[light]]\ntype = \"constant\"\nradiance = 0.5\n\
         [render]\nspp = 2\n",
    )
    .unwrap();
    let out = dir.path().join("apart.exr");
    let o = ok(volgrad(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--stats",
    ]));
    assert!(stdout(&o).contains("memory"), "{}", stdout(&o));
}

#[test]
fn finite_differences_refuse_to_list_a_huge_domain_instead_of_exhausting_memory() {
    let mut b = BrickMapBuilder::new();
    b.set(IVec3::ZERO, 1.0, true);
    b.set(IVec3::splat(200_000), 1.0, true);
    let grid = b.build();
    let (lo, hi) = fd::domain_bounds(&grid).unwrap();
    let err = fd::ensure_enumerable(&grid, lo, hi)
        .unwrap_err()
        .to_string();
    assert!(err.contains("200003 × 200003 × 200003"), "{err}");
    assert!(err.contains("smaller box"), "{err}");
    fd::ensure_enumerable(&grid, IVec3::splat(-1), IVec3::splat(8)).unwrap();
    fd::ensure_enumerable(&two_blobs(), IVec3::splat(i32::MIN), IVec3::splat(i32::MAX)).unwrap();
}

#[test]
fn a_root_level_tile_costs_its_surface_not_its_volume() {
    // OpenVDB's largest tiles are 4096³ voxels: constant fog over a whole sky.
    let tile = Tile {
        origin: IVec3::ZERO,
        size: 4096,
        value: 0.25,
    };
    let mut leaf = BrickMapBuilder::new();
    leaf.set(IVec3::new(5000, 7, 7), 2.0, true);
    let leaves = leaf.build().leaves().to_vec();
    let grid = BrickMap::new(leaves, vec![tile]);
    assert_eq!(grid.voxel(IVec3::splat(4095)), 0.25);
    assert_eq!(grid.voxel(IVec3::new(5000, 7, 7)), 2.0);
    // One region of the index above its nodes (O(1)), not 64³ uniform nodes (8.9 MB).
    assert!(
        grid.memory_bytes() < 64 << 10,
        "brick map {} bytes",
        grid.memory_bytes()
    );
    let (lo, hi) = grid.active_bounds().unwrap();
    let bounds = (lo.as_vec3() - 0.5, hi.as_vec3() + 0.5);
    let m = MajorantGrid::build(&grid, bounds, 1.0, Majorant::grid(4));
    println!(
        "4096³ tile: brick map {} bytes, majorant {} bytes",
        grid.memory_bytes(),
        m.memory_bytes()
    );
    // Its surface: the cells of the tile's apron.
    assert!(
        m.memory_bytes() < 4 << 20,
        "majorant {} bytes",
        m.memory_bytes()
    );
    // The majorant bounds the lookups along rays through the tile, its faces and the leaf.
    for (o, d) in [
        (Vec3::new(-0.5, 7.2, 7.3), Vec3::X),
        (
            Vec3::new(2000.0, -0.5, 4095.2),
            Vec3::new(0.3, 1.0, 0.0).normalize(),
        ),
        (
            Vec3::new(4090.0, 4090.0, 4090.0),
            Vec3::new(1.0, -0.001, -0.001).normalize(),
        ),
    ] {
        let t_end = 1200.0;
        for seg in m.walk(o, d, 0.0, t_end) {
            for k in 0..4 {
                let t = seg.t0 + (seg.t1 - seg.t0) * (k as f32 + 0.5) / 4.0;
                let sigma = grid.trilinear(o + d * t);
                assert!(
                    sigma <= seg.sigma_max + 1e-6,
                    "σ {sigma} > {} at {}",
                    seg.sigma_max,
                    o + d * t
                );
            }
        }
    }
}

#[test]
fn walks_skip_empty_nodes_but_never_data() {
    // Two hot voxels 5,000 apart along a diagonal-ish line; every ray between them crosses empty
    // nodes (skipped whole) and must still see both voxels' cells.
    let mut b = BrickMapBuilder::new();
    let far = IVec3::new(5000, 1200, -700);
    b.set(IVec3::ZERO, 3.0, true);
    b.set(far, 5.0, true);
    let grid = b.build();
    let (lo, hi) = grid.active_bounds().unwrap();
    let bounds = (lo.as_vec3() - 0.5, hi.as_vec3() + 0.5);
    for cell in [1, 4] {
        let m = MajorantGrid::build(&grid, bounds, 1.0, Majorant::grid(cell));
        for k in 0..200 {
            let jitter = Vec3::new(
                ((k * 37) % 11) as f32 / 11.0 - 0.5,
                ((k * 53) % 13) as f32 / 13.0 - 0.5,
                ((k * 71) % 7) as f32 / 7.0 - 0.5,
            ) * 0.8;
            let (o, target) = if k % 2 == 0 {
                (jitter, far.as_vec3() - jitter)
            } else {
                (far.as_vec3() + jitter, -jitter)
            };
            let d = (target - o).normalize();
            let length = (target - o).length();
            let mut seen = [false; 2];
            let mut last = 0.0f32;
            for seg in m.walk(o, d, 0.0, length) {
                assert!(
                    seg.t0 >= last - 1e-3 && seg.t1 >= seg.t0,
                    "segments go backwards"
                );
                last = seg.t1;
                for j in 0..8 {
                    let t = seg.t0 + (seg.t1 - seg.t0) * (j as f32 + 0.5) / 8.0;
                    let sigma = grid.trilinear(o + d * t);
                    assert!(
                        sigma <= seg.sigma_max + 1e-6,
                        "σ {sigma} > {}",
                        seg.sigma_max
                    );
                }
                for (i, t_voxel) in [0.0, length].into_iter().enumerate() {
                    let t_near = if k % 2 == 0 {
                        t_voxel
                    } else {
                        length - t_voxel
                    };
                    if seg.sigma_max > 0.0 && seg.t0 <= t_near + 0.25 && seg.t1 >= t_near - 0.25 {
                        seen[i] = true;
                    }
                }
            }
            assert_eq!(
                seen,
                [true, true],
                "cell {cell}, ray {k}: a voxel's cells were skipped"
            );
        }
    }
}

/// `grad` over the whole box (`--domain all`) of a grid whose three voxels lie 60,000 voxels apart
/// along the box's diagonal, under a 2 GiB address-space limit: the gradient and its picture take
/// memory for where gradient arrives, never for the box (its projection picture once asked for a
/// 56,000² image, 12.5 GB, and aborted).
#[test]
fn the_gradient_of_a_diagonal_sparse_grid_fits_in_little_memory() {
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    let voxels = [0, 30_000, 60_000].map(IVec3::splat);
    write_voxels(&dir.path().join("diagonal.vdb"), &voxels);
    // Looking down the diagonal from beyond its first corner: every ray crosses the empty box.
    std::fs::write(
        dir.path().join("diagonal.toml"),
        "[camera]\nposition = [-50, -40, -60]\ntarget = [60000, 60000, 60000]\nfov_deg = 20\nwidth = 32\nheight = 32\n\
         [medium]\nvdb = \"diagonal.vdb\"\ndensity_scale = 0.5\nalbedo = 0.5\n\
         [[light]]\ntype = \"constant\"\nradiance = 0.5\n",
    )
    .unwrap();
    let limit = 2u64 << 30;
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_volgrad"));
    command.current_dir(dir.path()).args([
        "grad",
        "diagonal.toml",
        "--estimator",
        "joint",
        "--loss",
        "mean",
        "--spp",
        "1",
        "--domain",
        "all",
        "-o",
        "g.vdb",
    ]);
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        command.pre_exec(move || {
            let rlimit = libc::rlimit {
                rlim_cur: limit,
                rlim_max: limit,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &rlimit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let o = ok(command.output().unwrap());
    let picture = image::open(dir.path().join("g.png")).unwrap();
    assert!(
        picture.width() <= 1024 && picture.height() <= 1024,
        "{}×{} picture: {}",
        picture.width(),
        picture.height(),
        stdout(&o)
    );
    let g = vdb::read_grid(&dir.path().join("g.vdb"), &GridSelector::Index(0)).unwrap();
    assert!(g.bricks.active_voxel_count() > 100, "{}", stdout(&o));
}
