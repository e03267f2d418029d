//! A gradient pass's quanta. Its samples are added as whole quanta (`Quanta`), whose integer sums
//! are the same bits in any order, on any number of threads or processes; but an i64 spans 2⁶³
//! quanta, and one quantum cannot serve a pixel whose adjoint is 10²⁰ times the others' (a hot
//! pixel in a target): sized for it, the others' samples dither to nothing but noise (a gradient
//! of exactly 0 beside a pixel of 10²⁰ that sees only sky); sized for them, its own overflow. So
//! a pass groups its pixels in bands of adjoint size, each band with its quantum and its grid,
//! and adds the bands in f64 at the end, band by band: the same bits whatever the samples' order.
//! A pass whose adjoints span less than `BAND_RANGE` (nearly every one) has one band, and the
//! bits of the single quantum it always had.

use glam::{IVec3, Vec3};

use crate::gradient::grid::{Accumulator, GradientGrid, Quanta};

/// How far below a band's largest adjoint its smallest may lie: 2³⁶. With the quantum that the
/// largest sets (`quantum_for`: one sample of it is at most 2⁴⁴ quanta), a sample of the smallest
/// still spans 2⁸ quanta per unit of the scale, so dithering adds little to its own noise. A
/// target's ordinary residuals span less (f32 rounding leaves some 10⁻⁸ of a pixel's value where
/// the render matches it); a hot pixel 10¹² times the rest does not fit.
const BAND_RANGE: f64 = (1u64 << 36) as f64;

/// The quantum of pixels with adjoint images `deltas` at `spp`, each with the scale of its
/// samples' d_pixel (`passes::sample_scale`): the power of two just above the larger of
/// - Σ|δ|·scale / 2⁵⁴: a voxel's sum, at most Σᵢ |δᵢ| times a path's d_pixel, keeps 2⁸ times
///   `scale` of headroom below i64's 2⁶³ quanta, and its resolution follows the whole image's
///   weight, not one pixel's;
/// - the largest |δ|·scale / (spp · 2⁴⁴): one sample, at most |δ|/spp · d_pixel, keeps 2¹⁹ times
///   `scale` of headroom (a peaked phase function's NEE is some 10³ times the light).
///
/// Samples are rounded with a dither (`Quanta::from_f32_dithered`), so that those far below a
/// quantum keep their mean.
fn quantum_for(sizes: impl Iterator<Item = f64>, spp: u32) -> f64 {
    let (largest, total) = sizes.fold((0.0f64, 0.0f64), |(m, s), x| (m.max(x), s + x));
    let bound = (total * 2f64.powi(-54)).max(largest / spp.max(1) as f64 * 2f64.powi(-44));
    if bound > 0.0 && bound.is_finite() {
        2f64.powi(bound.log2().ceil() as i32)
    } else {
        1.0
    }
}

/// The size a pixel's samples are banded by: its adjoint's largest channel times the scale of
/// its samples. Not finite for a non-finite δ, whose samples the pass drops (and counts).
#[inline]
fn size(delta: Vec3, scale: f64) -> f64 {
    f64::from(delta.abs().max_element()) * scale
}

/// A pass's bands: band b holds the pixels of size in [`floors[b]`, `floors[b - 1]`), band 0
/// everything from `floors[0]` up, and the last band everything below; each with its quantum.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantumBands {
    floors: Vec<f64>,
    quanta: Vec<f64>,
}

impl QuantumBands {
    /// The bands of adjoint images `deltas`, each with the scale of its samples, at `spp`.
    /// Non-finite δs are left out: one infinite δ would make the quantum 1 and round every other
    /// sample to 0 (its own samples are dropped and counted by the pass).
    pub fn of<'a>(deltas: impl IntoIterator<Item = (&'a [Vec3], f64)> + Clone, spp: u32) -> Self {
        let sizes = || {
            (deltas.clone().into_iter())
                .flat_map(|(delta, scale)| delta.iter().map(move |&d| size(d, scale)))
                .filter(|x| x.is_finite() && *x > 0.0)
        };
        let mut floors = Vec::new();
        let mut quanta = Vec::new();
        let mut ceiling = f64::INFINITY;
        // Each band's floor from the largest size below the last band's floor: a few passes over
        // the sizes, one per band, none for the bands no pixel falls in.
        while let Some(largest) = sizes().filter(|&x| x < ceiling).reduce(f64::max) {
            let floor = largest / BAND_RANGE;
            quanta.push(quantum_for(
                sizes().filter(|&x| x < ceiling && x >= floor),
                spp,
            ));
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

    /// One band for every pixel of `deltas`, as `of` would size its first: for passes whose paths
    /// follow the adjoint (`PixelSamples::Adjoint`). A path there weighs about the same at every
    /// pixel, 1/k for k paths per unit of |δ| over the whole batch, so a pixel far below a hot
    /// one takes a path rarely and a heavy one: a band sized by its own |δ| would saturate.
    pub fn single<'a>(deltas: impl IntoIterator<Item = (&'a [Vec3], f64)>, spp: u32) -> Self {
        let sizes = (deltas.into_iter())
            .flat_map(|(delta, scale)| delta.iter().map(move |&d| size(d, scale)))
            .filter(|x| x.is_finite());
        QuantumBands::one(quantum_for(sizes, spp))
    }

    /// One band of quantum `quantum` for every pixel.
    pub fn one(quantum: f64) -> Self {
        QuantumBands {
            floors: Vec::new(),
            quanta: vec![quantum],
        }
    }

    /// The band of a pixel of adjoint `delta` whose samples have `scale`; band 0 for a
    /// non-finite δ (the pass drops its samples).
    #[inline]
    pub fn band_of(&self, delta: Vec3, scale: f64) -> usize {
        let x = size(delta, scale);
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

    #[test]
    fn adjoints_within_the_range_have_one_band_and_the_single_quantum() {
        let delta = [Vec3::new(1e-9, 0.0, 0.0), Vec3::splat(0.5), Vec3::ZERO];
        let bands = QuantumBands::of([(&delta[..], 4.0)], 8);
        assert_eq!(bands.len(), 1);
        // The larger bound: the largest sample, 0.5·4/8 = 2⁻², over 2⁴⁴.
        assert_eq!(bands.quantum(0), 2f64.powi(-46));
        assert!((0..3).all(|i| bands.band_of(delta[i], 4.0) == 0));
    }

    #[test]
    fn a_pixel_beyond_the_range_has_a_band_and_quantum_of_its_own() {
        let ordinary = [Vec3::splat(0.25), Vec3::splat(0.5), Vec3::ZERO];
        let mut delta = ordinary.to_vec();
        delta.push(Vec3::new(0.0, 1e20, 0.0));
        delta.push(Vec3::splat(f32::INFINITY));
        let bands = QuantumBands::of([(&delta[..], 1.0)], 8);
        let alone = QuantumBands::of([(&ordinary[..], 1.0)], 8);
        assert_eq!(bands.len(), 2);
        let band = |i: usize| bands.band_of(delta[i], 1.0);
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
        let bands = QuantumBands::of([(&[Vec3::ZERO][..], 1.0)], 8);
        assert_eq!((bands.len(), bands.quantum(0)), (1, 1.0));
        assert_eq!(bands.band_of(Vec3::ZERO, 1.0), 0);
    }
}
