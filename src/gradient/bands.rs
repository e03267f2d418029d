//! A gradient pass's quanta. Its samples are added as whole quanta (`Quanta`), whose integer sums
//! are the same bits in any order, on any number of threads or processes; but an i64 spans 2⁶³
//! quanta, and one quantum cannot serve a pixel whose adjoint is 10²⁰ times the others' (a hot
//! pixel in a target): sized for it, the others' samples dither to nothing but noise (a gradient
//! of exactly 0 beside a pixel of 10²⁰ that sees only sky); sized for them, its own overflow. So
//! a pass groups its pixels in bands of sample size (the adjoint times what a path there weighs),
//! each band with its quantum and its grid, and adds the bands in f64 at the end, band by band:
//! the same bits whatever the samples' order.
//! A pass whose samples' sizes span less than `BAND_RANGE` (nearly every one) has one band, and
//! the bits of the single quantum it always had.

use glam::{IVec3, Vec3};

use crate::gradient::grid::{Accumulator, GradientGrid, Quanta};
use crate::gradient::pixel_samples::PixelSamples;

/// How far below a band's largest sample size its smallest may lie: 2³⁶. With the quantum that
/// the largest sets (`quantum_for`: one sample of it is at most 2⁴⁴ quanta), a sample of the
/// smallest still spans 2⁸ quanta per unit of the scale, so dithering adds little to its own
/// noise. A target's ordinary residuals span less (f32 rounding leaves some 10⁻⁸ of a pixel's
/// value where the render matches it); a hot pixel 10¹² times the rest does not fit.
const BAND_RANGE: f64 = (1u64 << 36) as f64;

/// The quantum of pixels of `sizes` at `spp`: the power of two just above the larger of
/// - Σ mass / 2⁵⁴: a voxel's sum, at most Σᵢ |δᵢ| times a path's d_pixel, keeps 2⁸ times
///   `scale` of headroom below i64's 2⁶³ quanta, and its resolution follows the whole image's
///   weight, not one pixel's;
/// - the largest sample size / (spp · 2⁴⁴): one sample, at most |δ|/spp · d_pixel for uniform
///   paths, keeps 2¹⁹ times `scale` of headroom (a peaked phase function's NEE is some 10³ times
///   the light).
///
/// Samples are rounded with a dither (`Quanta::from_f32_dithered`), so that those far below a
/// quantum keep their mean.
fn quantum_for(sizes: impl Iterator<Item = PixelSize>, spp: u32) -> f64 {
    let (largest, total) = sizes.fold((0.0f64, 0.0f64), |(m, s), x| (m.max(x.sample), s + x.mass));
    let bound = (total * 2f64.powi(-54)).max(largest / spp.max(1) as f64 * 2f64.powi(-44));
    if bound > 0.0 && bound.is_finite() {
        2f64.powi(bound.log2().ceil() as i32)
    } else {
        1.0
    }
}

/// A pixel's adjoint's largest channel times `scale`. Not finite for a non-finite δ, whose
/// samples the pass drops (and counts).
#[inline]
fn size(delta: Vec3, scale: f64) -> f64 {
    f64::from(delta.abs().max_element()) * scale
}

/// What a pixel's samples add, as `size`s: `mass` with the scale of their d_pixel (what all of
/// them add up to, on average), `sample` with that scale times their path weight
/// (`PixelSamples::path_weight`: what one of them weighs, times spp). The two are the same for
/// uniform paths; a pixel that takes paths in proportion to its |δ| has samples as heavy as
/// every other pixel's, however small its |δ|, and is banded with them by `sample`.
#[derive(Clone, Copy)]
struct PixelSize {
    sample: f64,
    mass: f64,
}

/// A pass's bands: band b holds the pixels of sample size in [`floors[b]`, `floors[b - 1]`),
/// band 0 everything from `floors[0]` up, and the last band everything below; each with its
/// quantum.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantumBands {
    floors: Vec<f64>,
    quanta: Vec<f64>,
}

impl QuantumBands {
    /// The bands of adjoint images `deltas` at `spp`, each with the scale of its samples and
    /// the paths its pixels take. Non-finite δs are left out: one infinite δ would make the
    /// quantum 1 and round every other sample to 0 (its own samples are dropped and counted by
    /// the pass).
    pub fn of<'a>(
        deltas: impl IntoIterator<Item = (&'a [Vec3], f64, PixelSamples)> + Clone,
        spp: u32,
    ) -> Self {
        let sizes = || {
            (deltas.clone().into_iter())
                .flat_map(move |(delta, scale, samples)| {
                    delta.iter().map(move |&d| PixelSize {
                        sample: size(d, scale * samples.path_weight(spp, d)),
                        mass: size(d, scale),
                    })
                })
                .filter(|x| x.sample.is_finite() && x.sample > 0.0)
        };
        let mut floors = Vec::new();
        let mut quanta = Vec::new();
        let mut ceiling = f64::INFINITY;
        // Each band's floor from the largest size below the last band's floor: a few passes over
        // the sizes, one per band, none for the bands no pixel falls in.
        while let Some(largest) = sizes()
            .map(|x| x.sample)
            .filter(|&x| x < ceiling)
            .reduce(f64::max)
        {
            let floor = largest / BAND_RANGE;
            let band = sizes().filter(|x| x.sample < ceiling && x.sample >= floor);
            quanta.push(quantum_for(band, spp));
            floors.push(floor);
            ceiling = floor;
        }
        if quanta.is_empty() {
            quanta.push(1.0);
        }
        // The last band also takes the zero sizes (and, through `band_of`, nothing else).
        floors.pop();
        QuantumBands { floors, quanta }
    }

    /// One band of quantum `quantum` for every pixel.
    pub fn one(quantum: f64) -> Self {
        QuantumBands {
            floors: Vec::new(),
            quanta: vec![quantum],
        }
    }

    /// The band of a pixel of adjoint `delta` whose samples have `scale` and `path_weight`
    /// (`PixelSamples::path_weight`); band 0 for a non-finite δ (the pass drops its samples).
    #[inline]
    pub fn band_of(&self, delta: Vec3, scale: f64, path_weight: f64) -> usize {
        let x = size(delta, scale * path_weight);
        if !x.is_finite() {
            return 0;
        }
        self.floors.iter().take_while(|&&floor| x < floor).count()
    }

    /// Band `band`'s quantum.
    #[inline]
    pub fn quantum(&self, band: usize) -> f64 {
        self.quanta[band]
    }

    pub fn len(&self) -> usize {
        self.quanta.len()
    }

    pub fn is_empty(&self) -> bool {
        self.quanta.is_empty()
    }
}

/// A gradient in quanta, one grid per band (`QuantumBands`).
pub struct BandedGradient {
    pub bands: QuantumBands,
    /// Band b's sums, in quanta of `bands.quantum(b)`.
    pub grids: Vec<GradientGrid<Quanta>>,
}

impl BandedGradient {
    /// Empty grids like `grid` (`passes::gradient_grid_for`), one per band.
    pub fn new(bands: QuantumBands, grid: GradientGrid<Quanta>) -> Self {
        let mut grids: Vec<_> = (1..bands.len()).map(|_| grid.empty_like()).collect();
        grids.insert(0, grid);
        BandedGradient { bands, grids }
    }

    /// ∂loss/∂voxel: each band's quanta times its quantum, added band by band in f64.
    pub fn values<U: Accumulator>(&self) -> GradientGrid<U> {
        let quantum = |b| self.bands.quantum(b);
        match &self.grids[..] {
            [one] => one.converted(quantum(0)),
            [first, rest @ ..] => {
                let mut sum: GradientGrid<f64> = first.converted(quantum(0));
                for (b, grid) in rest.iter().enumerate() {
                    sum.merge(grid, quantum(b + 1));
                }
                sum.converted(1.0)
            }
            [] => unreachable!("a pass has at least one band"),
        }
    }

    /// Every voxel with its value, as `values` gives them.
    pub fn voxels(&self) -> Vec<(IVec3, f64)> {
        match &self.grids[..] {
            [one] => {
                let quantum = self.bands.quantum(0);
                one.voxels().map(|(v, q)| (v, q * quantum)).collect()
            }
            _ => self.values::<f64>().voxels().collect(),
        }
    }

    /// The blocks every band holds.
    pub fn block_count(&self) -> usize {
        self.grids.iter().map(GradientGrid::block_count).sum()
    }

    pub fn memory_bytes(&self) -> usize {
        self.grids.iter().map(GradientGrid::memory_bytes).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use PixelSamples::Uniform;

    #[test]
    fn adjoints_within_the_range_have_one_band_and_the_single_quantum() {
        let delta = [Vec3::new(1e-9, 0.0, 0.0), Vec3::splat(0.5), Vec3::ZERO];
        let bands = QuantumBands::of([(&delta[..], 4.0, Uniform)], 8);
        assert_eq!(bands.len(), 1);
        // The larger bound: the largest sample, 0.5·4/8 = 2⁻², over 2⁴⁴.
        assert_eq!(bands.quantum(0), 2f64.powi(-46));
        assert!((0..3).all(|i| bands.band_of(delta[i], 4.0, 1.0) == 0));
    }

    #[test]
    fn a_pixel_beyond_the_range_has_a_band_and_quantum_of_its_own() {
        let ordinary = [Vec3::splat(0.25), Vec3::splat(0.5), Vec3::ZERO];
        let mut delta = ordinary.to_vec();
        delta.push(Vec3::new(0.0, 1e20, 0.0));
        delta.push(Vec3::splat(f32::INFINITY));
        let bands = QuantumBands::of([(&delta[..], 1.0, Uniform)], 8);
        let alone = QuantumBands::of([(&ordinary[..], 1.0, Uniform)], 8);
        assert_eq!(bands.len(), 2);
        let band = |i: usize| bands.band_of(delta[i], 1.0, 1.0);
        assert_eq!(
            [band(0), band(1), band(2), band(3), band(4)],
            [1, 1, 1, 0, 0]
        );
        // The ordinary pixels keep the quantum they have without the hot one.
        assert_eq!(bands.quantum(1), alone.quantum(0));
        assert!(bands.quantum(0) > 1e20 * bands.quantum(1));
    }

    #[test]
    fn no_adjoint_has_one_band_of_quantum_one() {
        let bands = QuantumBands::of([(&[Vec3::ZERO][..], 1.0, Uniform)], 8);
        assert_eq!((bands.len(), bands.quantum(0)), (1, 1.0));
        assert_eq!(bands.band_of(Vec3::ZERO, 1.0, 0.0), 0);
    }

    #[test]
    fn paths_that_follow_the_adjoint_are_banded_by_what_they_weigh() {
        // 96 residuals of 1, four of 10⁻³ to 10⁻³⁰ and a hot pixel of 10³⁰: in proportion to |δ|
        // the residuals' paths all weigh 1/k, whatever their |δ|, and share one band; the hot
        // pixel, capped at 8·spp paths, weighs 10³⁰/(8·spp) a path and has a band of its own.
        let mut delta = vec![Vec3::X; 96];
        delta.extend([1e-3, 1e-10, 1e-20, 1e-30].map(|a| Vec3::new(a, 0.0, 0.0)));
        delta.push(Vec3::new(1e30, 0.0, 0.0));
        let pixels: Vec<(f32, f32)> = delta.iter().map(|d| (d.x, 1.0)).collect();
        let samples = PixelSamples::following_adjoint(&pixels, 8);
        let bands = QuantumBands::of([(&delta[..], 1.0, samples)], 8);
        assert_eq!(bands.len(), 2);
        let band = |d: &Vec3| bands.band_of(*d, 1.0, samples.path_weight(8, *d));
        assert!(delta[..100].iter().all(|d| band(d) == 1));
        assert_eq!(band(&delta[100]), 0);
        // The residuals' quantum is sized by one path's weight, 1/k (k paths per unit of |δ|,
        // about 7.75 here: none of them is capped): every one of their samples spans the same
        // 2⁴³ to 2⁴⁴ quanta.
        let PixelSamples::Adjoint { per_adjoint } = samples else {
            panic!("{samples:?}")
        };
        let quanta = 1.0 / per_adjoint / bands.quantum(1);
        assert!(
            quanta <= 2f64.powi(44) && quanta > 2f64.powi(43),
            "{quanta}"
        );
    }
}
