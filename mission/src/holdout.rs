//! Scoring without a truth: a deterministic share of the boats' readings is held out (never
//! assimilated) and predicted by the estimate of its step, which has not seen it. The squared
//! errors, less the readings' own noise, estimate the estimate's error where boats go; the
//! share of readings inside the estimate's 95% interval (its variance plus the reading's noise)
//! says whether its reported uncertainty holds.

use crate::protocol::Sample;
use serde::{Deserialize, Serialize};

/// The hold-out share a mission without a truth uses unless it says otherwise.
pub const DEFAULT_SHARE: f64 = 0.1;

/// One held-out reading and what the estimate said there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldOut {
    pub cell: usize,
    pub value: f64,
    /// The reading's own noise variance.
    pub noise_var: f64,
    pub predicted: f64,
    /// The estimate's variance at the cell.
    pub variance: f64,
}

/// The hold-out's figures over a run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HoldoutScore {
    pub readings: usize,
    /// Mean squared difference between the held-out readings and the estimate.
    pub mse: f64,
    /// The readings' mean noise variance: `mse - noise_var` estimates the estimate's own MSE
    /// at the held-out cells.
    pub noise_var: f64,
    /// Share of held-out readings inside the estimate's 95% interval.
    pub coverage_95: f64,
    /// Mean normalised squared error (1 when the reported variance is right).
    pub normalised: f64,
}

/// Whether the reading at `step` and `cell` is held out (a fixed hash: the same readings in
/// every run and restart).
pub fn is_held(step: u64, cell: u32, share: f64) -> bool {
    let mut x = step.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ u64::from(cell).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    x ^= x >> 31;
    x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x ^= x >> 29;
    ((x >> 11) as f64 / (1u64 << 53) as f64) < share
}

/// Split a step's boat samples into what is assimilated and what is held out: `(cell, value,
/// noise variance)`, the noise a sample's own or `sigma`'s.
pub fn split(samples: Vec<Sample>, share: f64, sigma: f64) -> (Vec<Sample>, Vec<(usize, f64, f64)>) {
    if share <= 0.0 {
        return (samples, vec![]);
    }
    let mut held = vec![];
    let kept = samples
        .into_iter()
        .filter_map(|mut s| {
            let mut keep = vec![];
            for i in 0..s.cells.len() {
                let sd = s.sigma.as_ref().map_or(sigma, |v| v[i]);
                if is_held(s.step, s.cells[i], share) {
                    held.push((s.cells[i] as usize, s.values[i], sd * sd));
                } else {
                    keep.push(i);
                }
            }
            s.values = keep.iter().map(|&i| s.values[i]).collect();
            s.sigma = s.sigma.map(|v| keep.iter().map(|&i| v[i]).collect());
            s.cells = keep.iter().map(|&i| s.cells[i]).collect();
            (!s.cells.is_empty()).then_some(s)
        })
        .collect();
    (kept, held)
}

/// The figures of every held-out reading.
pub fn score<'a>(held: impl IntoIterator<Item = &'a HeldOut>) -> Option<HoldoutScore> {
    let (mut n, mut se, mut noise, mut inside, mut norm) = (0usize, 0.0, 0.0, 0usize, 0.0);
    for h in held {
        let d2 = (h.value - h.predicted).powi(2);
        let total = (h.variance + h.noise_var).max(1e-300);
        n += 1;
        se += d2;
        noise += h.noise_var;
        norm += d2 / total;
        inside += usize::from(d2 <= 1.959_963_984_540_054f64.powi(2) * total);
    }
    (n > 0).then(|| HoldoutScore {
        readings: n,
        mse: se / n as f64,
        noise_var: noise / n as f64,
        coverage_95: inside as f64 / n as f64,
        normalised: norm / n as f64,
    })
}

/// One step's normalised innovation squared (mean over the boats' values fused then; 1 when
/// the reported variance is right).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepInnovation {
    pub epoch: u64,
    pub step: u64,
    pub nis: f64,
    pub values: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_share_held_is_the_share_asked_for_and_always_the_same() {
        let held = (0..200u64)
            .flat_map(|k| (0..500u32).map(move |c| (k, c)))
            .filter(|&(k, c)| is_held(k, c, 0.1));
        let n = held.count() as f64 / 100_000.0;
        // Binomial: 0.1 +- 4 standard errors (sqrt(0.09 / 1e5) ~ 0.00095).
        assert!((n - 0.1).abs() < 0.004, "{n}");
        assert_eq!(is_held(7, 9, 0.1), is_held(7, 9, 0.1));
        assert!(!is_held(7, 9, 0.0));
    }

    #[test]
    fn split_keeps_every_value_once_with_its_noise() {
        let s = Sample {
            step: 3,
            position: [0.0, 0.0],
            cells: (0..100).collect(),
            values: (0..100).map(f64::from).collect(),
            sigma: Some(vec![0.5; 100]),
        };
        let (kept, held) = split(vec![s], 0.2, 9.0);
        let k = &kept[0];
        assert_eq!(k.cells.len() + held.len(), 100);
        assert_eq!(k.sigma.as_ref().unwrap().len(), k.cells.len());
        assert!(k.cells.iter().zip(&k.values).all(|(&c, &v)| v == c as f64));
        assert!(held
            .iter()
            .all(|&(c, v, n)| v == c as f64 && n == 0.25 && is_held(3, c as u32, 0.2)));
    }

    /// Monte Carlo of a calibrated estimate: errors drawn with the reported variance give
    /// coverage near 95% and a normalised error near 1; `mse - noise_var` recovers the error.
    #[test]
    fn a_calibrated_estimate_scores_as_calibrated() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let (var, noise): (f64, f64) = (0.04, 0.01);
        let err = Normal::new(0.0, (var + noise).sqrt()).unwrap();
        let held: Vec<HeldOut> = (0..20_000)
            .map(|c| HeldOut {
                cell: c,
                value: err.sample(&mut rng),
                noise_var: noise,
                predicted: 0.0,
                variance: var,
            })
            .collect();
        let s = score(&held).unwrap();
        // Standard errors: coverage sqrt(.95 .05 / 2e4) ~ 0.0015; normalised sqrt(2 / 2e4) = 0.01.
        assert!((s.coverage_95 - 0.95).abs() < 0.006, "{s:?}");
        assert!((s.normalised - 1.0).abs() < 0.04, "{s:?}");
        assert!((s.mse - s.noise_var - var).abs() < 0.004, "{s:?}");
        assert!(score(&[]).is_none());
    }
}
