//! Run files that cannot give a result are refused when the run loads, with a message that says
//! why, instead of failing at a checkpoint after minutes of steps or writing settings that do not
//! reproduce the run.

mod common;
mod optimize_common;

use common::{assert_clean_error, volgrad_in};
use optimize_common::*;

/// A held-out view that sees nothing but black (a camera looking away from the ball, under a sun
/// alone, which no camera sees directly) has no PSNR: it made every evaluation −inf and the run
/// fail at its first checkpoint, when the chart of the held-out PSNR found no point to draw.
#[test]
fn a_black_held_out_view_is_refused() {
    let run = run_file("0.2", "iterations = 2");
    let orbit = &run[run.find("[holdouts.orbit]").unwrap()..run.find("[unknown]").unwrap()];
    let away = "[[holdout]]\nposition = [0, 0, 12]\ntarget = [0, 0, 24]\nfov_deg = 40\nwidth = 24\nheight = 24\n\
                light = [{ type = \"directional\", direction = [-0.5, -1.0, -0.3], irradiance = 4.0 }]\n\n";
    let dir = fixture(&run.replace(orbit, away));
    assert_clean_error(
        &volgrad_in(dir.path(), &["optimize", "run.toml", "--out", "out", "-q"]),
        &["holdout[0]", "black everywhere", "PSNR"],
    );
}
