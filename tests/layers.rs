//! The library's layers, as `src/lib.rs` states them: volume < io < render < capture < gradient <
//! cluster < compare < optimize, with the binary's `cli` on top. A file may use its own layer and
//! the layers below it, never one above: this test reads every source file and fails on a
//! `crate::<layer>` (or `volgrad::<layer>` from the binary) path that points upward, grouped
//! imports (`use crate::{io::vdb, render::scene}`) included. Inside the `volume` and `render`
//! layers the modules read bottom-up too: the modules each file names through
//! `crate::<layer>::<module>` must form no cycle.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

const LAYERS: [&str; 9] = [
    "volume", "io", "render", "capture", "gradient", "cluster", "compare", "optimize", "cli",
];

/// Layers whose modules must not import each other in a circle.
const ACYCLIC_LAYERS: [&str; 2] = ["volume", "render"];

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

fn is_ident(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'_'
}

/// Skips whitespace and `//` comments (rustfmt keeps comments inside import groups).
fn skip_blank(s: &[u8], i: &mut usize) {
    loop {
        while *i < s.len() && s[*i].is_ascii_whitespace() {
            *i += 1;
        }
        if s[*i..].starts_with(b"//") {
            while *i < s.len() && s[*i] != b'\n' {
                *i += 1;
            }
        } else {
            return;
        }
    }
}

/// The paths of the use tree (or plain path) that starts at `s[*i]`, each as its segments:
/// `a::b` gives `[a, b]`, `a::{b, c::{d, e as f}}` gives `[a, b]`, `[a, c, d]`, `[a, c, e]`.
fn use_tree(s: &[u8], i: &mut usize) -> Vec<Vec<String>> {
    skip_blank(s, i);
    if *i < s.len() && s[*i] == b'{' {
        *i += 1;
        let mut paths = Vec::new();
        loop {
            skip_blank(s, i);
            if *i >= s.len() {
                return paths;
            }
            if s[*i] == b'}' {
                *i += 1;
                return paths;
            }
            paths.extend(use_tree(s, i));
            // Past what follows the tree (` as alias`) to the next item or the group's end.
            while *i < s.len() && s[*i] != b',' && s[*i] != b'}' {
                *i += 1;
            }
            if *i < s.len() && s[*i] == b',' {
                *i += 1;
            }
        }
    }
    let start = *i;
    while *i < s.len() && (is_ident(s[*i]) || s[*i] == b'*') {
        *i += 1;
    }
    if *i == start {
        return Vec::new();
    }
    let segment = String::from_utf8_lossy(&s[start..*i]).into_owned();
    if !s[*i..].starts_with(b"::") {
        return vec![vec![segment]];
    }
    *i += 2;
    let rest = use_tree(s, i);
    if rest.is_empty() {
        return vec![vec![segment]];
    }
    rest.into_iter()
        .map(|path| std::iter::once(segment.clone()).chain(path).collect())
        .collect()
}

/// Every path the text names after `prefix` (`crate::`, `volgrad::`, `super::`), grouped imports
/// expanded, without the prefix.
fn paths_after(text: &str, prefix: &str) -> Vec<Vec<String>> {
    let s = text.as_bytes();
    let mut paths = Vec::new();
    for (at, _) in text.match_indices(prefix) {
        if at > 0 && is_ident(s[at - 1]) {
            continue; // `foocrate::`, not `crate::`
        }
        let mut i = at + prefix.len();
        paths.extend(use_tree(s, &mut i));
    }
    paths
}

/// The layers a source text names through `crate::x` or `volgrad::x` paths, grouped ones included.
fn layers_used(text: &str) -> Vec<&'static str> {
    let mut used = Vec::new();
    for prefix in ["crate::", "volgrad::"] {
        for path in paths_after(text, prefix) {
            if let Some(&layer) = LAYERS.iter().find(|&&l| l == path[0]) {
                used.push(layer);
            }
        }
    }
    used
}

/// The layers above `layer` that a file of it names.
fn upward_uses(layer: &str, text: &str) -> Vec<&'static str> {
    let own = rank(layer).unwrap();
    layers_used(text)
        .into_iter()
        .filter(|&used| rank(used).unwrap() > own)
        .collect()
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
            .filter(|&l| rank(l).is_some())
        else {
            continue; // lib.rs and main.rs sit above every layer
        };
        checked += 1;
        let text = std::fs::read_to_string(file).unwrap();
        for used in upward_uses(layer, &text) {
            violations.push(format!("{} uses {used}", relative.display()));
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

#[test]
fn the_check_sees_grouped_imports() {
    let text = "use crate::{\n    // the scene\n    io::vdb,\n    render::{scene::Scene, path::{self, trace}},\n    volume::brickmap as bricks,\n};\n";
    assert_eq!(
        layers_used(text),
        ["io", "render", "render", "render", "volume"]
    );
    // A file of the volume layer with that import uses two layers above it (render thrice).
    assert_eq!(
        upward_uses("volume", text),
        ["io", "render", "render", "render"]
    );
    assert_eq!(upward_uses("render", text), Vec::<&str>::new());
    let binary = "use volgrad::{io::vdb, optimize::{run_file::RunFile as R}};";
    assert_eq!(upward_uses("compare", binary), ["optimize"]);
}

/// The modules of `layer` (among `modules`) that a file of it names through
/// `crate::<layer>::<module>` or `super::<module>` paths, grouped ones included.
fn modules_used(layer: &str, text: &str, modules: &[String]) -> Vec<String> {
    let mut used: Vec<String> = paths_after(text, "crate::")
        .into_iter()
        .filter(|path| path.len() > 1 && path[0] == layer)
        .map(|path| path[1].clone())
        .chain(
            paths_after(text, "super::")
                .into_iter()
                .map(|path| path[0].clone()),
        )
        .filter(|module| modules.contains(module))
        .collect();
    used.sort();
    used.dedup();
    used
}

/// A cycle of the graph (module → modules it uses), as the modules along it, if there is one.
fn find_cycle(graph: &BTreeMap<String, Vec<String>>) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        graph: &BTreeMap<String, Vec<String>>,
        done: &mut Vec<String>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node.to_string());
            return Some(cycle);
        }
        if done.iter().any(|n| n == node) {
            return None;
        }
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, graph, done, path) {
                return Some(cycle);
            }
        }
        path.pop();
        done.push(node.to_string());
        None
    }
    let (mut done, mut path) = (Vec::new(), Vec::new());
    graph
        .keys()
        .find_map(|node| visit(node, graph, &mut done, &mut path))
}

/// The modules of `src/<layer>/` (files directly in it, `mod.rs` aside) and whom each uses.
fn module_graph(layer: &str) -> BTreeMap<String, Vec<String>> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("src")
        .join(layer);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "rs") && !p.ends_with("mod.rs"))
        .collect();
    files.sort();
    let modules: Vec<String> = files
        .iter()
        .map(|p| p.file_stem().unwrap().to_str().unwrap().to_string())
        .collect();
    files
        .iter()
        .zip(&modules)
        .map(|(file, module)| {
            let text = std::fs::read_to_string(file).unwrap();
            let mut used = modules_used(layer, &text, &modules);
            used.retain(|m| m != module);
            (module.clone(), used)
        })
        .collect()
}

#[test]
fn the_modules_of_a_layer_form_no_cycle() {
    for layer in ACYCLIC_LAYERS {
        let graph = module_graph(layer);
        assert!(
            graph.len() > 5,
            "only {} modules in src/{layer}/",
            graph.len()
        );
        if let Some(cycle) = find_cycle(&graph) {
            panic!(
                "src/{layer}/ modules import each other in a circle: {}",
                cycle.join(" -> ")
            );
        }
    }
}

#[test]
fn the_cycle_check_sees_a_cycle() {
    let modules: Vec<String> = ["a", "b", "c"].map(String::from).to_vec();
    let uses = |text: &str| modules_used("volume", text, &modules);
    assert_eq!(
        uses("use crate::volume::{a::X, b::{self, Y}};\nuse super::c::Z;\nuse super::*;"),
        ["a", "b", "c"]
    );
    assert_eq!(uses("use crate::{io::vdb, volume::{c::Z}};"), ["c"]);
    let graph = |edges: &[(&str, &str)]| {
        let mut g = BTreeMap::<String, Vec<String>>::new();
        for (from, to) in edges {
            g.entry(from.to_string()).or_default().push(to.to_string());
        }
        g
    };
    assert_eq!(
        find_cycle(&graph(&[("a", "b"), ("b", "c"), ("a", "c")])),
        None
    );
    assert_eq!(
        find_cycle(&graph(&[("a", "b"), ("b", "c"), ("c", "a")])).unwrap(),
        ["a", "b", "c", "a"]
    );
}
