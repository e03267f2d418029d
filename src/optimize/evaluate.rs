//! How good the unknown is: held-out views rendered at a fixed seed and `eval_spp` (PSNR and
//! relative RMSE against their targets), and, when the truth is known, the volume's error and how
//! much density sits where the truth is empty ("haze").

use glam::IVec3;
use rayon::prelude::*;

use crate::cluster::images::render_shared;
use crate::cluster::Cluster;
use crate::io::images::RgbImage;
use crate::optimize::problem::Problem;
use crate::optimize::run_file::EvalSpp;
use crate::render::image::RenderOptions;
use crate::render::interrupt;
use crate::render::scene::Scene;

/// Seeds the held-out renders apart from training and targets; the same for every evaluation, so
/// two evaluations differ only by the unknown.
const EVALUATION_SEED_SALT: u64 = 0x3e7a_1c0d_e5ee_d000;

/// Seeds the second half of a held-out render apart from the first, and an "auto" evaluation's
/// later rounds apart from its first.
const HALF_SEED_SALT: u64 = 0x27d4_eb2f_1656_67c5;
const ROUND_SEED_SALT: u64 = 0x9e37_79b9_7f4a_7c15;

/// PSNR = 10·log10(max(target)² / MSE), over pixels and channels.
pub fn psnr(image: &RgbImage, target: &RgbImage) -> f64 {
    10.0 * (peak(target).powi(2) / mean_squared_error(image, target).max(1e-30)).log10()
}

/// The largest value of any channel of `image`.
fn peak(image: &RgbImage) -> f64 {
    f64::from((image.pixels.iter()).fold(0.0f32, |m, c| m.max(c.max_element())))
}

fn mean_squared_error(image: &RgbImage, target: &RgbImage) -> f64 {
    let sum: f64 = image
        .pixels
        .iter()
        .zip(&target.pixels)
        // In f64: a difference of 1e20 squares beyond f32.
        .map(|(&a, &b)| (a.as_dvec3() - b.as_dvec3()).length_squared())
        .sum();
    sum / (3 * image.pixels.len().max(1)) as f64
}

/// ‖image − target‖ / ‖target‖.
pub fn relative_rmse(image: &RgbImage, target: &RgbImage) -> f64 {
    let norm: f64 = target
        .pixels
        .iter()
        .map(|c| c.as_dvec3().length_squared())
        .sum();
    (mean_squared_error(image, target) * (3 * image.pixels.len()) as f64 / norm.max(1e-30)).sqrt()
}

#[derive(Debug, Clone, Default)]
pub struct Evaluation {
    /// Averages over the held-out views.
    pub psnr: f64,
    /// The PSNR the evaluation's own Monte Carlo noise allows: the score of a perfect volume,
    /// rendered at the evaluation's spp, against noise-free targets. A `psnr` near it is limited
    /// by the evaluation, not by the volume.
    pub noise_psnr: f64,
    /// The samples per pixel the held-out renders took, averaged over their pixels.
    pub spp: f64,
    /// The average over the held-out views under lights no training view had (none: `None`).
    pub relit_psnr: Option<f64>,
    pub relative_rmse: f64,
    /// RMS difference to the truth over the final level's voxels (grid-value units).
    pub volume_rmse: Option<f64>,
    /// The unknown's mean where the truth is 0 over its mean where it is not.
    pub haze: Option<f64>,
    pub renders: Vec<RgbImage>,
}

/// With `eval_spp = "auto"`, each held-out view's render noise may be at most this share of the
/// error it measures: the PSNR reported is then within 10·log10(1/(1 − 0.1)) = 0.46 dB of the
/// score of the same volume rendered without noise.
const AUTO_NOISE_SHARE: f64 = 0.1;
/// The first round of an "auto" evaluation: enough to measure the noise, and all an evaluation
/// needs while the error is large.
const AUTO_FIRST_SPP: u32 = 16;
/// What an "auto" evaluation may spend: at most this many samples per pixel, and this many paths
/// over all held-out pixels (about 80 s on 2 cores for the worked example's 16 views of 96²), but
/// never fewer than 2 spp.
const AUTO_MAX_SPP: u32 = 4096;
const AUTO_MAX_PATHS: u64 = 1 << 28;

/// Evaluates `scene` (the unknown at level `level`) on the held-out views, each render scaled by
/// its capture's fitted exposure factor (`exposures`, 1 when none is fitted), and against the
/// truth; every rank renders its share of each view's pixels, and all get the same evaluation.
///
/// Each view is rendered as two independent halves of its samples: their mean is the render,
/// and their difference measures its noise, E[(A − B)²]/4 = Var((A + B)/2). With a fixed
/// `eval_spp` that is one round; with "auto" a view gets rounds of more samples until its noise
/// is at most `AUTO_NOISE_SHARE` of its error, or the caps are reached. Every decision is made
/// from images every rank holds whole, so the ranks agree on it. None when a stop
/// (`interrupt::stop_stoppable`, from Ctrl-C) cut it short on any rank: the ranks agree on that
/// after every render.
pub fn evaluate(
    problem: &Problem,
    scene: &Scene,
    level: usize,
    exposures: &[f32],
    cluster: &Cluster,
) -> Option<Evaluation> {
    let stretch = interrupt::Stoppable::begin();
    let stopped = || cluster.max_each([f64::from(u8::from(stretch.stopped()))])[0] > 0.0;
    let mut scene = scene.clone();
    let mut e = Evaluation::default();
    let (mut lit, mut relit) = (0, Vec::new());
    let pixels = heldout_pixels(problem);
    let (first_spp, max_spp) = spp_range(problem);
    let mut paths = 0u64;
    for view in &problem.holdouts {
        problem.look_through(&mut scene, &mut lit, view);
        let exposure = exposures[view.capture];
        let target = view.target_at(exposure);
        let render_half = |round: u64, half: u64, spp: u32| {
            let options = RenderOptions {
                spp,
                seed: problem.settings.seed
                    ^ EVALUATION_SEED_SALT
                    ^ half.wrapping_mul(HALF_SEED_SALT)
                    ^ round.wrapping_mul(ROUND_SEED_SALT),
                max_depth: problem.settings.max_depth,
                progress: false,
            };
            let mut image = render_shared(cluster, &scene, &options).0;
            image.scale(exposure);
            image
        };
        let mut half_spp = (first_spp / 2).max(1);
        let (mut a, mut b) = (render_half(0, 0, half_spp), render_half(0, 1, half_spp));
        let mut round = 1;
        let (image, noise) = loop {
            if stopped() {
                return None;
            }
            let image = RgbImage::average(&a, &b);
            let noise = mean_squared_error(&a, &b) / 4.0;
            let error = mean_squared_error(&image, &target);
            let wanted = wanted_half_spp(half_spp, noise, error).min(max_spp / 2);
            if wanted <= half_spp {
                break (image, noise);
            }
            let more = wanted - half_spp;
            let weight = more as f32 / wanted as f32;
            a = RgbImage::blend(&a, &render_half(round, 0, more), weight);
            b = RgbImage::blend(&b, &render_half(round, 1, more), weight);
            (half_spp, round) = (wanted, round + 1);
        };
        paths +=
            2 * u64::from(half_spp) * u64::from(view.camera.width) * u64::from(view.camera.height);
        e.noise_psnr += 10.0 * (peak(&target).powi(2) / noise.max(1e-30)).log10();
        let view_psnr = psnr(&image, &target);
        e.psnr += view_psnr;
        if view.relit {
            relit.push(view_psnr);
        }
        e.relative_rmse += relative_rmse(&image, &target);
        e.renders.push(image);
    }
    let n = problem.holdouts.len().max(1) as f64;
    e.psnr /= n;
    e.noise_psnr /= n;
    e.relative_rmse /= n;
    e.spp = paths as f64 / pixels.max(1) as f64;
    e.relit_psnr = (!relit.is_empty()).then(|| relit.iter().sum::<f64>() / relit.len() as f64);
    if let Some(truth) = &problem.truth {
        let (rmse, haze) = volume_error(problem, truth, &scene, level);
        e.volume_rmse = Some(rmse);
        e.haze = haze;
    }
    Some(e)
}

/// An evaluation's first and largest samples per pixel: `eval_spp` twice, or "auto"'s range.
pub fn spp_range(problem: &Problem) -> (u32, u32) {
    match problem.settings.eval_spp {
        EvalSpp::Fixed(spp) => (spp, spp),
        EvalSpp::Auto => {
            // At least one sample per half, to measure the noise, however many the pixels.
            let affordable = (AUTO_MAX_PATHS / heldout_pixels(problem).max(1))
                .clamp(2, u64::from(AUTO_MAX_SPP)) as u32;
            (AUTO_FIRST_SPP.min(affordable), affordable)
        }
    }
}

fn heldout_pixels(problem: &Problem) -> u64 {
    (problem.holdouts.iter())
        .map(|v| u64::from(v.camera.width) * u64::from(v.camera.height))
        .sum()
}

/// The samples per half that bring a render's noise to `AUTO_NOISE_SHARE` of its error, from a
/// render of `half_spp` per half whose noise is `noise` and whose error (noise included) is
/// `error`. The noise falls as 1/spp while the error's noise-free part, b = error − noise,
/// stays: N/n ≥ noise·(1 − s)/(s·b) makes noise·n/N ≤ s·(b + noise·n/N). At least doubled, so
/// that a badly measured b costs few rounds; a b of 0 (noise is all the error) asks for the cap.
fn wanted_half_spp(half_spp: u32, noise: f64, error: f64) -> u32 {
    let s = AUTO_NOISE_SHARE;
    if noise <= s * error {
        return half_spp;
    }
    let bias = (error - noise).max(0.0);
    let ratio = noise * (1.0 - s) / (s * bias);
    let wanted = (f64::from(half_spp) * ratio).ceil();
    if wanted.is_finite() && wanted < f64::from(u32::MAX) {
        (wanted as u32).max(2 * half_spp)
    } else {
        u32::MAX
    }
}

/// (RMSE, haze) of the unknown's field against the truth at the final level's voxel centres.
/// Haze is the field's mean where the truth is empty over its mean where the truth is not; it
/// is not defined (`None`) while the field holds next to nothing where the truth has density
/// (under 1e-6 of the truth's mean there: a start of 0, or an estimator that cannot grow one),
/// where the ratio would be any number at all.
fn volume_error(
    problem: &Problem,
    truth: &crate::volume::brickmap::BrickMap,
    scene: &Scene,
    level: usize,
) -> (f64, Option<f64>) {
    let d = &problem.domain;
    let grid = problem.unknown.grid_in(scene);
    // (squared error, empty voxels, density in them, occupied voxels, density in them, the
    // truth's density in them)
    let sums = (d.lo.x..=d.hi.x)
        .into_par_iter()
        .map(|x| {
            let mut s = [0.0f64; 6];
            for y in d.lo.y..=d.hi.y {
                for z in d.lo.z..=d.hi.z {
                    let v = IVec3::new(x, y, z);
                    let t = truth.voxel(v) as f64;
                    let c = grid.trilinear(d.to_level(level, v.as_vec3())) as f64;
                    s[0] += (c - t) * (c - t);
                    if t > 0.0 {
                        s[3] += 1.0;
                        s[4] += c;
                        s[5] += t;
                    } else {
                        s[1] += 1.0;
                        s[2] += c;
                    }
                }
            }
            s
        })
        // Collected, then summed in x order: rayon's `reduce` would add the slices in an order
        // that depends on how the work was split, and so on the number of threads.
        .collect::<Vec<[f64; 6]>>()
        .into_iter()
        .fold([0.0; 6], |a, b| std::array::from_fn(|i| a[i] + b[i]));
    let rmse = (sums[0] / d.voxel_count().max(1) as f64).sqrt();
    let mean_empty = sums[2] / sums[1].max(1.0);
    let mean_occupied = sums[4] / sums[3].max(1.0);
    let truth_occupied = sums[5] / sums[3].max(1.0);
    let haze = (mean_occupied > 1e-6 * truth_occupied).then(|| mean_empty / mean_occupied);
    (rmse, haze)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn psnr_of_a_known_error() {
        let mut target = RgbImage::new(2, 1);
        target.pixels = vec![Vec3::splat(2.0), Vec3::ZERO];
        let mut image = target.clone();
        image.pixels[1] = Vec3::splat(0.2);
        // MSE = 3·0.04 / 6 = 0.02, peak 2: 10·log10(4 / 0.02) = 23.01 dB.
        assert!((psnr(&image, &target) - 23.0103).abs() < 1e-3);
        // ‖e‖ = √(3·0.04), ‖t‖ = √(3·4): ratio 0.1.
        assert!((relative_rmse(&image, &target) - 0.1).abs() < 1e-6);
    }

    /// "auto" asks for just the samples that bring the noise to its share of the error: none
    /// more when it is there, the cap when noise is all the error, and otherwise a count at
    /// which the noise, falling as 1/spp, is exactly that share of the new error.
    #[test]
    fn auto_spp_brings_the_noise_to_its_share() {
        assert_eq!(wanted_half_spp(8, 0.05, 1.0), 8);
        assert_eq!(wanted_half_spp(8, 1.0, 1.0), u32::MAX);
        assert_eq!(wanted_half_spp(8, 0.15, 1.0), 16, "at least doubled");
        let (noise, error) = (0.5, 1.0);
        let n = wanted_half_spp(8, noise, error);
        let new_noise = noise * 8.0 / f64::from(n);
        let new_error = (error - noise) + new_noise;
        assert!(
            (new_noise / new_error - AUTO_NOISE_SHARE).abs() < 1e-3,
            "{n} spp per half: noise {new_noise} of error {new_error}"
        );
    }
}
