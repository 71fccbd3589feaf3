//! The paper's Fig. 7 study: how well each method recovers the dominant continuous-time
//! eigenvalue (true value -1) of a noisy 20 x 20 field, 1000 steps, online methods started on
//! 400 pairs and updated every 10, over seeded trials at noise variances 0.01, 0.04, 0.1.

use super::{dominant_continuous, run_online};
use fleet_math::dmd::{Debias, DmdConfig, DmdError, Method, RankPolicy};
use fleet_math::process::synthetic::EigStudy;
use serde::Serialize;

/// One way of estimating the eigenvalue.
#[derive(Debug, Clone, Serialize)]
pub struct Variant {
    pub label: String,
    pub config: DmdConfig,
}

impl Variant {
    pub fn new(label: &str, method: Method, rank: RankPolicy, debias: Debias, gamma: f64) -> Self {
        Self {
            label: label.into(),
            config: DmdConfig {
                method,
                rank,
                debias,
                gamma,
                forgetting: Default::default(),
            },
        }
    }
}

/// The variants of Fig. 7 (batch and long-term at full rank, as in the paper) plus the
/// debiased ones. Debiasing needs truncation to the signal's rank: at full rank the backward
/// operator of fb is singular along pure-noise directions and TLS has no noise subspace to
/// remove, and both then give garbage. So the debiased variants use the optimal hard threshold
/// (and are shown beside exact DMD at that same rank, which is *more* biased than at full rank).
pub fn default_variants() -> Vec<Variant> {
    use Debias::*;
    use Method::*;
    vec![
        Variant::new("batch", Batch, RankPolicy::Full, None, 1.0),
        Variant::new("long-term", LongTerm, RankPolicy::Full, None, 1.0),
        Variant::new("long-term-g0.999", LongTerm, RankPolicy::Full, None, 0.999),
        Variant::new("batch-optimal", Batch, RankPolicy::Optimal, None, 1.0),
        Variant::new("batch-optimal-fb", Batch, RankPolicy::Optimal, Fb, 1.0),
        Variant::new("batch-optimal-tls", Batch, RankPolicy::Optimal, Tls, 1.0),
        Variant::new("general-optimal", General, RankPolicy::Optimal, None, 1.0),
        Variant::new("general-optimal-fb", General, RankPolicy::Optimal, Fb, 1.0),
        Variant::new("general-optimal-tls", General, RankPolicy::Optimal, Tls, 1.0),
    ]
}

#[derive(Debug, Clone, Serialize)]
pub struct VariantResult {
    pub label: String,
    /// Dominant continuous-time eigenvalue per trial, `[re, im]`.
    pub estimates: Vec<[f64; 2]>,
    /// Median of `|estimate - (-1)|` over trials.
    pub median_abs_error: f64,
    pub median_real: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct NoiseLevel {
    pub noise_var: f64,
    pub variants: Vec<VariantResult>,
}

/// Seed of trial `trial` at noise level index `level` (fixed so results are reproducible).
pub fn trial_seed(base: u64, level: usize, trial: usize) -> u64 {
    base + 1000 * level as u64 + trial as u64
}

/// The dominant eigenvalue a variant estimates from one noisy realisation: batch methods fit
/// all pairs at once, online methods start on `INIT` pairs and take `TAU` per update.
pub fn estimate(v: &Variant, noise_var: f64, seed: u64) -> Result<[f64; 2], DmdError> {
    let field = EigStudy::field(noise_var, seed);
    let z = field.snapshots.as_ref();
    let model = match v.config.method {
        Method::Batch => {
            let (x, y) = fleet_math::dmd::pairs_of(z);
            v.config.init(x, y)?
        }
        _ => run_online(&v.config, z, EigStudy::INIT, EigStudy::TAU, |_| Ok(()))?,
    };
    let modes = model.decompose()?;
    let l = dominant_continuous(&modes, field.dt).ok_or(DmdError::ZeroRank)?;
    Ok([l.re, l.im])
}

pub fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Run every variant over `trials` trials at each noise variance. `progress` is called once
/// per finished estimate.
pub fn run(
    variants: &[Variant],
    noise_vars: &[f64],
    trials: usize,
    base_seed: u64,
    mut progress: impl FnMut(),
) -> Result<Vec<NoiseLevel>, DmdError> {
    let mut out = vec![];
    for (li, &var) in noise_vars.iter().enumerate() {
        let mut results = vec![];
        for v in variants {
            let mut estimates = vec![];
            for t in 0..trials {
                estimates.push(estimate(v, var, trial_seed(base_seed, li, t))?);
                progress();
            }
            let mut err: Vec<f64> = estimates
                .iter()
                .map(|e| ((e[0] - EigStudy::TRUE_EIGENVALUE).powi(2) + e[1].powi(2)).sqrt())
                .collect();
            let mut re: Vec<f64> = estimates.iter().map(|e| e[0]).collect();
            results.push(VariantResult {
                label: v.label.clone(),
                median_abs_error: median(&mut err),
                median_real: median(&mut re),
                estimates,
            });
        }
        out.push(NoiseLevel {
            noise_var: var,
            variants: results,
        });
    }
    Ok(out)
}
