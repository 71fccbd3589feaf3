//! Scoring without a truth: a deterministic share of the boats' readings is held out (never
//! assimilated) and predicted by the estimate of its step, which has not seen it. The squared
//! errors, less the readings' own noise, estimate the estimate's error where boats go; the
//! share of readings inside the estimate's 95% interval (its variance plus the reading's noise)
//! says whether its reported uncertainty holds.

use crate::protocol::{HeldDecile, HoldoutScore, Sample};

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

/// The held-out readings by decile of reported variance, and their ENCE.
fn deciles(held: &[&HeldOut]) -> (Vec<HeldDecile>, Option<f64>) {
    if held.len() < 10 {
        return (vec![], None);
    }
    let mut sorted = held.to_vec();
    sorted.sort_by(|a, b| a.variance.total_cmp(&b.variance));
    let n = sorted.len();
    let by_decile: Vec<HeldDecile> = (0..10)
        .map(|d| {
            let part = &sorted[d * n / 10..(d + 1) * n / 10];
            let m = part.len() as f64;
            let mean = |f: &dyn Fn(&HeldOut) -> f64| part.iter().map(|h| f(h)).sum::<f64>() / m;
            let d2 = |h: &HeldOut| (h.value - h.predicted).powi(2);
            HeldDecile {
                readings: part.len(),
                variance: mean(&|h| h.variance),
                z2: mean(&|h| d2(h) / (h.variance + h.noise_var).max(1e-300)),
                error: (mean(&d2) - mean(&|h| h.noise_var)).max(0.0),
            }
        })
        .collect();
    let ence = by_decile
        .iter()
        .map(|d| {
            let rmv = d.variance.max(1e-300).sqrt();
            (rmv - d.error.sqrt()).abs() / rmv
        })
        .sum::<f64>()
        / 10.0;
    (by_decile, Some(ence))
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
    let held: Vec<&HeldOut> = held.into_iter().collect();
    let (mut n, mut se, mut noise, mut inside, mut norm) = (0usize, 0.0, 0.0, 0usize, 0.0);
    for h in held.iter().copied() {
        let d2 = (h.value - h.predicted).powi(2);
        let total = (h.variance + h.noise_var).max(1e-300);
        n += 1;
        se += d2;
        noise += h.noise_var;
        norm += d2 / total;
        inside += usize::from(d2 <= 1.959_963_984_540_054f64.powi(2) * total);
    }
    let (by_decile, ence) = deciles(&held);
    (n > 0).then(|| HoldoutScore {
        readings: n,
        mse: se / n as f64,
        noise_var: noise / n as f64,
        coverage_95: inside as f64 / n as f64,
        normalised: norm / n as f64,
        by_decile,
        ence,
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

    /// Monte Carlo by decile: readings whose reported variance varies from cell to cell (over
    /// two orders of magnitude) and whose errors are drawn with it score about 1 in every
    /// decile (2,000 readings a decile: a mean z^2 has a standard error of 0.03, so within 0.15)
    /// and an ENCE near 0; the same errors with the variances reported in reverse order (large
    /// where the error is small) fail at both ends, and the ENCE shows it.
    #[test]
    fn the_deciles_find_a_variance_right_on_average_but_wrong_by_place() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let z = Normal::new(0.0, 1.0).unwrap();
        let noise = 0.001;
        let var = |c: usize| 0.001 * 100f64.powf(c as f64 / 20_000.0);
        let errors: Vec<f64> = (0..20_000)
            .map(|c| (var(c) + noise).sqrt() * z.sample(&mut rng))
            .collect();
        let held = |reported: &dyn Fn(usize) -> f64| -> Vec<HeldOut> {
            (0..20_000)
                .map(|c| HeldOut {
                    cell: c,
                    value: errors[c],
                    noise_var: noise,
                    predicted: 0.0,
                    variance: reported(c),
                })
                .collect()
        };
        let right = score(&held(&var)).unwrap();
        assert_eq!(right.by_decile.len(), 10);
        assert!(right.by_decile.iter().all(|d| (d.z2 - 1.0).abs() < 0.15), "{right:?}");
        assert!(right.ence.unwrap() < 0.1, "{right:?}");
        let reversed = score(&held(&|c| var(19_999 - c))).unwrap();
        assert!(
            reversed.by_decile[0].z2 > 3.0 && reversed.by_decile[9].z2 < 0.3,
            "{reversed:?}"
        );
        assert!(reversed.ence.unwrap() > 0.5, "{reversed:?}");
        assert!(score(&held(&var)[..9]).unwrap().by_decile.is_empty());
    }
}
