//! Keeps the manual (`docs/`, and the front page `README.md`) true to the code:
//!
//! - every ```toml block is marked with what it claims to be (`<!-- scene -->`, `<!-- scene: PATH
//!   -->`, `<!-- run -->` or `<!-- fragment -->` on the line before it) and parses as that: a scene
//!   file (and, given a PATH, loads there: the files it names exist), a run file (parsed and
//!   validated), or at least valid TOML;
//! - every key and every named value that scene and run files accept — read from the code's own
//!   "unknown field … expected one of …" errors, so a new key cannot be missed — appears in the
//!   reference pages, and so does every `log.csv` column;
//! - every relative link and image points at a file inside the repository, and every `#anchor` at
//!   a heading of its page.
//!
//! The command lines of ```sh blocks are checked by the binary's own tests
//! (`src/cli/manual_tests.rs`: the parser lives in the binary).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use volgrad::optimize::log::COLUMNS;
use volgrad::optimize::run_file::RunFile;
use volgrad::render::scene::Scene;
use volgrad::render::scene_file::SceneFile;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The manual's pages: `docs/*.md` and the front page.
fn pages() -> Vec<(PathBuf, String)> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(repo().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    paths.push(repo().join("README.md"));
    paths.sort();
    assert!(paths.len() > 10, "docs/ has its pages");
    paths
        .into_iter()
        .map(|p| {
            let text = std::fs::read_to_string(&p).unwrap();
            (p, text)
        })
        .collect()
}

/// A fenced block: its language, its text, the line before its opening fence, and where it is.
struct Block {
    lang: String,
    text: String,
    marker: String,
    line: usize,
}

fn blocks(text: &str) -> Vec<Block> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let fence = lines[i].trim_start();
        if let Some(lang) = fence.strip_prefix("```") {
            let start = i;
            let mut body = Vec::new();
            i += 1;
            while i < lines.len() && !lines[i].trim_start().starts_with("```") {
                body.push(lines[i]);
                i += 1;
            }
            let marker = if start > 0 {
                lines[start - 1].trim()
            } else {
                ""
            };
            out.push(Block {
                lang: lang.trim().to_string(),
                text: body.join("\n"),
                marker: marker.to_string(),
                line: start + 1,
            });
        }
        i += 1;
    }
    out
}

/// Checks one ```toml block against its marker; an error names what is wrong.
fn check_toml_block(block: &Block) -> Result<&'static str, String> {
    let marker = block
        .marker
        .strip_prefix("<!--")
        .and_then(|m| m.strip_suffix("-->"))
        .map(str::trim)
        .ok_or("no <!-- scene | scene: PATH | run | fragment --> marker on the line before")?;
    let (kind, place) = match marker.split_once(':') {
        Some((k, p)) => (k.trim(), Some(p.trim())),
        None => (marker, None),
    };
    match kind {
        "scene" => {
            let file: SceneFile =
                toml::from_str(&block.text).map_err(|e| format!("not a scene file: {e}"))?;
            match place {
                // Loads it where the page says to save it: every file it names must exist.
                Some(path) => {
                    Scene::from_file(file, &repo().join(path))
                        .map_err(|e| format!("does not load as {path}: {e:#}"))?;
                }
                None => file
                    .validate()
                    .map_err(|e| format!("not a valid scene: {e:#}"))?,
            }
            Ok("scene")
        }
        "run" => {
            let file: RunFile =
                toml::from_str(&block.text).map_err(|e| format!("not a run file: {e}"))?;
            file.validate()
                .map_err(|e| format!("not a valid run file: {e:#}"))?;
            Ok("run")
        }
        "fragment" => {
            toml::from_str::<toml::Table>(&block.text).map_err(|e| format!("not TOML: {e}"))?;
            Ok("fragment")
        }
        other => Err(format!("unknown marker '{other}'")),
    }
}

#[test]
fn every_toml_block_parses_as_what_it_claims_to_be() {
    let mut counts = std::collections::BTreeMap::new();
    let mut errors = Vec::new();
    for (path, text) in pages() {
        for block in blocks(&text).iter().filter(|b| b.lang == "toml") {
            match check_toml_block(block) {
                Ok(kind) => *counts.entry(kind).or_insert(0) += 1,
                Err(e) => errors.push(format!("{}:{}: {e}", path.display(), block.line)),
            }
        }
    }
    assert!(errors.is_empty(), "{}", errors.join("\n"));
    assert!(counts.get("scene").copied().unwrap_or(0) >= 1, "{counts:?}");
    assert!(counts.get("run").copied().unwrap_or(0) >= 2, "{counts:?}");
}

/// The checks have teeth: a wrong key, a wrong marker, a missing file and a run file without
/// held-out views are each refused.
#[test]
fn the_toml_check_refuses_what_is_wrong() {
    let block = |marker: &str, text: &str| Block {
        lang: "toml".into(),
        text: text.into(),
        marker: marker.into(),
        line: 1,
    };
    let scene = std::fs::read_to_string(repo().join("scenes/cloud.toml")).unwrap();
    assert_eq!(
        check_toml_block(&block("<!-- scene -->", &scene)),
        Ok("scene")
    );
    let cases = [
        ("", scene.clone()),
        ("<!-- run -->", scene.clone()),
        ("<!-- scene -->", scene.replace("phase_g", "phase")),
        ("<!-- scene: scenes/x.toml -->", scene.replace("assets/", "nowhere/")),
        ("<!-- scene -->", scene.replace("phase_g       = 0.5", "phase_g = 1.5")),
        ("<!-- fragment -->", "a = ".to_string()),
        (
            "<!-- run -->",
            "scene = \"s.toml\"\ntruth = \"t.vdb\"\n[views.orbit]\ncount = 2\nelevation_deg = [0, 10]\ndistance = 5\nfov_deg = 40\nwidth = 8\nheight = 8\n[unknown]\nbounds = \"truth\"\n".to_string(),
        ),
    ];
    for (marker, text) in cases {
        assert!(
            check_toml_block(&block(marker, &text)).is_err(),
            "accepted: {marker}"
        );
    }
}

/// The names in an error's "expected `a`, `b` or `c`" (serde's unknown field and unknown variant
/// messages).
fn expected_names(error: &str) -> Vec<String> {
    let tail = error
        .split_once("expected")
        .map(|(_, t)| t)
        .unwrap_or_else(|| panic!("no list of names in: {error}"));
    let tail = tail.lines().next().unwrap_or_default();
    tail.split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect()
}

fn parse_scene(text: &str) -> Result<(), String> {
    toml::from_str::<SceneFile>(text)
        .map(|_| ())
        .map_err(|e| e.to_string())
}

fn parse_run(text: &str) -> Result<(), String> {
    toml::from_str::<RunFile>(text)
        .map(|_| ())
        .map_err(|e| e.to_string())
}

/// A scene with every table; `@SLOT@` marks where a key or value may be injected.
const SCENE: &str = "@TOP@[camera]\n@CAMERA@position = [0, 0, 5]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n\
     [medium]\n@MEDIUM@vdb = \"m.vdb\"\nalbedo = { grid = \"Cd\" @AL@ }\n\
     emission = { grid = \"t\", blackbody = { scale = 1000 @BB@ } @EM@ }\n\
     filter = @FILTER@\nlevelset = @LEVELSET@\n\
     [[light]]\n@LIGHT@\n\
     [render]\n@RENDER@majorant = @MAJORANT@\n";

/// A run file with every table.
const RUN: &str = "scene = \"s.toml\"\ntruth = \"t.vdb\"\n@TOP@\n\
     [[view]]\nposition = [0, 0, 5]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n@VIEW@\n\
     [views]\ncolor_space = @CS@\n@VIEWS@\n\
     [views.orbit]\ncount = 2\nelevation_deg = [0, 10]\ndistance = 5\nfov_deg = 40\nwidth = 8\nheight = 8\n@ORBIT@\n\
     [views.colmap]\nmodel = \"m\"\n@COLMAP@\n\
     [[holdout]]\nposition = [0, 0, 5]\ntarget = [0, 0, 0]\nfov_deg = 40\nwidth = 8\nheight = 8\n\
     [unknown]\nbounds = { min = [0, 0, 0], max = [1, 1, 1] @BOUNDS@ }\nvoxel_size = 0.1\n\
     grid = @GRID@\nmoments = @MOMENTS@\n@UNKNOWN@\n\
     [optimizer]\nloss = @LOSS@\nprior = { kind = @KIND@, weight = 1 @PRIOR@ }\n@OPTIMIZER@\n";

/// `template` with `place` filled by `inject` and every other slot by its default.
fn fill(template: &str, defaults: &[(&str, &str)], place: &str, inject: &str) -> String {
    let mut text = template.to_string();
    for (slot, default) in defaults {
        let token = format!("@{slot}@");
        text = text.replace(&token, if *slot == place { inject } else { default });
    }
    assert!(!text.contains('@'), "{text}");
    text
}

const SCENE_SLOTS: [(&str, &str); 11] = [
    ("TOP", ""),
    ("CAMERA", ""),
    ("MEDIUM", ""),
    ("RENDER", ""),
    ("AL", ""),
    ("BB", ""),
    ("EM", ""),
    ("FILTER", "\"nearest\""),
    ("LEVELSET", "\"fog\""),
    ("LIGHT", "type = \"constant\"\nradiance = 1"),
    ("MAJORANT", "\"grid\""),
];

const RUN_SLOTS: [(&str, &str); 14] = [
    ("TOP", ""),
    ("VIEW", ""),
    ("VIEWS", ""),
    ("ORBIT", ""),
    ("COLMAP", ""),
    ("BOUNDS", ""),
    ("UNKNOWN", ""),
    ("OPTIMIZER", ""),
    ("PRIOR", ""),
    ("CS", "\"srgb\""),
    ("GRID", "\"density\""),
    ("MOMENTS", "\"reset\""),
    ("LOSS", "\"l2\""),
    ("KIND", "\"tv\""),
];

/// Every key of every table, and every named value, that scene and run files accept.
fn accepted_names() -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let key = "zz_not_a_key = 1\n";
    let inline_key = ", zz_not_a_key = 1";
    let value = "\"zz\"";
    let scene = |place: &str, inject: &str| fill(SCENE, &SCENE_SLOTS, place, inject);
    parse_scene(&scene("", "")).expect("the scene of the key census parses");
    for (place, _) in SCENE_SLOTS {
        let inject = match place {
            "AL" | "BB" | "EM" => inline_key,
            "FILTER" | "LEVELSET" | "MAJORANT" => value,
            "LIGHT" => "type = \"zz\"",
            _ => key,
        };
        let text = scene(place, inject);
        let error = parse_scene(&text).expect_err(&text);
        names.extend(expected_names(&error));
    }
    // Each light type's keys.
    for light in [
        "type = \"constant\"\nradiance = 1",
        "type = \"directional\"\ndirection = [0, -1, 0]\nirradiance = 1",
        "type = \"envmap\"\nfile = \"sky.exr\"",
    ] {
        let text = scene("LIGHT", &format!("{light}\n{key}"));
        let error = parse_scene(&text).expect_err(&text);
        names.extend(expected_names(&error));
    }
    let run = |place: &str, inject: &str| fill(RUN, &RUN_SLOTS, place, inject);
    parse_run(&run("", "")).expect("the run file of the key census parses");
    for (place, default) in RUN_SLOTS {
        let inject = match place {
            "BOUNDS" | "PRIOR" => inline_key,
            _ if !default.is_empty() => value,
            _ => key,
        };
        let text = run(place, inject);
        let error = parse_run(&text).expect_err(&text);
        names.extend(expected_names(&error));
    }
    names
}

/// Whether a reference page names `name` as code: `name` or "name".
fn documented(reference: &str, name: &str) -> bool {
    [
        format!("`{name}`"),
        format!("\"{name}\""),
        format!("[{name}]"),
        format!("[[{name}]]"),
        format!(".{name}]"),
    ]
    .iter()
    .any(|form| reference.contains(form.as_str()))
}

fn reference_pages() -> String {
    pages()
        .into_iter()
        .filter(|(p, _)| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("reference-"))
        })
        .map(|(_, text)| text)
        .collect()
}

#[test]
fn every_key_the_files_accept_is_in_the_reference() {
    let names = accepted_names();
    eprintln!("{} names accepted: {names:?}", names.len());
    assert!(names.len() >= 90, "the census is short: {names:?}");
    for must in [
        "density_scale",
        "majorant_cell",
        "step_optical_depth",
        "transforms",
        "relative-l2",
    ] {
        assert!(names.contains(must), "the census missed {must}: {names:?}");
    }
    let reference = reference_pages();
    let missing: Vec<&String> = names
        .iter()
        .filter(|n| !documented(&reference, n))
        .collect();
    assert!(
        missing.is_empty(),
        "accepted by scene or run files but not in docs/reference-*.md: {missing:?}"
    );
    let missing: Vec<&&str> = COLUMNS
        .iter()
        .filter(|c| !documented(&reference, c))
        .collect();
    assert!(
        missing.is_empty(),
        "log.csv columns not in the reference: {missing:?}"
    );
}

/// The census sees a key the reference would lack: a page without `density_scale` fails.
#[test]
fn the_key_check_would_fail_on_a_missing_key() {
    let reference = reference_pages().replace("`density_scale`", "`densty`");
    assert!(accepted_names().iter().any(|n| !documented(&reference, n)));
}

/// GitHub's anchor for a heading: lower case, letters, digits, `-` and `_` kept, spaces as `-`.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .flat_map(char::to_lowercase)
        .collect()
}

fn anchors(text: &str) -> BTreeSet<String> {
    let mut in_code = false;
    let mut out = BTreeSet::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_code = !in_code;
        } else if !in_code && line.starts_with('#') {
            out.insert(anchor(line.trim_start_matches('#')));
        }
    }
    out
}

/// Every `](target)` of a page, outside code blocks.
fn links(text: &str) -> Vec<String> {
    let mut in_code = false;
    let mut out = Vec::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_code = !in_code;
            continue;
        }
        if in_code {
            continue;
        }
        let mut rest = line;
        while let Some(i) = rest.find("](") {
            rest = &rest[i + 2..];
            if let Some(end) = rest.find(')') {
                out.push(rest[..end].to_string());
            }
        }
        // HTML images: <img src="…">
        let mut rest = line;
        while let Some(i) = rest.find("src=\"") {
            rest = &rest[i + 5..];
            if let Some(end) = rest.find('"') {
                out.push(rest[..end].to_string());
            }
        }
    }
    out
}

fn check_link(page: &Path, text: &str, target: &str) -> Result<(), String> {
    if target.starts_with("http://") || target.starts_with("https://") {
        return Ok(());
    }
    let (file, fragment) = target.split_once('#').unwrap_or((target, ""));
    let (resolved, linked_text) = if file.is_empty() {
        (page.to_path_buf(), text.to_string())
    } else {
        let path = page.parent().unwrap().join(file);
        let resolved = path
            .canonicalize()
            .map_err(|_| format!("'{target}': no such file"))?;
        let root = repo().canonicalize().unwrap();
        if !resolved.starts_with(&root) {
            return Err(format!("'{target}' leaves the repository"));
        }
        let linked = if file.ends_with(".md") {
            std::fs::read_to_string(&resolved).unwrap_or_default()
        } else {
            String::new()
        };
        (resolved, linked)
    };
    if !fragment.is_empty() && !anchors(&linked_text).contains(fragment) {
        return Err(format!(
            "'{target}': no heading #{fragment} in {}",
            resolved.display()
        ));
    }
    Ok(())
}

#[test]
fn every_link_stays_in_the_repository_and_finds_its_target() {
    let mut errors = Vec::new();
    let mut count = 0;
    for (path, text) in pages() {
        for target in links(&text) {
            count += 1;
            if let Err(e) = check_link(&path, &text, &target) {
                errors.push(format!("{}: {e}", path.display()));
            }
        }
    }
    assert!(count > 50, "{count} links");
    assert!(errors.is_empty(), "{}", errors.join("\n"));
    // And the check has teeth.
    let page = repo().join("docs/results.md");
    for bad in [
        "missing.md",
        "../../shared/docs/DESIGN.md",
        "render.md#no-such-heading",
        "#nowhere",
    ] {
        assert!(check_link(&page, "", bad).is_err(), "{bad}");
    }
    assert_eq!(
        anchor("5. Emission: fire and glowing gas"),
        "5-emission-fire-and-glowing-gas"
    );
    assert_eq!(
        anchor("The path loop's contract"),
        "the-path-loops-contract"
    );
}

/// No page of the manual is over 600 lines: split it instead.
#[test]
fn no_page_is_over_600_lines() {
    for (path, text) in pages() {
        let n = text.lines().count();
        assert!(n <= 600, "{}: {n} lines", path.display());
    }
    let front = std::fs::read_to_string(repo().join("README.md")).unwrap();
    assert!(
        front.lines().count() <= 200,
        "the front page is a front page"
    );
}
