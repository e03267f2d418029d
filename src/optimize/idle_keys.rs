//! Keys a run file may give that the rest of it leaves without effect: `brick_scale_lr` when the
//! brick scales are not fitted, say. Given, such a key says the user expects something the run
//! will not do, so it is refused, naming what idles it; `settings.toml`, which writes every key a
//! run resolved, leaves them out, so that it still loads.

use anyhow::{bail, Result};

use crate::optimize::run_file::RunFile;

/// A key (`table.key`) and the setting that leaves it without effect.
struct IdleKey {
    table: &'static str,
    key: &'static str,
    because: &'static str,
}

/// The keys `file` leaves without effect. Levels left to the run are derived when it loads, so
/// `level_lr` and `moments` are idle only once `unknown.levels` is known to be empty: as the file
/// says, or as the run derives.
fn idle_keys(file: &RunFile) -> Vec<IdleKey> {
    let o = &file.optimizer;
    let idle = |table, key, because| IdleKey {
        table,
        key,
        because,
    };
    let mut keys = Vec::new();
    if !o.fit_brick_scales {
        let because = "optimizer.fit_brick_scales = false";
        keys.push(idle("optimizer", "brick_scale_lr", because));
    }
    if !o.smooth_gradient {
        let because = "optimizer.smooth_gradient = false";
        keys.push(idle("optimizer", "first_level_smoothing", because));
    }
    if file.unknown.levels.as_deref() == Some(&[]) {
        let written = (file.given.get("unknown").and_then(|t| t.as_table()))
            .is_some_and(|t| t.contains_key("levels"));
        let because = match written {
            true => "unknown.levels = []: no upsampling",
            false => "the levels derived from the views and the box are none (unknown.levels = []): no upsampling",
        };
        keys.push(idle("optimizer", "level_lr", because));
        keys.push(idle("unknown", "moments", because));
    }
    if !file.renders_from_truth() {
        let because = "every view has its picture: no target is rendered from a truth";
        keys.push(idle("", "target_spp", because));
    }
    keys
}

/// The place of `key` in the file as TOML: the top level, or one of its tables.
fn table_of<'a>(toml: &'a mut toml::Table, key: &IdleKey) -> Option<&'a mut toml::Table> {
    match key.table {
        "" => Some(toml),
        name => toml.get_mut(name)?.as_table_mut(),
    }
}

/// Refuses a key the file gives that the rest of it idles.
pub fn refuse_given(file: &RunFile) -> Result<()> {
    let mut given = file.given.clone();
    for key in idle_keys(file) {
        if table_of(&mut given, &key).is_some_and(|t| t.contains_key(key.key)) {
            let name = match key.table {
                "" => key.key.to_string(),
                table => format!("{table}.{}", key.key),
            };
            bail!(
                "{name} has no effect here ({}): leave it out, or change what idles it",
                key.because
            );
        }
    }
    Ok(())
}

/// A resolved file as TOML (`settings.toml`) without the keys the rest of it idles.
pub fn leave_out(file: &RunFile, resolved: &mut toml::Table) {
    for key in idle_keys(file) {
        if let Some(table) = table_of(resolved, &key) {
            table.remove(key.key);
        }
    }
}
