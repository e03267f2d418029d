//! Light the medium gives off: a grid (temperature, flames, heat) with its own transform and
//! brick map, turned into radiance Le per point. The medium emits σa·Le = σt·(1 − α)·Le, so
//! emission shows only where there is density, and the medium's bounds and majorants stay those
//! of the density grid.

use glam::Vec3;

use crate::volume::blackbody::blackbody_rgb;
use crate::volume::brickmap::BrickMap;
use crate::volume::ray::Filter;
use crate::volume::transform::IndexTransform;

/// How a grid value v becomes radiance.
#[derive(Debug, Clone, PartialEq)]
pub enum EmissionKind {
    /// pbrt-v4's temperature grid: T = (v − offset) · scale kelvin; nothing at or below `cutoff`
    /// kelvin; else `strength` × the normalised blackbody at T (`blackbody`).
    Blackbody {
        scale: f32,
        offset: f32,
        cutoff: f32,
        strength: f32,
    },
    /// `radiance` × v.
    Radiance(Vec3),
}

/// Temperatures between table entries are interpolated; beyond the table, its last entry holds.
const TABLE_KELVIN_STEP: f32 = 10.0;
const TABLE_ENTRIES: usize = 4001;

/// An emission grid and what its values mean.
#[derive(Clone)]
pub struct Emission {
    /// The grid's name in its file (what `volgrad info` shows).
    pub name: String,
    pub grid: BrickMap,
    pub transform: IndexTransform,
    pub kind: EmissionKind,
    /// The medium's filter, so that emission and density end at the same place.
    pub filter: Filter,
    /// The blackbody's sRGB every `TABLE_KELVIN_STEP` kelvin from 0 (for `Blackbody` only):
    /// Planck's law against the colour-matching functions is 471 wavelengths per temperature.
    table: Vec<Vec3>,
}

impl Emission {
    pub fn new(
        name: String,
        grid: BrickMap,
        transform: IndexTransform,
        kind: EmissionKind,
        filter: Filter,
    ) -> Emission {
        let table = match kind {
            EmissionKind::Blackbody { .. } => (0..TABLE_ENTRIES)
                .map(|i| blackbody_rgb(i as f64 * TABLE_KELVIN_STEP as f64))
                .collect(),
            EmissionKind::Radiance(_) => Vec::new(),
        };
        Emission {
            name,
            grid,
            transform,
            kind,
            filter,
            table,
        }
    }

    /// Le at world point `p` (looked up in the grid's own index space).
    pub fn radiance(&self, p: Vec3) -> Vec3 {
        self.radiance_of(self.value(self.transform.point_to_index(p)))
    }

    /// The largest channel of Le anywhere, in f64 (so that a product beyond f32 is seen), with
    /// the hottest temperature for a blackbody (kelvin; 0 for radiance). A lookup interpolates
    /// stored values and the 0 read outside them, so v ≤ max(the grid's largest value, 0), and T
    /// grows with v (scale > 0). For a blackbody, the largest table entry up to the one past that
    /// T bounds every interpolated value up to it (the cutoff is left out: a bound, not the value).
    pub fn largest_radiance(&self) -> (f64, f64) {
        let v = f64::from(self.grid.max_value().max(0.0));
        match self.kind {
            EmissionKind::Radiance(rgb) => (f64::from(rgb.max_element()) * v, 0.0),
            EmissionKind::Blackbody {
                scale,
                offset,
                strength,
                ..
            } => {
                let kelvin = (v - f64::from(offset)) * f64::from(scale);
                if kelvin <= 0.0 {
                    return (0.0, kelvin);
                }
                let step = f64::from(TABLE_KELVIN_STEP);
                let last = ((kelvin / step).ceil() as usize).min(TABLE_ENTRIES - 1);
                let peak = (self.table[..=last].iter())
                    .map(|c| c.max_element())
                    .fold(0.0, f32::max);
                (f64::from(strength) * f64::from(peak), kelvin)
            }
        }
    }

    /// The largest channel of ∂Le/∂v anywhere (`radiance_derivative`'s bound), in f64: `radiance`
    /// for a radiance grid; for a blackbody strength × |scale| × the steepest slope of the table
    /// up to the hottest temperature (`largest_radiance`'s).
    pub fn largest_radiance_derivative(&self) -> f64 {
        match self.kind {
            EmissionKind::Radiance(rgb) => f64::from(rgb.abs().max_element()),
            EmissionKind::Blackbody {
                scale, strength, ..
            } => {
                let (_, kelvin) = self.largest_radiance();
                if kelvin <= 0.0 {
                    return 0.0;
                }
                let last = ((kelvin / f64::from(TABLE_KELVIN_STEP)).ceil() as usize)
                    .min(TABLE_ENTRIES - 1);
                let steepest = (self.table[..=last].windows(2))
                    .map(|pair| (pair[1] - pair[0]).abs().max_element() / TABLE_KELVIN_STEP)
                    .fold(0.0, f32::max);
                f64::from(strength) * f64::from(scale).abs() * f64::from(steepest)
            }
        }
    }

    /// The grid's value at index point `index`, through the medium's filter.
    fn value(&self, index: Vec3) -> f32 {
        match self.filter {
            Filter::Nearest => self.grid.nearest(index),
            Filter::Trilinear => self.grid.trilinear(index),
        }
    }

    /// ∂Le/∂v at world point `p`, with `p` in the grid's index space (where the lookup's voxel
    /// weights are): `radiance` for a radiance grid; for a temperature grid strength × scale ×
    /// the blackbody's slope at T (0 at or below the cutoff, where Le does not depend on v).
    pub fn radiance_derivative(&self, p: Vec3) -> (Vec3, Vec3) {
        let index = self.transform.point_to_index(p);
        let d = match self.kind {
            EmissionKind::Radiance(rgb) => rgb,
            EmissionKind::Blackbody {
                scale, strength, ..
            } => match self.kelvin(self.value(index)) {
                Some(kelvin) => strength * scale * self.blackbody_slope(kelvin),
                None => Vec3::ZERO,
            },
        };
        (index, d)
    }

    fn radiance_of(&self, v: f32) -> Vec3 {
        match self.kind {
            EmissionKind::Radiance(rgb) => rgb * v,
            EmissionKind::Blackbody { strength, .. } => match self.kelvin(v) {
                Some(kelvin) => strength * self.blackbody(kelvin),
                None => Vec3::ZERO,
            },
        }
    }

    /// T = (v − offset) · scale of a temperature grid's value, where it is above the cutoff and
    /// 0 K (`None`: it emits nothing there, and Le does not depend on v).
    fn kelvin(&self, v: f32) -> Option<f32> {
        let EmissionKind::Blackbody {
            scale,
            offset,
            cutoff,
            ..
        } = self.kind
        else {
            return None;
        };
        let kelvin = (v - offset) * scale;
        (kelvin > cutoff && kelvin > 0.0).then_some(kelvin)
    }

    /// d blackbody / dT, per kelvin: the slope of the table's interval holding `kelvin`.
    fn blackbody_slope(&self, kelvin: f32) -> Vec3 {
        let x = kelvin / TABLE_KELVIN_STEP;
        if x >= (TABLE_ENTRIES - 1) as f32 {
            return Vec3::ZERO;
        }
        let i = x as usize;
        (self.table[i + 1] - self.table[i]) / TABLE_KELVIN_STEP
    }

    fn blackbody(&self, kelvin: f32) -> Vec3 {
        let x = (kelvin / TABLE_KELVIN_STEP).min((TABLE_ENTRIES - 1) as f32);
        let i = (x as usize).min(TABLE_ENTRIES - 2);
        let f = x - i as f32;
        self.table[i].lerp(self.table[i + 1], f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DVec3, IVec3};

    fn constant(value: f32) -> BrickMap {
        BrickMap::block(4, |_: IVec3| value)
    }

    /// The bound the gradient's quantum is sized by holds wherever the grid is read, and for a
    /// radiance grid it is the radiance itself.
    #[test]
    fn the_largest_radiance_derivative_bounds_every_point() {
        let transform = IndexTransform::uniform(1.0, DVec3::ZERO);
        let ramp = BrickMap::block(8, |v: IVec3| 0.5 + 0.25 * v.x as f32);
        let kinds = [
            EmissionKind::Radiance(Vec3::new(1.0, -3.0, 0.25)),
            EmissionKind::Blackbody {
                scale: 1000.0,
                offset: 0.0,
                cutoff: 0.0,
                strength: 3.0,
            },
        ];
        for kind in kinds {
            let glow = Emission::new(
                "glow".into(),
                ramp.clone(),
                transform,
                kind.clone(),
                Filter::Trilinear,
            );
            let bound = glow.largest_radiance_derivative();
            let steepest = (0..64)
                .map(|i| {
                    let p = Vec3::new(0.5 + i as f32 * 0.11, 3.5, 3.5);
                    glow.radiance_derivative(p).1.abs().max_element()
                })
                .fold(0.0, f32::max);
            assert!(
                steepest > 0.0 && f64::from(steepest) <= bound * (1.0 + 1e-6),
                "{kind:?}"
            );
            if let EmissionKind::Radiance(_) = kind {
                assert_eq!(bound, 3.0);
            }
        }
    }

    #[test]
    fn radiance_scales_the_grid_value_and_blackbody_follows_the_table() {
        let transform = IndexTransform::uniform(1.0, DVec3::ZERO);
        let flames = Emission::new(
            "flames".into(),
            constant(2.0),
            transform,
            EmissionKind::Radiance(Vec3::new(1.0, 0.5, 0.25)),
            Filter::Trilinear,
        );
        assert_eq!(flames.radiance(Vec3::splat(1.5)), Vec3::new(2.0, 1.0, 0.5));
        let kind = |cutoff| EmissionKind::Blackbody {
            scale: 1000.0,
            offset: 0.5,
            cutoff,
            strength: 3.0,
        };
        // v = 2: T = 1500 K.
        let fire = Emission::new(
            "t".into(),
            constant(2.0),
            transform,
            kind(0.0),
            Filter::Trilinear,
        );
        let le = fire.radiance(Vec3::splat(1.5));
        let exact = 3.0 * blackbody_rgb(1500.0);
        assert!(
            (le - exact).abs().max_element() < 1e-3 * exact.max_element(),
            "{le} {exact}"
        );
        // Between table entries: within 0.5 % of the exact colour.
        let between = fire.blackbody(1234.5);
        let exact = blackbody_rgb(1234.5);
        assert!((between - exact).abs().max_element() < 5e-3 * exact.max_element());
        let cut = Emission::new(
            "t".into(),
            constant(2.0),
            transform,
            kind(1600.0),
            Filter::Nearest,
        );
        assert_eq!(cut.radiance(Vec3::splat(1.5)), Vec3::ZERO);
    }
}
