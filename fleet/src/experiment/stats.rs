//! What a claim over seeds needs: a mean with its 95% confidence interval (Student's t on the
//! per-seed values), and a verdict read from a paired difference's interval.

use serde::{Deserialize, Serialize};

/// The mean of `n` values and its two-sided 95% confidence interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub mean: f64,
    pub lo: f64,
    pub hi: f64,
    pub n: usize,
}

/// `t_{0.975}` of Student's t with `df` degrees of freedom: the table to 30, then the
/// Cornish-Fisher expansion around the normal quantile (error below 1e-4 there).
pub fn t975(df: usize) -> f64 {
    const TABLE: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
        2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
    ];
    match df {
        0 => f64::INFINITY,
        1..=30 => TABLE[df - 1],
        _ => {
            let (z, d): (f64, f64) = (1.959_963_984_540_054, df as f64);
            z + (z.powi(3) + z) / (4.0 * d) + (5.0 * z.powi(5) + 16.0 * z.powi(3) + 3.0 * z) / (96.0 * d * d)
        }
    }
}

impl Interval {
    /// The mean of `values` and its 95% t-interval (a single value: an infinite interval).
    pub fn of(values: &[f64]) -> Self {
        let n = values.len();
        let mean = values.iter().sum::<f64>() / n.max(1) as f64;
        if n < 2 {
            return Self {
                mean,
                lo: f64::NEG_INFINITY,
                hi: f64::INFINITY,
                n,
            };
        }
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let half = t975(n - 1) * (var / n as f64).sqrt();
        Self {
            mean,
            lo: mean - half,
            hi: mean + half,
            n,
        }
    }

    /// The interval of the paired differences `a_i - b_i` (same seed, same truth and noise).
    pub fn paired(a: &[f64], b: &[f64]) -> Self {
        let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
        Self::of(&d)
    }
}

/// What a paired difference `first - second` of errors says: lower is better.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Outcome {
    /// The interval lies below 0: the first has the lower error.
    Better,
    /// Above 0.
    Worse,
    /// It contains 0.
    NotDistinguishable,
}

impl Outcome {
    pub fn of(d: &Interval) -> Self {
        if d.hi < 0.0 {
            Self::Better
        } else if d.lo > 0.0 {
            Self::Worse
        } else {
            Self::NotDistinguishable
        }
    }

    pub fn words(self) -> &'static str {
        match self {
            Self::Better => "better",
            Self::Worse => "worse",
            Self::NotDistinguishable => "not distinguishable",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_interval_is_the_t_interval() {
        // Three values 1, 2, 3: mean 2, s = 1, half width t_{0.975,2} / sqrt(3) = 4.303 / 1.732.
        let i = Interval::of(&[1.0, 2.0, 3.0]);
        assert_eq!(i.mean, 2.0);
        assert!((i.hi - 2.0 - 4.303 / 3f64.sqrt()).abs() < 1e-12);
        assert!((t975(31) - 2.0395).abs() < 1e-3 && (t975(1000) - 1.9623).abs() < 1e-3);
        assert_eq!(
            Outcome::of(&Interval::paired(&[1.0, 1.1, 0.9], &[2.0, 2.2, 2.1])),
            Outcome::Better
        );
        assert_eq!(
            Outcome::of(&Interval::paired(&[1.0, 2.0, 0.0], &[1.0, 1.0, 1.0])),
            Outcome::NotDistinguishable
        );
        assert!(
            Interval::of(&[5.0]).lo.is_infinite(),
            "one seed says nothing about spread"
        );
    }

    #[test]
    fn the_interval_covers_the_mean_95_percent_of_the_time() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let normal = Normal::new(3.0, 2.0).unwrap();
        let trials = 20_000;
        let covered = (0..trials).filter(|_| {
            let v: Vec<f64> = (0..10).map(|_| normal.sample(&mut rng)).collect();
            let i = Interval::of(&v);
            i.lo <= 3.0 && 3.0 <= i.hi
        });
        // 95% +- 3 binomial standard deviations (0.0015 at 20,000 trials).
        let rate = covered.count() as f64 / trials as f64;
        assert!((rate - 0.95).abs() < 0.005, "coverage {rate}");
    }
}
