//! The two studies `volgrad compare` runs, end to end: the equal-time study of one scene (reference,
//! its check against finite differences, sweeps, charts, CSV, summary) and the stability suite.
//! Each writes its files into an output folder and returns the markdown it wrote.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Result};

use crate::compare::{self as c, Reference};
use crate::gradient::adjoint::Estimator;
use crate::gradient::fd::FdOptions;
use crate::gradient::gradcheck::{checks_table, Z_LIMIT};
use crate::gradient::loss::Loss;
use crate::io::output::{prepare_out_dir, write_bytes_whole};
use crate::render::scene::Scene;

pub struct EqualTimeOptions {
    pub estimators: Vec<Estimator>,
    /// Wall time per estimator.
    pub budget: Duration,
    /// Wall time per majorant mode of the forward-renderer comparison (zero skips it).
    pub render_budget: Duration,
    /// A reference written by an earlier study; `None` builds one into `out/reference.vdb`.
    pub reference: Option<PathBuf>,
    pub reference_spp: u32,
    pub reference_seeds: u32,
    /// Use the reference even if finite differences disagree with it.
    pub force_reference: bool,
    pub max_spp: u32,
    /// Voxels (of largest |gradient|) checked against finite differences.
    pub fd_voxels: usize,
    pub fd_spp: u32,
    pub fd_repeats: u32,
    pub seed: u64,
    pub progress: bool,
    /// Overwrite existing outputs.
    pub overwrite: bool,
}

/// The files the equal-time study writes into `out`.
fn equal_time_outputs(out: &Path, o: &EqualTimeOptions) -> Vec<PathBuf> {
    let mut names = vec![
        "runs.csv",
        "summary.md",
        "gradient-error.png",
        "gradient-error.svg",
    ];
    if o.reference.is_none() {
        names.push("reference.vdb");
    }
    if !o.render_budget.is_zero() {
        names.extend(["render-error.png", "render-error.svg"]);
    }
    names.iter().map(|f| out.join(f)).collect()
}

/// Error against time of each estimator (and of the renderer's majorant modes) on `scene`; writes
/// `out/{runs.csv, summary.md, *-error.png/svg, reference.vdb}` and returns the summary.
pub fn equal_time(scene: &Scene, name: &str, out: &Path, o: &EqualTimeOptions) -> Result<String> {
    if o.estimators.is_empty() {
        bail!("--estimators needs at least one of joint, drt, naive");
    }
    if o.reference_spp == 0 || o.reference_seeds < 1 || o.max_spp == 0 {
        bail!("--reference-spp, --reference-seeds and --max-spp must be at least 1");
    }
    prepare_out_dir(out, &equal_time_outputs(out, o), o.overwrite)?;
    let max_depth = scene.settings.max_depth;
    let reference = reference(scene, out, o)?;
    let check_table = checked_reference_table(scene, &reference, o)?;

    let sweep = c::SweepOptions {
        budget: o.budget,
        max_spp: o.max_spp,
        seed: o.seed,
        max_depth,
        progress: o.progress,
    };
    let mut rows = c::gradient_sweeps(scene, &o.estimators, &reference, &sweep);
    let names: Vec<String> = o.estimators.iter().map(|e| e.to_string()).collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let mut summary = format!(
        "### `volgrad compare {}`\n\nBudget {} s per estimator, spp doubling from 1 up to {}, seed {}; reference: {} runs × {} spp (joint and drt alternating); {} threads.\n\n#### Reference against finite differences\n\n{check_table}\n",
        scene.path.display(),
        o.budget.as_secs_f64(), // as given: 0.2 s, not "0"
        o.max_spp,
        o.seed,
        reference.runs,
        reference.spp_per_run,
        rayon::current_num_threads()
    );
    summary += &c::summary(&rows, &names, "drt", "joint", "Gradient");
    let mut charts = vec![(
        "gradient-error",
        c::chart(
            &rows,
            &format!("{name}: gradient error against time"),
            "relative RMSE vs reference",
        ),
    )];
    if !o.render_budget.is_zero() {
        let image_reference = c::build_image_reference(
            scene,
            o.reference_spp,
            o.reference_seeds.max(2),
            o.seed,
            max_depth,
            o.progress,
        );
        let render_sweep = c::SweepOptions {
            budget: o.render_budget,
            ..sweep
        };
        let render_rows = c::render_sweeps(scene, &image_reference, &render_sweep);
        summary += "\n";
        summary += &c::summary(
            &render_rows,
            &[c::RENDER_GRID, c::RENDER_GLOBAL],
            c::RENDER_GLOBAL,
            c::RENDER_GRID,
            "Forward render",
        );
        let title = format!("{name}: image error against time");
        charts.push((
            "render-error",
            c::chart(&render_rows, &title, "relative image RMSE"),
        ));
        rows.extend(render_rows);
    }
    // The measurements first: a chart that cannot be drawn must not lose them.
    write_bytes_whole(&out.join("runs.csv"), c::csv(&rows))?;
    write_bytes_whole(&out.join("summary.md"), &summary)?;
    for (file, chart) in &charts {
        c::write_chart(out, file, chart)?;
    }
    Ok(summary)
}

/// The reference the study scores against: loaded, or built and saved as `out/reference.vdb`.
fn reference(scene: &Scene, out: &Path, o: &EqualTimeOptions) -> Result<Reference> {
    if let Some(file) = &o.reference {
        let r = c::load_reference(file, scene)?;
        eprintln!(
            "reference: {} ({} runs × {} spp)",
            file.display(),
            r.runs,
            r.spp_per_run
        );
        return Ok(r);
    }
    let options = c::ReferenceOptions {
        spp: o.reference_spp,
        seeds: o.reference_seeds,
        seed: o.seed,
        max_depth: scene.settings.max_depth,
        progress: o.progress,
    };
    eprintln!(
        "building the reference: {} runs each of joint and drt at {} spp",
        options.seeds, options.spp
    );
    let (r, seconds) = c::timed(|| c::build_reference(scene, &options));
    let file = out.join("reference.vdb");
    c::save_reference(&file, scene, &r, o.overwrite)?;
    eprintln!("wrote {} ({seconds:.1} s)", file.display());
    Ok(r)
}

/// Checks the reference against finite differences and returns the checks as a markdown table;
/// an error if any |z| reaches `Z_LIMIT` (or is NaN) unless `force_reference`.
fn checked_reference_table(
    scene: &Scene,
    reference: &Reference,
    o: &EqualTimeOptions,
) -> Result<String> {
    let fd = FdOptions {
        loss: Loss::Mean,
        // Chosen per check by `check_reference`: a step that suits one voxel is far too large
        // for the whole domain.
        eps: 0.0,
        spp: o.fd_spp,
        repeats: o.fd_repeats,
        seed: o.seed,
        max_depth: scene.settings.max_depth,
    };
    eprintln!(
        "checking the reference against finite differences ({} spp × {} repeats)",
        fd.spp, fd.repeats
    );
    let checks = c::check_reference(scene, reference, &fd, o.fd_voxels)?;
    let table = checks_table(&checks).markdown();
    for line in table.lines().skip(2) {
        eprintln!("  {line}");
    }
    // f64::max would drop a NaN z (no finite difference), which must fail too.
    let worst =
        checks
            .iter()
            .map(|c| c.z().abs())
            .fold(0.0, |w: f64, z| if z.is_nan() || z > w { z } else { w });
    if worst.is_nan() || worst >= Z_LIMIT {
        if !o.force_reference {
            bail!("the reference disagrees with finite differences (|z| = {worst:.1} > {Z_LIMIT}): build it with more --reference-spp/--reference-seeds, or pass --force-reference");
        }
        eprintln!("warning: the reference disagrees with finite differences (|z| = {worst:.1}); using it because of --force-reference");
    }
    Ok(table)
}

/// What the stability suite found.
pub struct StabilityReport {
    pub markdown: String,
    pub non_finite: usize,
    /// Checks biased beyond |z| = 4 where no bias is expected.
    pub unexpected_bias: usize,
}

impl StabilityReport {
    /// A non-finite value anywhere, or an unexpected bias, fails the suite.
    pub fn failure(&self) -> Option<String> {
        (self.non_finite > 0 || self.unexpected_bias > 0).then(|| {
            format!(
                "{} non-finite values and {} unexpected biased checks",
                self.non_finite, self.unexpected_bias
            )
        })
    }
}

/// Runs the stability suite and writes `out/stability.{md,csv}`.
pub fn stability_suite(
    estimators: &[Estimator],
    options: &c::StabilityOptions,
    out: &Path,
    overwrite: bool,
) -> Result<StabilityReport> {
    let files = [out.join("stability.md"), out.join("stability.csv")];
    prepare_out_dir(out, &files, overwrite)?;
    let scenes = c::stability_scenes();
    let rows = c::stability(&scenes, estimators, options)?;
    let markdown = c::stability_markdown(&scenes, &rows, options);
    write_bytes_whole(&files[0], &markdown)?;
    write_bytes_whole(&files[1], c::stability_csv(&rows))?;
    eprintln!("wrote {} and {}", files[0].display(), files[1].display());
    Ok(StabilityReport {
        markdown,
        non_finite: rows.iter().map(|r| r.non_finite).sum(),
        unexpected_bias: rows
            .iter()
            .filter(|r| !r.unbiased() && !r.expected_failure)
            .count(),
    })
}
