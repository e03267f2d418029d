//! The colour of a blackbody at temperature T, as linear sRGB (Rec. 709 primaries), normalised as
//! pbrt-v4's `BlackbodySpectrum`: Planck's spectral radiance divided by its value at the peak
//! wavelength (Wien's law, λ_max = b / T), so the spectrum's maximum is 1 at every temperature;
//! then XYZ = ∫ B(λ)·(x̄, ȳ, z̄)(λ) dλ / ∫ ȳ dλ over 360–830 nm, and sRGB from XYZ.
//!
//! The colour-matching functions are Wyman, Sloan and Shirley's multi-lobe Gaussian fit to the
//! CIE 1931 2° observer ("Simple analytic approximations to the CIE XYZ color matching
//! functions", JCGT 2013), within about 1 % of the tables: a blackbody's colour does not need more.

use glam::Vec3;

/// Planck's constant, the speed of light and Boltzmann's constant (SI), and Wien's constant.
const H: f64 = 6.626_070_15e-34;
const C: f64 = 2.997_924_58e8;
const KB: f64 = 1.380_649e-23;
const WIEN: f64 = 2.897_771_955e-3;

/// Planck's law: spectral radiance at wavelength `lambda` (m) and temperature `t` (K).
fn planck(lambda: f64, t: f64) -> f64 {
    let l5 = lambda.powi(5);
    2.0 * H * C * C / (l5 * ((H * C / (lambda * KB * t)).exp_m1()))
}

/// A piecewise Gaussian: its width differs below and above the mean.
fn lobe(x: f64, mean: f64, below: f64, above: f64) -> f64 {
    let t = (x - mean) * if x < mean { below } else { above };
    (-0.5 * t * t).exp()
}

/// (x̄, ȳ, z̄) at wavelength `nm` (Wyman et al. 2013, multi-lobe fit).
fn cmf(nm: f64) -> [f64; 3] {
    let x = 1.056 * lobe(nm, 599.8, 0.0264, 0.0323) + 0.362 * lobe(nm, 442.0, 0.0624, 0.0374)
        - 0.065 * lobe(nm, 501.1, 0.0490, 0.0382);
    let y = 0.821 * lobe(nm, 568.8, 0.0213, 0.0247) + 0.286 * lobe(nm, 530.9, 0.0613, 0.0322);
    let z = 1.217 * lobe(nm, 437.0, 0.0845, 0.0278) + 0.681 * lobe(nm, 459.0, 0.0385, 0.0725);
    [x, y, z]
}

/// The normalised blackbody's linear sRGB at temperature `t` kelvin (0 for t ≤ 0).
pub fn blackbody_rgb(t: f64) -> Vec3 {
    if !(t > 0.0 && t.is_finite()) {
        return Vec3::ZERO;
    }
    let peak = planck(WIEN / t, t);
    let (mut xyz, mut y_integral) = ([0.0f64; 3], 0.0);
    for nm in 360..=830 {
        let nm = nm as f64;
        let b = planck(nm * 1e-9, t) / peak;
        let m = cmf(nm);
        for k in 0..3 {
            xyz[k] += b * m[k];
        }
        y_integral += m[1];
    }
    let [x, y, z] = xyz.map(|v| v / y_integral);
    Vec3::new(
        (3.240_454_2 * x - 1.537_138_5 * y - 0.498_531_4 * z) as f32,
        (-0.969_266_0 * x + 1.876_010_8 * y + 0.041_556_0 * z) as f32,
        (0.055_643_4 * x - 0.204_025_9 * y + 1.057_225_2 * z) as f32,
    )
    .max(Vec3::ZERO)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planck's peak sits where Wien says, and the fit's ȳ integrates to the CIE table's 106.86 nm.
    #[test]
    fn planck_peaks_at_wien_and_the_fit_integrates_like_the_tables() {
        let t = 3000.0;
        let peak = WIEN / t;
        assert!(planck(peak, t) > planck(peak * 0.98, t));
        assert!(planck(peak, t) > planck(peak * 1.02, t));
        let y: f64 = (360..=830).map(|nm| cmf(nm as f64)[1]).sum();
        assert!((y - 106.857).abs() < 1.5, "∫ȳ = {y}");
    }

    /// A candle is red-orange, 6500 K is near white (D65's temperature), 20,000 K is blue.
    #[test]
    fn blackbody_colours_go_from_red_to_white_to_blue() {
        let candle = blackbody_rgb(1800.0);
        assert!(candle.x > 2.0 * candle.y && candle.y > candle.z, "{candle}");
        let white = blackbody_rgb(6500.0);
        let spread = white.max_element() / white.min_element();
        assert!(spread < 1.25, "6500 K: {white}");
        let hot = blackbody_rgb(20_000.0);
        assert!(hot.z > hot.x, "{hot}");
        assert_eq!(blackbody_rgb(0.0), Vec3::ZERO);
        assert_eq!(blackbody_rgb(f64::NAN), Vec3::ZERO);
    }
}
