//! Every command line of the manual parses with the command line as clap sees it: each line of a
//! ```sh block of `docs/*.md` and `README.md` that runs volgrad (`volgrad …`, `cargo run --release
//! -- …`, or volgrad under `mpirun`/`srun`). Parsing only: nothing runs. (The manual's TOML,
//! keys and links are `tests/manual.rs`'s.)

use std::path::PathBuf;

use clap::Parser;

use crate::Cli;

/// The manual's pages, with their text.
fn pages() -> Vec<(PathBuf, String)> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let mut paths: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("docs/ is readable")
        .map(|e| e.expect("a docs/ entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    paths.push(root.join("README.md"));
    paths
        .into_iter()
        .map(|p| {
            let text = std::fs::read_to_string(&p).expect("a page of the manual");
            (p, text)
        })
        .collect()
}

/// The lines of a page's ```sh blocks, with their line numbers.
fn shell_lines(text: &str) -> Vec<(usize, String)> {
    let mut in_sh = false;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let fence = line.trim_start();
        if let Some(lang) = fence.strip_prefix("```") {
            in_sh = !in_sh && (lang.trim() == "sh" || lang.trim() == "bash");
            continue;
        }
        if in_sh {
            out.push((i + 1, line.to_string()));
        }
    }
    out
}

/// A shell line split into words: quotes removed, a `#` comment dropped, `$VARIABLES` read as
/// `1` (they stand for numbers or folders the shell would fill in).
fn words(line: &str) -> Vec<String> {
    let mut words = Vec::new();
    let mut word = String::new();
    let mut quote: Option<char> = None;
    let mut in_word = false;
    for c in line.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), c) => word.push(c),
            (None, '\'' | '"') => {
                quote = Some(c);
                in_word = true;
            }
            (None, '#') if !in_word => break,
            (None, c) if c.is_whitespace() => {
                if in_word {
                    words.push(std::mem::take(&mut word));
                    in_word = false;
                }
            }
            (None, c) => {
                word.push(c);
                in_word = true;
            }
        }
    }
    if in_word {
        words.push(word);
    }
    words
        .into_iter()
        .map(|w| {
            if w.starts_with('$') {
                "1".to_string()
            } else {
                w
            }
        })
        .collect()
}

/// The volgrad command lines in a shell line (`a && b` holds two), as argv.
fn commands(line: &str) -> Vec<Vec<String>> {
    line.split("&&")
        .filter_map(|part| {
            let w = words(part);
            let first = w.first()?.as_str();
            let start = match first {
                "volgrad" => 0,
                "cargo" if w.get(1).is_some_and(|s| s == "run") => {
                    let dashes = w.iter().position(|s| s == "--")?;
                    let mut argv = vec!["volgrad".to_string()];
                    argv.extend(w[dashes + 1..].iter().cloned());
                    return Some(argv);
                }
                "mpirun" | "srun" => w.iter().position(|s| s == "volgrad")?,
                _ => return None,
            };
            Some(w[start..].to_vec())
        })
        .collect()
}

#[test]
fn every_command_line_of_the_manual_parses() {
    let mut errors = Vec::new();
    let mut parsed = 0;
    for (path, text) in pages() {
        for (n, line) in shell_lines(&text) {
            for argv in commands(&line) {
                match Cli::try_parse_from(&argv) {
                    Ok(_) => parsed += 1,
                    Err(e) => {
                        // --help and --version "fail" with their text: a documented line may ask.
                        use clap::error::ErrorKind::{DisplayHelp, DisplayVersion};
                        if !matches!(e.kind(), DisplayHelp | DisplayVersion) {
                            let first = e.to_string().lines().next().unwrap_or("").to_string();
                            errors.push(format!(
                                "{}:{n}: `{}`: {first}",
                                path.display(),
                                argv.join(" ")
                            ));
                        }
                    }
                }
            }
        }
    }
    assert!(errors.is_empty(), "{}", errors.join("\n"));
    assert!(
        parsed >= 40,
        "only {parsed} command lines found in the manual"
    );
}

#[test]
fn the_command_line_check_has_teeth() {
    let parses = |line: &str| {
        let argv = commands(line);
        assert_eq!(argv.len(), 1, "{line}");
        Cli::try_parse_from(&argv[0]).is_ok()
    };
    assert!(parses(
        "volgrad render scenes/cloud.toml -o a.exr --spp 4   # a comment"
    ));
    assert!(parses(
        "scripts/setup.sh && cargo run --release -- render scenes/cloud.toml -o cloud.exr"
    ));
    assert!(parses(
        "srun volgrad optimize run.toml --threads \"$SLURM_CPUS_PER_TASK\" --out \"$DIR/run.out\""
    ));
    assert!(parses(
        "volgrad grad s.toml --estimator fd --fd 'voxels:5,7,5;1,2,3'"
    ));
    for bad in [
        "volgrad render scenes/cloud.toml --spp 16 [--majorant global]",
        "volgrad render scenes/cloud.toml --sp 16",
        "volgrad grad s.toml --estimator exact",
        "mpirun -n 2 volgrad optimise run.toml",
        "volgrad compare s.toml --budget 3 fortnights",
    ] {
        assert!(!parses(bad), "{bad}");
    }
    assert!(commands("sed 's/a/b/' x > y").is_empty());
    assert_eq!(words("a 'b c' \"d\" # e"), ["a", "b c", "d"]);
}
