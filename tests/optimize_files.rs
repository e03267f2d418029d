//! What `volgrad optimize` reads and writes, on the tiny reconstruction (`optimize_common`): views
//! under their own lights and relit held-out views, the study's chart, table and summary, bad run
//! files, the target cache and the noise ceiling (pictures from elsewhere: `optimize_pictures`).

mod common;
mod optimize_common;

use std::path::Path;

use common::{assert_clean_error, ok, stderr, stdout, volgrad_in};
use optimize_common::*;
use volgrad::cluster::Cluster;
use volgrad::optimize::target_cache;

/// Views under their own lights: training views split over two suns (two orbits), held-out views
/// under one of them and under a third sun no training view had. The targets are rendered under
/// each view's lights, the third sun's held-out views count as relit, and the log and the summary
/// report their PSNR apart.
#[test]
fn views_under_their_own_lights_and_relit_held_out_views() {
    use volgrad::optimize::problem::Problem;
    let sun = |d: &str| {
        format!("light = [{{ type = \"directional\", direction = [{d}], irradiance = 4.0 }}]")
    };
    let orbit = |set: &str, count: u32, elevation: &str, offset: u32, light: &str| {
        format!(
            "[[{set}.orbit]]\ncount = {count}\nelevation_deg = [{elevation}]\ndistance = 12\nfov_deg = 40\nwidth = 24\nheight = 24\nazimuth_offset_deg = {offset}\n{light}\n"
        )
    };
    let run = format!(
        "scene = \"scene.toml\"\ntruth = \"ball.vdb\"\ntarget_spp = 64\neval_spp = 32\neval_every = 2\n\
         {}{}{}{}\n[unknown]\nbounds = \"truth\"\nstart = 0.2\n[optimizer]\nspp = 1\niterations = 4\n",
        orbit("views", 3, "-30, 70", 0, &sun("-0.5, -1.0, -0.3")),
        orbit("views", 3, "-30, 70", 60, &sun("0.5, -1.0, 0.3")),
        orbit("holdouts", 1, "20, 20", 30, &sun("-0.5, -1.0, -0.3")),
        orbit("holdouts", 1, "20, 20", 30, &sun("0.0, 1.0, 0.0")),
    );
    let dir = fixture(&run);
    let problem = Problem::load(
        &dir.path().join("run.toml"),
        None,
        false,
        None,
        &Cluster::single(),
    )
    .unwrap();
    let sets: Vec<usize> = problem.views.iter().map(|v| v.light_set).collect();
    assert_eq!(sets, vec![1, 1, 1, 2, 2, 2]);
    let relit: Vec<bool> = problem.holdouts.iter().map(|v| v.relit).collect();
    assert_eq!(relit, vec![false, true]);
    // The same camera under two suns: the targets differ.
    let (a, b) = (&problem.holdouts[0].target, &problem.holdouts[1].target);
    let difference: f32 = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(x, y)| (*x - *y).abs().max_element())
        .sum();
    assert!(difference > 1.0, "{difference}");

    let out = ok(volgrad_in(
        dir.path(),
        &["optimize", "run.toml", "--out", "o", "-q"],
    ));
    assert!(stdout(&out).contains("relit"), "{}", stdout(&out));
    let rows = log(&dir.path().join("o"));
    let relit = evaluated(&rows, "relit_psnr");
    assert!(
        relit.len() >= 2 && relit.iter().all(|p| p.is_finite()),
        "{relit:?}"
    );
    // settings.toml keeps the lights, and reads back.
    let settings = std::fs::read_to_string(dir.path().join("o/settings.toml")).unwrap();
    assert_eq!(settings.matches("[[views.orbit]]").count(), 2, "{settings}");
    ok(volgrad_in(
        dir.path(),
        &[
            "optimize",
            "o/settings.toml",
            "--out",
            "again",
            "--iterations",
            "1",
            "-q",
        ],
    ));
}

/// `--estimators` runs each estimator into its folder and writes the study's files.
#[test]
fn the_study_writes_its_chart_table_and_summary() {
    let dir = fixture(
        &run_file("0.2", "spp = 2\niterations = 4").replace("eval_every = 10", "eval_every = 2"),
    );
    let d = dir.path();
    let out = ok(volgrad_in(
        d,
        &[
            "optimize",
            "run.toml",
            "--estimators",
            "joint,drt",
            "--out",
            "study",
            "-q",
        ],
    ));
    for f in [
        "inverse.png",
        "inverse.svg",
        "inverse.csv",
        "summary.md",
        "renders.png",
        "joint/final.vdb",
        "drt/log.csv",
    ] {
        assert!(d.join("study").join(f).is_file(), "no {f}");
    }
    let csv = std::fs::read_to_string(d.join("study/inverse.csv")).unwrap();
    // 3 evaluations (start, 2, 4) per estimator.
    assert_eq!(
        csv.lines().filter(|l| l.starts_with("joint,")).count(),
        3,
        "{csv}"
    );
    assert_eq!(
        csv.lines().filter(|l| l.starts_with("drt,")).count(),
        3,
        "{csv}"
    );
    let summary = std::fs::read_to_string(d.join("study/summary.md")).unwrap();
    assert!(
        summary.contains("| joint") && summary.contains("| drt"),
        "{summary}"
    );
    assert!(common::stdout(&out).contains("final PSNR"));
    // The study's folder is not overwritten without --force.
    assert_clean_error(
        &volgrad_in(
            d,
            &[
                "optimize",
                "run.toml",
                "--estimators",
                "joint",
                "--out",
                "study",
            ],
        ),
        &["not empty", "--force"],
    );
}

/// Each class of bad run file or flag gets one clean error naming the key.
#[test]
fn bad_run_files_name_the_key() {
    let dir = fixture(&run_file("0.1", "spp = 1\niterations = 2"));
    let d = dir.path();
    let good = std::fs::read_to_string(d.join("run.toml")).unwrap();
    let image_view = |image: &str| {
        format!(
            "\n[[view]]\nposition = [0, 0, 12]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 24\nheight = 24\nimage = \"{image}\"\n"
        )
    };
    std::fs::write(d.join("junk.exr"), b"not an image").unwrap();
    // A 24x24 view with a 32x32 image: render one to have a real file of the wrong size.
    ok(volgrad_in(
        d,
        &[
            "render",
            "scene.toml",
            "-o",
            "small.exr",
            "--spp",
            "1",
            "-q",
        ],
    ));
    // The training views' block cut out.
    let (head, rest) = good.split_once("[views.orbit]").unwrap();
    let no_views = format!(
        "{head}[holdouts.orbit]{}",
        rest.split_once("[holdouts.orbit]").unwrap().1
    );
    let (head, rest) = good.split_once("[holdouts.orbit]").unwrap();
    let no_holdouts = format!("{head}[unknown]{}", rest.split_once("[unknown]").unwrap().1);
    let cases: Vec<(String, Vec<&str>)> = vec![
        (no_views.clone(), vec!["no views"]),
        (no_holdouts, vec!["no held-out views"]),
        (
            good.replacen("distance = 12", "distance = 2", 1),
            vec!["views.orbit", "inside"],
        ),
        (
            good.replace("bounds = \"truth\"", "bounds = \"views\""),
            vec!["views.orbit", "orbits circle the unknown's box"],
        ),
        (
            good.replace("bounds = \"truth\"", "bounds = \"views\"\nvoxel_size = -1"),
            vec!["unknown.voxel_size"],
        ),
        (good.replace("lr = 0.1", "lr = 0"), vec!["optimizer.lr"]),
        (good.replace("lr = 0.1", "lr = -2"), vec!["optimizer.lr"]),
        (
            good.replace("lr = 0.1", "lr = 1e-300"),
            vec!["optimizer.lr = 1e-300", "32-bit float's range"],
        ),
        (
            good.replace("batch = 3", "batch = 3\nsmooth_gradient = 2"),
            vec!["smooth_gradient"],
        ),
        (
            good.replace("first_level_smoothing = 0", "first_level_smoothing = 9"),
            vec!["optimizer.first_level_smoothing", "at most 8"],
        ),
        (
            good.replace("first_level_smoothing = 0", "first_level_smoothing = -1"),
            vec!["first_level_smoothing"],
        ),
        (
            good.replace("batch = 3", "batch = 3\naverage_from = 1.5"),
            vec!["optimizer.average_from", "[0, 1]"],
        ),
        (
            good.replace("batch = 3", "batch = 3\naverage_from = -0.1"),
            vec!["optimizer.average_from", "[0, 1]"],
        ),
        (
            good.replace("batch = 3", "batch = 3\nfit_scale = \"yes\""),
            vec!["fit_scale"],
        ),
        (
            good.replace("batch = 3", "batch = 3\nfit_brick_scales = 1"),
            vec!["fit_brick_scales"],
        ),
        (
            good.replace("batch = 3", "batch = 3\nalpha_weight = -1"),
            vec!["optimizer.alpha_weight", "from 0"],
        ),
        // Past it the squared gradients overflow: the run emptied its grid without a word.
        (
            good.replace("batch = 3", "batch = 3\nalpha_weight = 1e22"),
            vec!["optimizer.alpha_weight", "1e6"],
        ),
        // 2 × spp, the default primal_spp, wrapped to 0.
        (
            good.replace("\nspp = 1\n", "\nspp = 2147483648\n"),
            vec!["optimizer.spp", "more than"],
        ),
        // One of the two was dropped without a word.
        (
            good.replace("lr = 0.1", "lr = 0.1\nstep_optical_depth = 0.5"),
            vec!["step_optical_depth", "lr", "give one"],
        ),
        // NaN cameras, scored as a perfect match.
        (
            good.replace("azimuth_offset_deg = 60", "azimuth_offset_deg = nan"),
            vec!["holdouts.orbit", "azimuth_offset_deg", "finite"],
        ),
        // A scene file where a run file belongs: said so, not "unknown field `camera`".
        (SCENE.to_string(), vec!["is a scene file", "volgrad render"]),
        // Read as "the scene's lights", which leaving the key out already says.
        (
            good.replace("[views.orbit]\n", "[views.orbit]\nlight = []\n"),
            vec!["light = []", "leave `light` out"],
        ),
        // A held-out capture no training set names, with no exposure fitted.
        (
            good.replace(
                "[holdouts.orbit]\n",
                "[holdouts]\ncapture = \"bright\"\n[holdouts.orbit]\n",
            ),
            vec!["holdouts.orbit", "capture \"bright\" is no training set's"],
        ),
        (
            good.replace(
                "start = 0.1",
                "start = 0.1\nlevels = [0.5]\nstart_voxel_size = 3.0",
            ),
            vec!["unknown.levels", "final"],
        ),
        (
            format!("{good}{}", image_view("missing.exr")),
            vec!["view[0].image"],
        ),
        (
            format!("{good}{}", image_view("junk.exr")),
            vec!["view[0].image"],
        ),
        (
            format!(
                "{good}{}",
                image_view("small.exr").replace("width = 24", "width = 32")
            ),
            vec!["view[0].image", "24×24"],
        ),
        // A vacuum scene: the images do not depend on the grid, and the settings derived from the
        // optical depth would be infinite.
        (
            good.replace("scene = \"scene.toml\"", "scene = \"vacuum.toml\""),
            vec!["density_scale", "0"],
        ),
        (
            good.replace(
                "[unknown]",
                "[views]\ntransforms = \"missing.json\"\n[unknown]",
            ),
            vec!["views.transforms", "missing.json"],
        ),
        (
            good.replace(
                "[views.orbit]\n",
                "[views.orbit]\nlight = [{ type = \"constant\", radiance = -1 }]\n",
            ),
            vec!["views.orbit[0]", "light[0].radiance"],
        ),
    ];
    std::fs::write(
        d.join("vacuum.toml"),
        SCENE.replace("density_scale = 0.6", "density_scale = 0.0"),
    )
    .unwrap();
    for (i, (text, needles)) in cases.iter().enumerate() {
        let name = format!("bad{i}.toml");
        std::fs::write(d.join(&name), text).unwrap();
        let out = volgrad_in(d, &["optimize", &name, "--out", &format!("o{i}"), "-q"]);
        assert_clean_error(&out, needles);
    }
    // Flags: a budget of 0, an unknown estimator.
    assert_clean_error(
        &volgrad_in(d, &["optimize", "run.toml", "--budget", "0s", "-q"]),
        &["--budget"],
    );
    let out = volgrad_in(d, &["optimize", "run.toml", "--estimator", "magic", "-q"]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("magic"), "{}", stderr(&out));
}

/// `--target-cache`: the first run renders its 7 targets into the cache, later runs read them and
/// reach the same bits as a run without the cache; another target_spp or another light makes new
/// entries, another --seed none (targets depend on the run file only); an entry that is read is
/// used (a valid changed one changes the run), and a damaged one (cut short, or pixels changed
/// under an intact header: its checksum fails) is rendered again.
#[test]
fn a_target_cache_renders_each_target_once_and_changes_nothing() {
    let dir = fixture(&run_file("0.2", "spp = 2\niterations = 4"));
    let d = dir.path();
    let run = |out: &str, cache: bool, extra: &[&str]| {
        let mut args = vec!["optimize", "run.toml", "--out", out];
        if cache {
            args.extend(["--target-cache", "cache"]);
        }
        args.extend(extra);
        ok(volgrad_in(d, &args))
    };
    let entries = || std::fs::read_dir(d.join("cache")).unwrap().count();
    let results = |out: &str| -> Vec<(String, String)> {
        log(&d.join(out))
            .into_iter()
            .map(|r| (r["loss"].clone(), r["heldout_psnr"].clone()))
            .collect()
    };

    run("plain", false, &[]);
    run("first", true, &[]);
    assert_eq!(entries(), 7, "6 views and 1 held-out view");
    let second = run("second", true, &[]);
    assert!(
        stderr(&second).contains("7 of 7 targets read from the target cache"),
        "{}",
        stderr(&second)
    );
    assert_eq!(results("first"), results("plain"));
    assert_eq!(results("second"), results("plain"));
    run("seed", true, &["--seed", "2"]);
    assert_eq!(entries(), 7, "--seed does not change the targets");

    // An entry read is used: every target made twice as bright (a valid entry) changes the run.
    // Pixels changed under an intact header and length (scaled by 3, or zeroed) fail the
    // entry's checksum: rendered again and the entry replaced, so the run is the plain one.
    let rewrite = |change: &dyn Fn(&[u8], &str) -> Vec<u8>| {
        for entry in std::fs::read_dir(d.join("cache")).unwrap() {
            let path = entry.unwrap().path();
            let key = path.file_stem().unwrap().to_str().unwrap().to_string();
            let bytes = std::fs::read(&path).unwrap();
            std::fs::write(&path, change(&bytes, &key)).unwrap();
        }
    };
    let header_end = |bytes: &[u8]| bytes.iter().position(|&b| b == b'\n').unwrap() + 1;
    rewrite(&|bytes, key| {
        let header = std::str::from_utf8(&bytes[..header_end(bytes) - 1]).unwrap();
        let size: Vec<u32> = (header.split(' ').skip(3).take(2))
            .map(|n| n.parse().unwrap())
            .collect();
        let mut image = target_cache::decode(bytes, key, size[0], size[1]).unwrap();
        image.pixels.iter_mut().for_each(|p| *p *= 2.0);
        target_cache::encode(key, &image)
    });
    run("doubled", true, &[]);
    assert_ne!(results("doubled"), results("plain"));
    for (name, by) in [("tripled", 3.0f32), ("zeroed", 0.0)] {
        rewrite(&|bytes, _| {
            let mut bytes = bytes.to_vec();
            let at = header_end(&bytes);
            for value in bytes[at..].chunks_exact_mut(4) {
                let v = f32::from_le_bytes(value.try_into().unwrap()) * by;
                value.copy_from_slice(&v.to_le_bytes());
            }
            bytes
        });
        let changed = run(name, true, &[]);
        let warned = stderr(&changed).matches("unusable").count();
        assert_eq!(warned, 7, "{name}: {}", stderr(&changed));
        assert_eq!(results(name), results("plain"), "{name}");
    }
    let again = run("rewritten", true, &[]);
    assert!(
        stderr(&again).contains("7 of 7 targets read from the target cache"),
        "{}",
        stderr(&again)
    );
    // A damaged entry (cut short) is reported and rendered again.
    let first = std::fs::read_dir(d.join("cache")).unwrap().next().unwrap();
    let path = first.unwrap().path();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let again = run("damaged", true, &[]);
    assert!(stderr(&again).contains("unusable"), "{}", stderr(&again));
    assert_eq!(entries(), 7);

    let edit = |file: &str, from: &str, to: &str| {
        let text = std::fs::read_to_string(d.join(file)).unwrap();
        assert!(text.contains(from), "{file} has no {from:?}");
        std::fs::write(d.join(file), text.replace(from, to)).unwrap();
    };
    edit("run.toml", "target_spp = 256", "target_spp = 128");
    run("spp", true, &[]);
    assert_eq!(entries(), 14, "another target_spp: new targets");
    edit("scene.toml", "irradiance = 4.0", "irradiance = 3.0");
    run("light", true, &[]);
    assert_eq!(entries(), 21, "another light: new targets");
    // A cache that cannot be written (a file where its folder should be) ends the run cleanly.
    assert_clean_error(
        &volgrad_in(
            d,
            &[
                "optimize",
                "run.toml",
                "--out",
                "bad",
                "--target-cache",
                "run.toml",
            ],
        ),
        &["target cache", "run.toml"],
    );
}

/// The noise ceiling the log reports beside the held-out PSNR is what the evaluation's noise
/// allows: the true grid, rendered at `eval_spp = 8` against targets of 2048 spp (nearly noise
/// free), scores it to within a dB (a ceiling off by a factor of 2 in the noise's variance would
/// be 3 dB away).
#[test]
fn the_noise_ceiling_is_what_the_truth_scores() {
    let run = run_file("\"ball.vdb\"", "iterations = 1")
        .replace("target_spp = 256", "target_spp = 2048")
        .replace("eval_spp = 128", "eval_spp = 8");
    let dir = fixture(&run);
    let d = dir.path();
    ok(volgrad_in(
        d,
        &["optimize", "run.toml", "--out", "out", "-q"],
    ));
    let rows = log(&d.join("out"));
    let psnr: f64 = rows[0]["heldout_psnr"].parse().unwrap();
    let ceiling: f64 = rows[0]["heldout_noise_psnr"].parse().unwrap();
    assert!(
        (psnr - ceiling).abs() < 1.0,
        "the truth scores {psnr} dB, the ceiling says {ceiling}"
    );
}

/// `eval_spp = "auto"` renders each held-out view until its noise is a tenth of its error
/// (noise_psnr at least 10 dB above psnr), or the 4,096 spp cap: the true grid, whose error is
/// the targets' own small noise, takes the cap; a fog far from the ball, whose error is large,
/// far fewer; and every evaluation of a run from the fog obeys the rule.
#[test]
fn auto_evaluation_spp_follows_the_error() {
    let evaluations = |start: &str, iterations: u32| {
        let run = run_file(start, &format!("iterations = {iterations}"))
            // Targets nearly noise free: the truth's error is well below 4,096 spp's noise.
            .replace("target_spp = 256", "target_spp = 2048")
            .replace("eval_spp = 128", "eval_spp = \"auto\"")
            .replace("eval_every = 10", "eval_every = 4");
        let dir = fixture(&run);
        ok(volgrad_in(
            dir.path(),
            &["optimize", "run.toml", "--out", "out", "-q"],
        ));
        let rows = log(&dir.path().join("out"));
        (rows.into_iter())
            .filter(|r| !r["heldout_psnr"].is_empty())
            .map(|r| {
                let get = |k: &str| r[k].parse::<f64>().unwrap();
                (
                    get("heldout_spp"),
                    get("heldout_psnr"),
                    get("heldout_noise_psnr"),
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(evaluations("\"ball.vdb\"", 1)[0].0, 4096.0);
    let fog = evaluations("0.5", 12);
    assert!(fog[0].0 < 1024.0, "{fog:?}");
    for &(spp, psnr, noise_psnr) in &fog {
        assert!(
            spp == 4096.0 || noise_psnr - psnr >= 10.0 - 1e-6,
            "{spp} spp: {psnr} dB with a noise ceiling of {noise_psnr}: {fog:?}"
        );
    }
}

/// The worked example's pictures, as Blender's Cycles wrote them: every 8-bit sRGB PNG with alpha,
/// decoded and composited over the sky, is the linear EXR of the same render to 0.5 % in the mean
/// of each channel (read as linear, the PNGs would be several times brighter); the run file loads
/// 24 training views and 16 held-out ones, 8 of them relit, and so do the example's other run
/// files.
#[test]
fn the_worked_examples_pngs_decode_to_its_exrs() {
    use volgrad::optimize::problem::Problem;
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/capture");
    let load = |name: &str| {
        Problem::load(&repo.join(name), None, false, None, &Cluster::single()).unwrap()
    };
    let (png, exr) = (load("plume.toml"), load("plume-exr.toml"));
    // The worked example's other runs load too: the ceiling, the floor, the unknown exposure.
    for name in [
        "plume-ceiling.toml",
        "plume-floor.toml",
        "plume-exposure.toml",
    ] {
        assert_eq!(load(name).views.len(), 24, "{name}");
    }
    assert_eq!((png.views.len(), png.holdouts.len()), (24, 16));
    assert_eq!(png.holdouts.iter().filter(|v| v.relit).count(), 8);
    for (a, b) in png
        .views
        .iter()
        .zip(&exr.views)
        .chain(png.holdouts.iter().zip(&exr.holdouts))
    {
        let (a, b) = (a.target.mean(), b.target.mean());
        for c in 0..3 {
            assert!((a[c] / b[c] - 1.0).abs() < 0.005, "PNG {a} against EXR {b}");
        }
    }
}

/// `--iterations 0` evaluates the start and writes it: with the truth as the start, its row is
/// the held-out views' ceiling, and final.vdb is the truth's voxels, untouched.
#[test]
fn zero_iterations_evaluate_the_start_and_write_it() {
    let dir = fixture(&run_file("\"ball.vdb\"", ""));
    let d = dir.path();
    ok(volgrad_in(
        d,
        &[
            "optimize",
            "run.toml",
            "--iterations",
            "0",
            "--out",
            "out",
            "-q",
        ],
    ));
    let rows = log(&d.join("out"));
    assert_eq!(rows.len(), 1);
    assert!(rows[0]["heldout_psnr"].parse::<f64>().unwrap() > 20.0);
    use volgrad::io::vdb::{read_grid, GridSelector};
    let read = |p: &Path| read_grid(p, &GridSelector::Default).unwrap().bricks;
    let (written, truth) = (read(&d.join("out/final.vdb")), read(&d.join("ball.vdb")));
    let (lo, hi) = truth.active_bounds().unwrap();
    for x in lo.x..=hi.x {
        for y in lo.y..=hi.y {
            for z in lo.z..=hi.z {
                let v = glam::IVec3::new(x, y, z);
                assert_eq!(written.voxel(v), truth.voxel(v), "{v}");
            }
        }
    }
}
