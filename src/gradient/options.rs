//! What a gradient pass computes: the estimator, samples, seed, the parameter and its domain.

use glam::IVec3;

use crate::gradient::adjoint::{AdjointOptions, Estimator, Suffix, DEFAULT_SUFFIX_PATHS};
use crate::gradient::pixel_samples::PixelSamples;
use crate::render::alpha::ALPHA_SEED_SALT;

#[derive(Debug, Clone, Copy)]
pub struct GradOptions {
    pub adjoint: AdjointOptions,
    pub spp: u32,
    pub seed: u64,
    /// Keep only the grid's active voxels (`--domain active`).
    pub active_only: bool,
    pub progress: bool,
    /// Which grid's values the gradient is with respect to.
    pub parameter: Parameter,
    /// One colour channel of a colour parameter (an RGB albedo grid's red, green or blue): the
    /// pass weights only that channel of the adjoint image, and its grid is that channel's.
    pub channel: Option<usize>,
    /// The voxels (inclusive index box) whose gradient is wanted, when they are not the grid's
    /// own: an optimisation's unknown has a fixed domain, which its current bricks (none, for an
    /// empty start) do not cover. `None`: every voxel the pass's lookups can weight.
    pub domain: Option<(IVec3, IVec3)>,
    /// What the adjoint image weights: the pixels' radiance, or their alpha.
    pub measured: Measured,
    /// How many paths go through each pixel: `spp` each, or as many on average in proportion
    /// to the adjoint (an optimisation step's).
    pub samples: PixelSamples,
}

/// The pixel values a pass differentiates.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Measured {
    /// The camera paths' radiance (the estimators' business).
    #[default]
    Radiance,
    /// The camera rays' alpha, 1 − T (`render::alpha`, `alpha_gradient`): grey, its adjoint's
    /// three channels add up.
    Alpha,
}

/// The grid a gradient is taken with respect to.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Parameter {
    /// The density grid, through σt (the estimators' business).
    #[default]
    Extinction,
    /// The emission grid's values, through Le (`emission_gradient`).
    Emission,
    /// The albedo grid's values (`albedo_gradient`), one colour channel per pass for an RGB grid.
    Albedo,
}

crate::display_as_value_enum!(Parameter);

impl GradOptions {
    /// The seed of the pass's random streams: alpha's apart from the colour's of the same seed.
    pub fn stream_seed(&self) -> u64 {
        match self.measured {
            Measured::Radiance => self.seed,
            Measured::Alpha => self.seed ^ ALPHA_SEED_SALT,
        }
    }

    /// Per-path suffixes over every voxel of the domain, without a progress bar: what tests,
    /// benchmarks and comparisons use.
    pub fn new(estimator: Estimator, spp: u32, seed: u64, max_depth: u32) -> Self {
        GradOptions {
            adjoint: AdjointOptions {
                estimator,
                suffix: Suffix::PerPath,
                suffix_paths: DEFAULT_SUFFIX_PATHS,
                max_depth,
            },
            spp,
            seed,
            active_only: false,
            progress: false,
            parameter: Parameter::Extinction,
            channel: None,
            domain: None,
            measured: Measured::Radiance,
            samples: PixelSamples::Uniform,
        }
    }
}
