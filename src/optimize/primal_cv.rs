//! Recursive control variates for the primal image (Nicolet et al. 2023, "Recursive control
//! variates for inverse rendering", the primary-sample-space form).
//!
//! Each step's adjoint image δ = ∂loss/∂pixel comes from a noisy primal render F(θ, ξ). Between
//! two visits of a view θ changes little, so a render of the *previous* θ with *this* visit's
//! random numbers, H = F(θ_prev, ξ), is strongly correlated with F and the running estimate Ĩ
//! of the view's image can be carried forward through it:
//!
//!   Ĩ_k = F(θ_k, ξ_k) + w · (Ĩ_{k−1} − F(θ_{k−1}, ξ_k)),
//!
//! per pixel and channel, where w ∈ [0, 1] minimises the variance of Ĩ_k: with Var H = v_h,
//! Var F = v_f and Cov(H, F) = c (exponential moving estimates, as Adam's moments) and v the
//! variance of Ĩ_{k−1},
//!
//!   v ← w²·(v + v_h) + v_f − 2·w·c,    w ← c / (v_h + v).
//!
//! H is rendered at the end of a visit, before θ moves, so no θ is kept: each visit costs two
//! primal renders (F now, H for the next visit). Random numbers are a function of (seed, view,
//! visit), so H and the next visit's F share them whatever the batch order.

use glam::Vec3;
use rand::RngCore;

use crate::render::sampling::pixel_rng;

/// The moving averages' rates (the reference implementation's, as Adam's β1 and β2).
const MEAN_RATE: f32 = 0.9;
const VARIANCE_RATE: f32 = 0.999;
/// Distinguishes the control variates' random streams from every other pass of a run.
const PRIMAL_CV_SALT: u64 = 0x5ca1_ab1e_c0de_0001;

/// The running image estimate of every training view.
pub struct PrimalEstimates {
    seed: u64,
    views: Vec<ViewEstimate>,
}

impl PrimalEstimates {
    pub fn new(seed: u64, views: usize) -> Self {
        PrimalEstimates {
            seed,
            views: (0..views).map(|_| ViewEstimate::default()).collect(),
        }
    }

    /// The seed of view `view`'s primal render at its current visit (`next`: at the one after).
    pub fn visit_seed(&self, view: usize, next: bool) -> u64 {
        let visit = self.views[view].visits + u32::from(next);
        pixel_rng(self.seed ^ PRIMAL_CV_SALT, view as u64, u64::from(visit)).next_u64()
    }

    /// Ĩ of view `view` at this visit, from `current` = F(θ, ξ_k) (rendered with
    /// `visit_seed(view, false)`).
    pub fn update(&mut self, view: usize, current: Vec<Vec3>) -> &[Vec3] {
        self.views[view].update(current)
    }

    /// Keeps `next` = F(θ, ξ_{k+1}) (rendered with `visit_seed(view, true)` before θ moves) for
    /// view `view`'s next visit, and ends this one.
    pub fn remember(&mut self, view: usize, next: Vec<Vec3>) {
        let v = &mut self.views[view];
        v.previous = next;
        v.visits += 1;
    }
}

/// One view's estimate Ĩ, H for its next visit, and the per-pixel statistics that set w.
#[derive(Default)]
struct ViewEstimate {
    visits: u32,
    image: Vec<Vec3>,
    previous: Vec<Vec3>,
    statistics: Statistics,
    /// v: the variance of Ĩ.
    variance: Vec<Vec3>,
    /// w: the control variate's weight.
    weight: Vec<Vec3>,
}

impl ViewEstimate {
    fn update(&mut self, current: Vec<Vec3>) -> &[Vec3] {
        if self.visits == 0 {
            let n = current.len();
            self.image = current;
            self.variance = vec![Vec3::ZERO; n];
            self.weight = vec![Vec3::ZERO; n];
            self.statistics = Statistics::new(n);
            return &self.image;
        }
        // The weights need statistics of at least one earlier pair (H, F): w stays 0 until then.
        if self.statistics.updates > 0 {
            for i in 0..current.len() {
                let (v_h, v_f, c) = self.statistics.get(i);
                let (w, v) = (self.weight[i], self.variance[i]);
                let v = w * w * (v + v_h) + v_f - 2.0 * w * c;
                let w = c / (v_h + v);
                self.variance[i] = v;
                self.weight[i] = Vec3::select(w.is_finite_mask(), w, Vec3::ZERO).clamp(Vec3::ZERO, Vec3::ONE);
            }
        }
        for (i, f) in current.iter().enumerate() {
            self.image[i] = self.weight[i] * (self.image[i] - self.previous[i]) + *f;
        }
        self.statistics.update(&self.previous, &current);
        &self.image
    }
}

/// Exponential moving estimates of the means, variances and covariance of two per-pixel
/// variables x = H and y = F (Welford's update with moving averages, bias-corrected as Adam's).
#[derive(Default)]
struct Statistics {
    updates: i32,
    mean_x: Vec<Vec3>,
    mean_y: Vec<Vec3>,
    var_x: Vec<Vec3>,
    var_y: Vec<Vec3>,
    cov: Vec<Vec3>,
}

impl Statistics {
    fn new(pixels: usize) -> Self {
        let zero = vec![Vec3::ZERO; pixels];
        Statistics {
            updates: 0,
            mean_x: zero.clone(),
            mean_y: zero.clone(),
            var_x: zero.clone(),
            var_y: zero.clone(),
            cov: zero,
        }
    }

    fn update(&mut self, x: &[Vec3], y: &[Vec3]) {
        let before = 1.0 - MEAN_RATE.powi(self.updates);
        let after = 1.0 - MEAN_RATE.powi(self.updates + 1);
        for i in 0..x.len() {
            // Deviations from the mean before and after this sample joins it.
            let (dx1, dy1) = if self.updates > 0 {
                (x[i] - self.mean_x[i] / before, y[i] - self.mean_y[i] / before)
            } else {
                (x[i], y[i])
            };
            self.mean_x[i] = MEAN_RATE * self.mean_x[i] + (1.0 - MEAN_RATE) * x[i];
            self.mean_y[i] = MEAN_RATE * self.mean_y[i] + (1.0 - MEAN_RATE) * y[i];
            let (dx2, dy2) = (x[i] - self.mean_x[i] / after, y[i] - self.mean_y[i] / after);
            let rate = 1.0 - VARIANCE_RATE;
            self.var_x[i] = VARIANCE_RATE * self.var_x[i] + rate * dx1 * dx2;
            self.var_y[i] = VARIANCE_RATE * self.var_y[i] + rate * dy1 * dy2;
            self.cov[i] = VARIANCE_RATE * self.cov[i] + rate * dx1 * dy2;
        }
        self.updates += 1;
    }

    /// (Var x, Var y, Cov(x, y)) of pixel `i`, bias-corrected.
    fn get(&self, i: usize) -> (Vec3, Vec3, Vec3) {
        let correction = 1.0 / (1.0 - VARIANCE_RATE.powi(self.updates));
        (
            self.var_x[i] * correction,
            self.var_y[i] * correction,
            self.cov[i] * correction,
        )
    }
}
