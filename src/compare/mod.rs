//! `volgrad compare`: speed against accuracy, and stability where estimators are known to fail.
//!
//! - A reference gradient that favours no estimator: the mean of joint and drt runs (alternating,
//!   each with its own seed) and its per-voxel standard error, checked against finite differences
//!   before it is trusted.
//! - Equal-time sweeps: each method runs at 1, 2, 4, … spp until its time budget is spent; every
//!   run is scored against the reference. The reference's own noise adds Σ se² to ‖g − ref‖², so it
//!   is subtracted (`rel_rmse`; the raw value is kept as `rel_rmse_raw`): otherwise every curve
//!   would flatten at the reference's noise floor and the speed-ups would shrink towards 1.
//! - The same for the forward renderer (image error against time, majorant grid against global).
//! - The stability suite: small in-memory scenes built to break estimators, each estimator's
//!   ⟨g, 1⟩ against finite differences, its spread, and a count of non-finite values.
//!
//! Every gradient is that of the mean pixel value (loss `mean`). Uses every layer below
//! it (`volume`, `io`, `render`, `gradient`).

mod equal_time;
mod reference;
mod stability;
mod study;
mod summary;

pub use equal_time::*;
pub use reference::*;
pub use stability::*;
pub use study::*;
pub use summary::*;
