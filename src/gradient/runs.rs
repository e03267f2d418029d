//! Seeded repeats: an estimator run once per seed, and a value's mean and standard error over
//! the runs. The checks (gradcheck, the reference, the stability suite, the image reference) all
//! judge an estimate by its standard error, so they all go through these two.

/// `run(index, seed)` for `count` runs, index 0, 1, … with seed `first`, `first + 1`, … (wrapping),
/// in that order. Seeds are consecutive so that a run can be reproduced from the first seed alone.
pub fn seeded_runs<T>(first: u64, count: u32, mut run: impl FnMut(u32, u64) -> T) -> Vec<T> {
    (0..count)
        .map(|index| run(index, first.wrapping_add(index as u64)))
        .collect()
}

/// The mean of independent values and the standard error of that mean.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanAndError {
    pub mean: f64,
    pub se: f64,
}

impl MeanAndError {
    /// NaN for no values; a standard error of 0 for one value (there is no spread to see).
    pub fn of(values: &[f64]) -> MeanAndError {
        let n = values.len() as f64;
        if n == 0.0 {
            return MeanAndError {
                mean: f64::NAN,
                se: f64::NAN,
            };
        }
        let mean = values.iter().sum::<f64>() / n;
        // Two passes rather than a running sum of squares: no cancellation when the spread is
        // small against the mean (a converged ⟨g, 1⟩).
        let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
        MeanAndError {
            mean,
            se: (variance / n).sqrt(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_get_consecutive_seeds_in_order() {
        let runs = seeded_runs(u64::MAX, 3, |index, seed| (index, seed));
        assert_eq!(runs, [(0, u64::MAX), (1, 0), (2, 1)]);
    }

    #[test]
    fn mean_and_error_of_a_few_values() {
        let m = MeanAndError::of(&[1.0, 2.0, 3.0, 6.0]);
        assert_eq!(m.mean, 3.0);
        // Sample variance 14/3, over n = 4.
        assert!((m.se - (14.0f64 / 12.0).sqrt()).abs() < 1e-15);
        assert_eq!(
            MeanAndError::of(&[5.0]),
            MeanAndError { mean: 5.0, se: 0.0 }
        );
        assert!(MeanAndError::of(&[]).mean.is_nan());
    }
}
