//! Extinction gradients: path replay (`adjoint`), the passes over the image, the sparse gradient
//! grid, losses, finite differences and the estimator check. Uses `volume`, `io` and `render`.

pub mod adjoint;
pub mod albedo_gradient;
pub mod alpha_gradient;
pub mod bands;
pub mod emission_gradient;
pub mod fd;
pub mod gradcheck;
pub mod grid;
mod in_order;
pub mod loss;
pub mod objective;
pub mod options;
pub mod passes;
pub mod pixel_samples;
pub mod runs;
