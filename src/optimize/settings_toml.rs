//! `OUT/settings.toml`: a run file as a run resolved it, every key written out and every path
//! absolute, so that the run can be reproduced (or edited) from anywhere.

use std::path::Path;

use anyhow::{Context, Result};

use crate::gradient::adjoint::Estimator;
use crate::optimize::idle_keys;
use crate::optimize::run_file::{RunFile, StartFile};
use crate::optimize::schedule::Stop;
use crate::render::scene_file::LightFile;

/// The file with every key written out and every path absolute, as TOML that `optimize`
/// reads back: what a run resolved, to reproduce or edit it from anywhere.
/// `notes` (lines of text) follow as comments.
pub fn resolved(run_file: &RunFile, run_path: &Path, notes: &str) -> Result<String> {
    let absolute = |name: &String| -> String {
        let path = RunFile::resolve(run_path, name);
        std::path::absolute(&path)
            .unwrap_or(path)
            .to_string_lossy()
            .into_owned()
    };
    let mut file = run_file.clone();
    file.scene = absolute(&file.scene);
    file.truth = file.truth.as_ref().map(absolute);
    for view in file.view.iter_mut().chain(&mut file.holdout) {
        view.image = view.image.as_ref().map(absolute);
        absolute_envmaps(&mut view.light, &absolute);
    }
    for set in file.views.iter_mut().chain(&mut file.holdouts) {
        for orbit in &mut set.orbit {
            absolute_envmaps(&mut orbit.light, &absolute);
        }
        set.transforms = set.transforms.as_ref().map(absolute);
        if let Some(colmap) = &mut set.colmap {
            colmap.model = absolute(&colmap.model);
            colmap.images = colmap.images.as_ref().map(absolute);
        }
        absolute_envmaps(&mut set.light, &absolute);
    }
    if let Some(StartFile::Vdb(name)) = &file.unknown.start {
        file.unknown.start = Some(StartFile::Vdb(absolute(name)));
    }
    let mut value = toml::Value::try_from(&file).context("writing the resolved run file")?;
    if let toml::Value::Table(table) = &mut value {
        idle_keys::leave_out(&file, table);
    }
    shortest_floats(&mut value);
    let text = toml::to_string(&value).context("writing the resolved run file")?;
    let notes: String = notes.lines().map(|l| format!("# {l}\n")).collect();
    Ok(format!(
        "# The run file '{}' as volgrad resolved it: every key, absolute paths.\n\n{text}\n{notes}",
        run_path.display()
    ))
}

/// `settings` with what it cannot hold as keys, the command line's choices that shaped the run
/// (its estimator and when it stopped), as a closing note that says how to replay it: without
/// `--estimator`, a replay of a DRT run would run joint.
pub fn with_command(settings: &str, estimator: Estimator, stop: &Stop) -> String {
    let stop = match stop {
        Stop::Iterations(n) => format!(" --iterations {n}"),
        Stop::Budget(d) if d.subsec_nanos() == 0 => format!(" --budget {}s", d.as_secs()),
        Stop::Budget(d) => format!(" --budget {}ms", d.as_millis()),
        Stop::Replay(fractions) => {
            format!(" --schedule-from <a log of {} iterations>", fractions.len())
        }
    };
    format!(
        "{settings}# Run with --estimator {estimator}{stop}. To replay it, step for step: \
         volgrad optimize OUT/settings.toml --estimator {estimator} --schedule-from OUT/log.csv\n"
    )
}

/// An environment map's file named relative to the run file, made absolute.
fn absolute_envmaps(lights: &mut [LightFile], absolute: &impl Fn(&String) -> String) {
    for light in lights {
        if let LightFile::Envmap { file, .. } = light {
            *file = absolute(file);
        }
    }
}

/// Every number of a run file is an f32, which TOML writes through f64 (0.1 as
/// 0.10000000149011612): each is rewritten as the shortest decimal that reads back as the same f32.
fn shortest_floats(value: &mut toml::Value) {
    match value {
        toml::Value::Float(x) => {
            let shortest = (*x as f32).to_string();
            *x = shortest.parse().unwrap_or(*x);
        }
        toml::Value::Array(items) => items.iter_mut().for_each(shortest_floats),
        toml::Value::Table(table) => table.iter_mut().for_each(|(_, v)| shortest_floats(v)),
        _ => {}
    }
}
