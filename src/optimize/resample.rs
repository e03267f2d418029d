//! Coarse to fine: the unknown is upsampled ×2 per axis by sampling its continuous (trilinear)
//! field at the new voxel centres. New voxel j sits at old continuous index c = j/2 − ¼ (old voxel
//! i splits into new voxels 2i and 2i + 1 at c = i ∓ ¼), so the grid keeps its world box and the
//! new transform is the old one composed with j ↦ j/2 − ¼.
//!
//! Adam's moments are carried over the same way (`Moments::Resample`, scaled to the finer voxels'
//! gradients) or started afresh (`Moments::Reset`). A fresh Adam's first step moves every voxel by
//! the full learning rate whatever its gradient (m̂/√v̂ = ±1 at t = 1): with noisy per-voxel
//! gradients that is a random walk the θ ≥ 0 projection turns into haze, so run files default to
//! `Resample`.

use std::collections::HashSet;

use glam::{DAffine3, DQuat, DVec3, IVec3, Vec3};

use crate::optimize::parameters::Parameters;
use crate::volume::brickmap::{corner, floor_ivec3};
use crate::volume::transform::IndexTransform;

/// A new voxel holds 1/8 of an old voxel's volume, so the loss's gradient with respect to it is
/// about 1/8 of the old one's (the chain rule through the trilinear field): resampled first
/// moments are scaled by 1/8 and second moments by 1/64, which keeps Adam's step m/√v, and so the
/// size of the first steps after an upsampling, what they were.
const FINE_GRADIENT_SCALE: f32 = 1.0 / 8.0;

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Moments {
    /// The moments are resampled like θ (scaled to the finer voxels' gradients) and the step
    /// count continues: Adam goes on at the pace it had.
    Resample,
    /// The moments start at 0 with the step count (Adam starts over).
    Reset,
}

/// The old continuous index of new voxel `j`.
fn old_index(j: IVec3) -> Vec3 {
    j.as_vec3() * 0.5 - 0.25
}

/// Trilinear interpolation of θ, m and v between voxel centres (OpenVDB's box-sampler convention).
fn trilinear(p: &Parameters, c: Vec3) -> (f32, f32, f32) {
    let base = floor_ivec3(c);
    let f = c - base.as_vec3();
    let mut out = (0.0, 0.0, 0.0);
    for k in 0..8 {
        let o = corner(k);
        let w = (if o.x == 1 { f.x } else { 1.0 - f.x })
            * (if o.y == 1 { f.y } else { 1.0 - f.y })
            * (if o.z == 1 { f.z } else { 1.0 - f.z });
        if w > 0.0 {
            let (theta, m, v) = p.state(base + o);
            out.0 += w * theta;
            out.1 += w * m;
            out.2 += w * v;
        }
    }
    out
}

/// The unknown at twice the resolution per axis, and its transform. Work and memory follow the
/// stored bricks: each old brick b reaches the new bricks 2b − 1 ..= 2b + 2 (its voxels' trilinear
/// footprint), and only those are sampled; with `keep`, only the new voxels in that inclusive box
/// (an unknown whose field ends at its box: the trilinear field reaches half an old voxel past it).
pub fn upsample(
    p: &Parameters,
    transform: &IndexTransform,
    moments: Moments,
    keep: Option<(IVec3, IVec3)>,
) -> anyhow::Result<(Parameters, IndexTransform)> {
    let kept = |j: IVec3| keep.is_none_or(|(lo, hi)| j.cmpge(lo).all() && j.cmple(hi).all());
    let mut targets: HashSet<IVec3> = HashSet::new();
    for b in p.brick_keys() {
        for dx in -1..=2 {
            for dy in -1..=2 {
                for dz in -1..=2 {
                    targets.insert(b * 2 + IVec3::new(dx, dy, dz));
                }
            }
        }
    }
    let mut fine = Parameters::default();
    for key in targets {
        for x in 0..8 {
            for y in 0..8 {
                for z in 0..8 {
                    let j = (key << 3) + IVec3::new(x, y, z);
                    if !kept(j) {
                        continue;
                    }
                    let (theta, m, v) = trilinear(p, old_index(j));
                    if theta == 0.0 && m == 0.0 && v == 0.0 {
                        continue;
                    }
                    match moments {
                        Moments::Resample => fine.set_with_moments(
                            j,
                            theta,
                            m * FINE_GRADIENT_SCALE,
                            v * FINE_GRADIENT_SCALE * FINE_GRADIENT_SCALE,
                        ),
                        Moments::Reset => fine.set(j, theta),
                    }
                }
            }
        }
    }
    fine.prune();
    // The captures' exposures are no voxel's: whatever becomes of θ's moments, they stay as fitted.
    fine.exposures = p.exposures.clone();
    if moments == Moments::Resample {
        fine.continue_steps_of(p);
        fine.inherit_brick_scales(p, FINE_GRADIENT_SCALE);
    }
    let refine = DAffine3::from_scale_rotation_translation(
        DVec3::splat(0.5),
        DQuat::IDENTITY,
        DVec3::splat(-0.25),
    );
    let transform = IndexTransform::new(transform.index_to_world() * refine)?;
    Ok((fine, transform))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A field that is linear in the index reproduces exactly at the new voxel centres (trilinear
    /// interpolation is exact for it), in world space: the new voxel's world position reads the
    /// value the old field has there.
    #[test]
    fn upsampling_reproduces_the_continuous_field_at_the_new_centres() {
        let field = |c: Vec3| 4.0 + 0.3 * c.x - 0.2 * c.y + 0.1 * c.z; // > 0 on the block
        let mut p = Parameters::default();
        for x in -6..6 {
            for y in -6..6 {
                for z in -6..6 {
                    p.set(IVec3::new(x, y, z), field(IVec3::new(x, y, z).as_vec3()));
                }
            }
        }
        let coarse = IndexTransform::uniform(2.0, DVec3::new(10.0, -3.0, 0.5));
        let (fine, fine_transform) = upsample(&p, &coarse, Moments::Reset, None).unwrap();
        assert_eq!(fine_transform.voxel_size(), DVec3::splat(1.0));
        let mut checked = 0;
        for x in -8..8 {
            for y in -8..8 {
                for z in -8..8 {
                    let j = IVec3::new(x, y, z);
                    let world = fine_transform.point_to_world(j.as_vec3());
                    let c = coarse.point_to_index(world);
                    assert!(
                        (c - old_index(j)).length() < 1e-4,
                        "{j}: {c} vs {}",
                        old_index(j)
                    );
                    let expected = field(c);
                    assert!(
                        (fine.get(j) - expected).abs() < 1e-4,
                        "{j}: {} vs {expected}",
                        fine.get(j)
                    );
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 16 * 16 * 16);
        // The world box is kept: the fine grid's first voxel centre is ¼ of a coarse voxel inside
        // the coarse grid's first voxel.
        let shift = fine_transform.point_to_world(Vec3::ZERO) - coarse.point_to_world(Vec3::ZERO);
        assert!((shift - Vec3::splat(-0.5)).length() < 1e-5, "{shift}");
    }

    #[test]
    fn moments_are_resampled_or_reset() {
        let v = IVec3::new(4, 4, 4);
        let mut p = Parameters::default();
        p.set(v, 1.0);
        let adam = crate::optimize::adam::Adam {
            fit_brick_scales: true,
            ..Default::default()
        };
        let gradient = crate::optimize::brick_gradient::BrickGradient::from_voxels([(v, 1.0)]);
        p.adam_step(&adam, &gradient, &Default::default());
        p.exposures = vec![crate::optimize::exposure::Exposure::default(); 2];
        p.exposures[1].log = 0.25;
        let (kept, _) = upsample(
            &p,
            &IndexTransform::uniform(1.0, DVec3::ZERO),
            Moments::Resample,
            None,
        )
        .unwrap();
        let (reset, _) = upsample(
            &p,
            &IndexTransform::uniform(1.0, DVec3::ZERO),
            Moments::Reset,
            None,
        )
        .unwrap();
        assert_eq!(kept.steps(), 1);
        assert_eq!(reset.steps(), 0);
        // The fitted exposure survives either way (a reset once dropped it back to 1).
        assert_eq!(kept.exposures, p.exposures);
        assert_eq!(reset.exposures, p.exposures);
        // New voxel 2v sits at old index v − ¼: weight (¾)³ on v.
        let m_at =
            |q: &Parameters, j: IVec3| q.voxels().find(|(w, ..)| *w == j).map(|(_, _, m, _)| m);
        let expected = 0.75f32.powi(3) * 0.1 * FINE_GRADIENT_SCALE;
        assert!((m_at(&kept, v * 2).unwrap() - expected).abs() < 1e-6);
        assert_eq!(m_at(&reset, v * 2), Some(0.0));
        // Every new brick (keys 0 and 1 per axis) lies in old brick 0 and takes its log-scale's
        // moments, scaled like a voxel's; reset, they start at 0.
        let parent = p.sorted_bricks()[0].4;
        assert_ne!(parent, Default::default());
        let scales = |q: &Parameters| q.sorted_bricks().iter().map(|b| b.4).collect::<Vec<_>>();
        assert_eq!(scales(&kept).len(), 8);
        assert!(scales(&kept)
            .iter()
            .all(|&s| s == parent.scaled(FINE_GRADIENT_SCALE)));
        assert!(scales(&reset).iter().all(|&s| s == Default::default()));
    }
}
