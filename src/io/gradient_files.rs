//! Gradient files: the gradient grid as a VDB (`grad_<grid>`, the input's transform, fog class,
//! provenance metadata), its picture, and merging runs made with different seeds.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::IVec3;

use crate::io::bridge::MetaEntry;
use crate::io::colormap::write_signed_png;
use crate::io::vdb::{self, meta, Grid};
use crate::volume::brickmap::{BrickMap, BrickMapBuilder};
use crate::volume::transform::IndexTransform;

/// What a gradient file was computed from. `merge` combines only files whose computation fields
/// are all equal, so that their mean is a better estimate of one gradient; `scene` (the path as
/// given) is for people, the fingerprints are what is compared.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Provenance {
    pub estimator: String,
    pub spp: u64,
    /// The run's seed, or the comma-separated seeds of merged runs.
    pub seed: String,
    pub loss: String,
    pub scene: String,
    /// `render::fingerprint::scene` of the scene.
    pub scene_fingerprint: String,
    /// `io::fingerprint::image` of the loss's target, or "none".
    pub target_fingerprint: String,
    /// "all" or "active".
    pub domain: String,
    pub max_depth: u32,
    /// "per-path" or "per-segment".
    pub suffix: String,
    /// The grid the gradient is with respect to: "extinction", "emission" or "albedo".
    pub parameter: String,
}

impl Provenance {
    fn metadata(&self) -> Vec<MetaEntry> {
        vec![
            meta("volgrad_estimator", "string", &self.estimator),
            meta("volgrad_spp", "int64", self.spp),
            meta("volgrad_seed", "string", &self.seed),
            meta("volgrad_loss", "string", &self.loss),
            meta("volgrad_scene", "string", &self.scene),
            meta(
                "volgrad_scene_fingerprint",
                "string",
                &self.scene_fingerprint,
            ),
            meta(
                "volgrad_target_fingerprint",
                "string",
                &self.target_fingerprint,
            ),
            meta("volgrad_domain", "string", &self.domain),
            meta("volgrad_max_depth", "int64", self.max_depth),
            meta("volgrad_suffix", "string", &self.suffix),
            meta("volgrad_parameter", "string", &self.parameter),
        ]
    }

    /// Every field that defines the computation, as (metadata name, value), in the order a
    /// mismatch is reported.
    pub fn computation(&self) -> [(&'static str, String); 8] {
        [
            ("volgrad_parameter", self.parameter.clone()),
            ("volgrad_scene_fingerprint", self.scene_fingerprint.clone()),
            (
                "volgrad_target_fingerprint",
                self.target_fingerprint.clone(),
            ),
            ("volgrad_loss", self.loss.clone()),
            ("volgrad_estimator", self.estimator.clone()),
            ("volgrad_domain", self.domain.clone()),
            ("volgrad_max_depth", self.max_depth.to_string()),
            ("volgrad_suffix", self.suffix.clone()),
        ]
    }

    pub fn from_metadata(entries: &[MetaEntry], file: &Path) -> Result<Self> {
        let get = |name: &str| -> Result<String> {
            entries
                .iter()
                .find(|e| e.name == name)
                .map(|e| e.value.clone())
                .with_context(|| {
                    format!(
                        "'{}' has no {name} metadata: not a gradient written by this volgrad (compute it again)",
                        file.display()
                    )
                })
        };
        let number = |name: &str| -> Result<u64> {
            let text = get(name)?;
            text.parse()
                .with_context(|| format!("'{}': {name} = '{text}' is not a count", file.display()))
        };
        let spp = number("volgrad_spp")?;
        if spp == 0 {
            bail!(
                "'{}' has volgrad_spp = 0: it holds no samples",
                file.display()
            );
        }
        Ok(Provenance {
            // Files from before gradients had other parameters hold extinction gradients.
            parameter: get("volgrad_parameter").unwrap_or_else(|_| "extinction".into()),
            estimator: get("volgrad_estimator")?,
            spp,
            seed: get("volgrad_seed")?,
            loss: get("volgrad_loss")?,
            scene: get("volgrad_scene")?,
            scene_fingerprint: get("volgrad_scene_fingerprint")?,
            target_fingerprint: get("volgrad_target_fingerprint")?,
            domain: get("volgrad_domain")?,
            max_depth: u32::try_from(number("volgrad_max_depth")?)
                .with_context(|| format!("'{}': volgrad_max_depth is too large", file.display()))?,
            suffix: get("volgrad_suffix")?,
        })
    }
}

/// The gradient (as bricks: `GradientGrid::to_brickmap`) as a float grid named `grad_<grid_name>`.
pub fn gradient_grid(
    gradient: BrickMap,
    grid_name: &str,
    transform: IndexTransform,
    provenance: &Provenance,
) -> Grid {
    Grid {
        name: format!("grad_{grid_name}"),
        grid_class: "fog volume".into(),
        background: 0.0,
        transform,
        bricks: gradient,
        saved_as_half: false,
        metadata: provenance.metadata(),
    }
}

/// The longest side of the projection picture, in pixels.
const MAX_PROJECTION_SIDE: i64 = 1024;

/// Sum of a grid's values along index z over its active box: a picture of where the gradient is.
/// A box wider than `MAX_PROJECTION_SIDE` voxels sums square cells of voxels into each pixel, so
/// the picture's memory follows the picture, not the box (two voxels 60,000 apart along the
/// diagonal once asked for a 56,000² picture: 12.5 GB).
pub fn projection(grid: &Grid) -> Option<(u32, u32, Vec<f32>)> {
    let (lo, hi) = grid.bricks.active_bounds()?;
    let extent = (hi - lo).as_i64vec3() + 1;
    let cell = (extent.x.max(extent.y) + MAX_PROJECTION_SIDE - 1) / MAX_PROJECTION_SIDE;
    let (w, h) = ((extent.x + cell - 1) / cell, (extent.y + cell - 1) / cell);
    let mut values = vec![0.0f32; (w * h) as usize];
    for leaf in grid.bricks.leaves() {
        for (o, &v) in leaf.values.iter().enumerate() {
            let p =
                leaf.origin + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
            if p.cmpge(lo).all() && p.cmple(hi).all() {
                // Image rows run top to bottom, index y bottom to top.
                let (x, y) = (
                    (i64::from(p.x) - i64::from(lo.x)) / cell,
                    (i64::from(hi.y) - i64::from(p.y)) / cell,
                );
                values[(y * w + x) as usize] += v;
            }
        }
    }
    Some((w as u32, h as u32, values))
}

/// Writes the projection picture; returns the colour scale, or None for an empty grid.
pub fn write_projection_png(path: &Path, grid: &Grid) -> Result<Option<f32>> {
    match projection(grid) {
        Some((w, h, values)) => Ok(Some(write_signed_png(path, w, h, &values)?)),
        None => Ok(None),
    }
}

/// Combines gradient VDBs from runs with different seeds, weighted by their spp: one grid, or the
/// three components of a colour gradient (an RGB albedo's), which then stay three.
pub fn merge(inputs: &[&Path]) -> Result<Vec<Grid>> {
    if inputs.is_empty() {
        bail!("merge needs at least one input");
    }
    let mut sums: Vec<HashMap<IVec3, f64>> = Vec::new();
    let mut first: Option<(Vec<Grid>, Provenance)> = None;
    let mut total_spp = 0u64;
    let mut seeds: Vec<(String, &Path)> = Vec::new();
    for &path in inputs {
        let name = vdb::list_grid_names(path)?
            .into_iter()
            .find(|name| name.starts_with("grad_"))
            .with_context(|| format!("'{}' has no grad_* grid", path.display()))?;
        let components = vdb::read_components(path, &name)?;
        let provenance = Provenance::from_metadata(&components[0].metadata, path)?;
        if let Some((f, p)) = &first {
            // The computation first: another parameter is named as such, not as another grid.
            let mut differs = p.computation().into_iter().zip(provenance.computation());
            if let Some(((field, first_value), (_, value))) = differs.find(|(a, b)| a != b) {
                bail!(
                    "'{}' is another computation than '{}': {field} is '{first_value}' there and '{value}' here (merge combines runs of one computation with different seeds)",
                    path.display(),
                    inputs[0].display(),
                );
            }
            let grid = &components[0];
            if f[0].name != grid.name
                || f[0].transform != grid.transform
                || f.len() != components.len()
            {
                bail!(
                    "'{}' holds {} with another transform, name or number of channels than {}: not the same scene",
                    path.display(),
                    grid.name,
                    f[0].name
                );
            }
        }
        for seed in provenance.seed.split(',') {
            if let Some((_, other)) = seeds.iter().find(|(s, _)| s == seed) {
                bail!(
                    "seed {seed} is in both '{}' and '{}': the runs are not independent (give each run its own --seed)",
                    other.display(),
                    path.display()
                );
            }
            seeds.push((seed.to_string(), path));
        }
        sums.resize_with(components.len(), HashMap::new);
        for (grid, sums) in components.iter().zip(&mut sums) {
            for leaf in grid.bricks.leaves() {
                for (o, &v) in leaf.values.iter().enumerate() {
                    if v != 0.0 {
                        let p = leaf.origin
                            + IVec3::new((o >> 6) as i32, ((o >> 3) & 7) as i32, (o & 7) as i32);
                        *sums.entry(p).or_insert(0.0) += v as f64 * provenance.spp as f64;
                    }
                }
            }
        }
        // The sum is written back as OpenVDB's int64: only hand-edited counts come near it.
        total_spp = total_spp
            .checked_add(provenance.spp)
            .filter(|&sum| i64::try_from(sum).is_ok())
            .with_context(|| {
                format!(
                    "'{}': the inputs' volgrad_spp add up beyond 2^63 - 1 (not counts a run writes)",
                    path.display()
                )
            })?;
        if first.is_none() {
            first = Some((components, provenance));
        }
    }
    let (mut grids, mut provenance) = first.expect("at least one input");
    provenance.spp = total_spp;
    provenance.seed = seeds
        .iter()
        .map(|(s, _)| s.as_str())
        .collect::<Vec<_>>()
        .join(",");
    for (grid, sums) in grids.iter_mut().zip(sums) {
        let mut b = BrickMapBuilder::new();
        for (v, s) in sums {
            b.set(v, (s / total_spp as f64) as f32, true);
        }
        grid.bricks = b.build();
        grid.metadata = provenance.metadata();
    }
    Ok(grids)
}
