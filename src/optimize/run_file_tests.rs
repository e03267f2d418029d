//! Tests of `run_file`: parsing, defaults and refusals of a run file's keys.

use super::*;
use crate::gradient::loss::Loss;
use crate::optimize::prior::PriorKind;

const GOOD: &str = r#"
        scene = "s.toml"
        truth = "t.vdb"
        [views.orbit]
        count = 4
        elevation_deg = [0, 45]
        distance = 10
        fov_deg = 40
        width = 8
        height = 8
        [[holdout]]
        position = [0, 0, 10]
        target = [0, 0, 0]
        fov_deg = 40
        width = 8
        height = 8
        [unknown]
        bounds = "truth"
        start = 0.1
        levels = [0.5]
    "#;

fn check(text: &str) -> Result<RunFile> {
    let file: RunFile = toml::from_str(text).map_err(|e| anyhow::anyhow!("{e}"))?;
    file.validate()?;
    Ok(file)
}

#[test]
fn a_good_file_parses_with_defaults() {
    let f = check(GOOD).unwrap();
    assert_eq!(f.optimizer.batch, None);
    assert_eq!(f.optimizer.prior.len(), 2, "the default priors");
    assert_eq!(f.optimizer.loss, Loss::L2);
    assert_eq!(f.unknown.moments, Moments::Resample);
    assert_eq!(f.eval_spp, EvalSpp::Auto);
}

/// `eval_spp` is a positive number or "auto", and writes back as it was read.
#[test]
fn eval_spp_is_a_number_or_auto() {
    let with = |value: &str| check(&format!("eval_spp = {value}\n{GOOD}"));
    assert_eq!(with("512").unwrap().eval_spp, EvalSpp::Fixed(512));
    assert_eq!(with("\"auto\"").unwrap().eval_spp, EvalSpp::Auto);
    for bad in ["0", "-3", "\"many\"", "2.5"] {
        assert!(with(bad).is_err(), "eval_spp = {bad} accepted");
    }
    for spp in [EvalSpp::Auto, EvalSpp::Fixed(64)] {
        let text = toml::to_string(&RunFile {
            eval_spp: spp,
            ..check(GOOD).unwrap()
        })
        .unwrap();
        assert_eq!(check(&text).unwrap().eval_spp, spp, "{text}");
    }
}

/// `[[holdouts]]` gives several sets, each under its own lights; one `[holdouts]` table is one
/// set, and none is one empty set. A set's errors name it by its place.
#[test]
fn view_sets_are_a_table_or_several() {
    assert_eq!(check(GOOD).unwrap().holdouts.len(), 1);
    let relit = "[{ type = \"constant\", radiance = 0.5 }]";
    let two = format!(
            "{GOOD}\n[[holdouts]]\ntransforms = \"a.json\"\n[[holdouts]]\ntransforms = \"b.json\"\nlight = {relit}\n"
        );
    let f = check(&two).unwrap();
    assert_eq!(f.holdouts.len(), 2);
    assert!(f.holdouts[0].light.is_empty() && f.holdouts[1].light.len() == 1);
    assert_eq!(f.holdouts[1].transforms.as_deref(), Some("b.json"));
    let one = format!("{GOOD}\n[holdouts]\ntransforms = \"a.json\"\n");
    assert_eq!(check(&one).unwrap().holdouts.len(), 1);
    let bad = two.replace("radiance = 0.5", "radiance = -1");
    let error = format!("{:#}", check(&bad).unwrap_err());
    assert!(error.contains("holdouts[1].light"), "{error}");
}

/// Each bad value is refused with a message naming its key.
#[test]
fn bad_values_name_their_key() {
    let optimizer = |line: &str| format!("{GOOD}\n[optimizer]\n{line}");
    let cases = [
            (GOOD.replace("[views.orbit]", "[x.orbit]"), "unknown field"),
            (optimizer("lr = 0"), "optimizer.lr"),
            (optimizer("lr = -1"), "optimizer.lr"),
            (optimizer("batch = 0"), "optimizer.batch"),
            (optimizer("primal_spp = 0"), "optimizer.primal_spp"),
            (optimizer("suffix_paths = 0"), "optimizer.suffix_paths"),
            (optimizer("suffix_paths = 65"), "optimizer.suffix_paths"),
            (optimizer("brick_scale_lr = 0"), "optimizer.brick_scale_lr"),
            (optimizer("loss = \"mean\""), "optimizer.loss"),
            (optimizer("loss = \"l3\""), "unknown variant"),
            (optimizer("beta2 = 1"), "optimizer.beta2"),
            (optimizer("level_lr = 0"), "optimizer.level_lr"),
            (optimizer("prior = { kind = \"tvv\", weight = 1 }"), "unknown variant"),
            (optimizer("prior = { kind = \"log\", weight = 1 }"), "optimizer.prior.scale"),
            (optimizer("prior = { kind = \"log\", weight = 1, scale = 0 }"), "optimizer.prior.scale"),
            (optimizer("prior = { kind = \"log\", weight = 1, scale = 1e-45 }"), "optimizer.prior.scale"),
            (optimizer("prior = [{ kind = \"tv\", weight = 1, scale = 0.1 }]"), "optimizer.prior.scale"),
            (optimizer("prior = [{ kind = \"tv\", weight = -1 }]"), "optimizer.prior.weight"),
            (
                GOOD.replace("levels = [0.5]", "levels = [0.5, 0.4]"),
                "unknown.levels",
            ),
            (
                GOOD.replace("levels = [0.5]", "levels = [1.0]"),
                "unknown.levels",
            ),
            (GOOD.replace("start = 0.1", "start = -1"), "unknown.start"),
            (
                GOOD.replace("start = 0.1", "start = 0.1\nstart_voxel_size = nan"),
                "unknown.start_voxel_size",
            ),
            (
                GOOD.replace("levels = [0.5]", "levels = [0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.10, 0.11, 0.12, 0.13, 0.14, 0.15, 0.16, 0.17, 0.18, 0.19, 0.20, 0.21, 0.22, 0.23, 0.24, 0.25, 0.26, 0.27, 0.28, 0.29, 0.30, 0.31, 0.32, 0.33, 0.34, 0.35, 0.36, 0.37, 0.38, 0.39, 0.40]"),
                "at most",
            ),
            (
                GOOD.replace("width = 8\n        height = 8\n        [[holdout]]", "width = 2147483648\n        height = 2147483648\n        [[holdout]]"),
                "pixels",
            ),
            (
                GOOD.replace("start = 0.1", "start = 0.1\ncarve = true\ngrid = \"emission\""),
                "unknown.carve",
            ),
            (
                GOOD.replace("start = 0.1", "start = \"s.vdb\"\ncarve = true"),
                "unknown.carve",
            ),
            (
                GOOD.replace("bounds = \"truth\"", "bounds = \"all\""),
                "unknown.bounds",
            ),
            (
                GOOD.replace(
                    "bounds = \"truth\"",
                    "bounds = { min = [0,0,0], max = [1,1,1] }",
                ),
                "unknown.voxel_size",
            ),
            (
                GOOD.replace(
                    "bounds = \"truth\"",
                    "bounds = { min = [0,0,0], max = [0,1,1] }\nvoxel_size = 0.1",
                ),
                "unknown.bounds",
            ),
            // The final voxel size of bounds = "truth" or "start" is that grid's.
            (
                GOOD.replace("bounds = \"truth\"", "bounds = \"truth\"\nvoxel_size = 0.5"),
                "unknown.voxel_size",
            ),
            (
                GOOD.replace("bounds = \"truth\"", "bounds = \"start\"\nvoxel_size = 0.5")
                    .replace("start = 0.1", "start = \"s.vdb\""),
                "unknown.voxel_size",
            ),
            (GOOD.replace("truth = \"t.vdb\"", ""), "truth"),
            (
                GOOD.replace("[views.orbit]", "[holdouts.orbit]"),
                "no views",
            ),
            (GOOD.replace("[[holdout]]", "[[view]]"), "no held-out views"),
            (format!("target_spp = 0\n{GOOD}"), "target_spp"),
            (
                GOOD.replace(
                    "        [[holdout]]",
                    "        light = [{ type = \"directional\", direction = [0, 0, 0], irradiance = 1 }]\n        [[holdout]]",
                ),
                "views.orbit[0]: light[0].direction",
            ),
            (
                GOOD.replace(
                    "        [[holdout]]",
                    "        light = [{ type = \"sun\" }]\n        [[holdout]]",
                ),
                "unknown variant",
            ),
            (
                GOOD.replace("count = 4", "count = 4294967295"),
                "4294967295 views (listed and on orbits): at most 10000",
            ),
            (
                GOOD.replace("count = 4", "count = 9000").replace(
                    "width = 8\n        height = 8\n        [[holdout]]",
                    "width = 256\n        height = 256\n        [[holdout]]",
                ),
                "at most 2^28",
            ),
            (format!("colour = 1\n{GOOD}"), "unknown field"),
            (format!("eval_every = 0\n{GOOD}"), "eval_every"),
        ];
    for (text, key) in cases {
        let err = format!("{:#}", check(&text).unwrap_err());
        assert!(err.contains(key), "expected '{key}' in: {err}");
    }
}

/// A typo'd key in any table of a run file is refused with the key named: the top level,
/// views, an orbit, a listed view, its light, the unknown and its box, the optimizer and a
/// prior (a box with `mxa` was once read as the first form that fits, or as no form at all).
#[test]
fn a_typo_in_any_table_is_refused_by_name() {
    let prior = "prior = { kind = \"tv\", weight = 1 }";
    let light = "light = [{ type = \"constant\", radiance = 1 }]";
    let cases = [
            ("scene = ", "scen = 1\n        scene = ", "scen"),
            ("[views.orbit]", "[views]\n        orbitt = 1\n        [views.orbit]", "orbitt"),
            ("count = 4", "count = 4\n        cont = 4", "cont"),
            ("[[holdout]]", "[[holdout]]\n        imge = \"x.exr\"", "imge"),
            ("[[holdout]]", "[[holdout]]\n        light = [{ type = \"constant\", radiance = 1, scale = 2 }]", "scale"),
            ("start = 0.1", "start = 0.1\n        strat = 0.2", "strat"),
            ("bounds = \"truth\"", "bounds = { min = [0, 0, 0], max = [1, 1, 1], mxa = 2 }\n        voxel_size = 0.1", "mxa"),
            ("levels = [0.5]", "levels = [0.5]\n        [optimizer]\n        lrr = 1", "lrr"),
            ("levels = [0.5]", "levels = [0.5]\n        [optimizer]\n        prior = { kind = \"tv\", weight = 1, wieght = 2 }", "wieght"),
        ];
    check(&GOOD.replace(
        "levels = [0.5]",
        &format!("levels = [0.5]\n[optimizer]\n{prior}"),
    ))
    .unwrap();
    check(&GOOD.replace("[[holdout]]", &format!("[[holdout]]\n{light}"))).unwrap();
    check(&GOOD.replace(
        "bounds = \"truth\"",
        "bounds = { min = [0, 0, 0], max = [1, 1, 1] }\nvoxel_size = 0.1",
    ))
    .unwrap();
    for (from, to, key) in cases {
        assert!(GOOD.contains(from), "{from}");
        let err = format!("{:#}", check(&GOOD.replacen(from, to, 1)).unwrap_err());
        assert!(
            err.contains(&format!("unknown field `{key}`")),
            "{key}: {err}"
        );
    }
}

#[test]
fn one_prior_or_several_or_none() {
    let priors = |text: &str| check(text).unwrap().optimizer.prior;
    let one = priors(&format!(
        "{GOOD}\n[optimizer]\nprior = {{ kind = \"tv\", weight = 0.5 }}"
    ));
    assert_eq!(one.len(), 1);
    assert_eq!((one[0].kind, one[0].weight), (PriorKind::Tv, 0.5));
    let two = priors(&format!(
            "{GOOD}\n[optimizer]\nprior = [{{ kind = \"tv\", weight = 0.5 }}, {{ kind = \"log\", weight = 2, scale = 0.01 }}]"
        ));
    assert_eq!(two.len(), 2);
    assert_eq!(
        (two[1].kind, two[1].weight, two[1].scale),
        (PriorKind::Log, 2.0, Some(0.01))
    );
    assert!(priors(&format!("{GOOD}\n[optimizer]\nprior = []")).is_empty());
}

#[test]
fn levels_must_reach_the_final_voxel_size() {
    let mut f = check(GOOD).unwrap();
    f.unknown.start_voxel_size = Some(2.0);
    f.unknown.check_levels_reach(1, 1.0).unwrap();
    let err = f
        .unknown
        .check_levels_reach(1, 0.5)
        .unwrap_err()
        .to_string();
    assert!(err.contains("unknown.levels"), "{err}");
}

/// A key the rest of the file leaves without effect is refused, naming what idles it; the same key
/// where it acts is accepted; settings.toml, which writes every key a run resolved, leaves the
/// idle ones out and loads again.
#[test]
fn keys_without_effect_are_refused_and_left_out_of_settings() {
    let read = |text: &str| -> Result<RunFile> {
        let mut file = check(text)?;
        file.given = toml::from_str(text)?;
        crate::optimize::idle_keys::refuse_given(&file)?;
        Ok(file)
    };
    let optimizer = |lines: &str| format!("{GOOD}\n[optimizer]\n{lines}");
    let no_levels = GOOD.replace("levels = [0.5]", "levels = []");
    let camera = "position = [0, 0, 10]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8";
    let by_pictures = format!(
        "scene = \"s.toml\"\ntruth = \"t.vdb\"\ntarget_spp = 64\n[[view]]\nimage = \"a.png\"\n{camera}\n\
         [[holdout]]\nimage = \"b.png\"\n{camera}\n[unknown]\nbounds = \"truth\"\nstart = 0.1"
    );
    let cases = [
        (
            optimizer("fit_brick_scales = false\nbrick_scale_lr = 2"),
            "optimizer.brick_scale_lr",
            "fit_brick_scales = false",
        ),
        (
            optimizer("smooth_gradient = false\nfirst_level_smoothing = 2"),
            "optimizer.first_level_smoothing",
            "smooth_gradient = false",
        ),
        (
            format!("{no_levels}\n[optimizer]\nlevel_lr = 0.7"),
            "optimizer.level_lr",
            "unknown.levels = []",
        ),
        (
            no_levels.replace("start = 0.1", "start = 0.1\nmoments = \"reset\""),
            "unknown.moments",
            "unknown.levels = []",
        ),
        (
            by_pictures.clone(),
            "target_spp",
            "every view has its picture",
        ),
    ];
    for (text, key, because) in cases {
        let err = format!("{:#}", read(&text).unwrap_err());
        let named = err.contains(&format!("{key} has no effect here ("));
        assert!(named && err.contains(because), "{err}");
    }
    for text in [
        optimizer("brick_scale_lr = 2"),
        optimizer("first_level_smoothing = 2"),
        optimizer("level_lr = 0.7"),
        GOOD.replace("start = 0.1", "start = 0.1\nmoments = \"reset\""),
        format!("target_spp = 64\n{GOOD}"),
        by_pictures.replace("target_spp = 64\n", ""),
    ] {
        read(&text).unwrap();
    }
    let mut file = read(&format!(
        "{no_levels}\n[optimizer]\nfit_brick_scales = false\nsmooth_gradient = false"
    ))
    .unwrap();
    file.optimizer.first_level_smoothing = Some(1); // as a run resolves it
    let written = crate::optimize::settings_toml::resolved(&file, Path::new("/r/run.toml"), "");
    let written = written.unwrap();
    for key in [
        "brick_scale_lr",
        "first_level_smoothing",
        "level_lr",
        "moments",
    ] {
        assert!(!written.contains(key), "{key} written: {written}");
    }
    read(&written).unwrap();
}
