//! The library's layers, as `src/lib.rs` states them: volume < io < render < gradient < compare <
//! optimize, with the binary's `cli` on top. A file may use its own layer and the layers below it, never one
//! above: this test reads every source file and fails on a `crate::<layer>` (or `volgrad::<layer>`
//! from the binary) that points upward.

use std::path::{Path, PathBuf};

const LAYERS: [&str; 7] = [
    "volume", "io", "render", "gradient", "compare", "optimize", "cli",
];

fn rank(layer: &str) -> Option<usize> {
    LAYERS.iter().position(|&l| l == layer)
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The layers a source text names through `crate::x` or `volgrad::x` paths.
fn layers_used(text: &str) -> Vec<&'static str> {
    let mut used = Vec::new();
    for prefix in ["crate::", "volgrad::"] {
        for (i, _) in text.match_indices(prefix) {
            let rest = &text[i + prefix.len()..];
            let name: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if let Some(&layer) = LAYERS.iter().find(|&&l| l == name) {
                used.push(layer);
            }
        }
    }
    used
}

#[test]
fn no_layer_uses_a_layer_above_it() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut checked = 0;
    let mut violations = Vec::new();
    for file in &files {
        let relative = file.strip_prefix(&src).unwrap();
        let Some(layer) = relative
            .components()
            .next()
            .and_then(|c| c.as_os_str().to_str())
            .and_then(rank)
        else {
            continue; // lib.rs and main.rs sit above every layer
        };
        checked += 1;
        let text = std::fs::read_to_string(file).unwrap();
        for used in layers_used(&text) {
            if rank(used).unwrap() > layer {
                violations.push(format!("{} uses {used}", relative.display()));
            }
        }
    }
    assert!(checked > 30, "only {checked} files found under src/");
    assert!(violations.is_empty(), "upward uses: {violations:#?}");
}

#[test]
fn the_check_sees_an_upward_use() {
    let text = "use crate::gradient::fd;\nlet x = volgrad::compare::Row;\n";
    assert_eq!(layers_used(text), ["gradient", "compare"]);
    assert!(layers_used("use crate::volumes::x; // crate::iox").is_empty());
}
