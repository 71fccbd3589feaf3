//! The paper's Table 1: wall time of a whole online run (initial fit + every update, optionally
//! with the eigendecomposition after each) for batch, general and long-term DMD on the four
//! synthetic cases. Times are measured here, never asserted in tests (see `fleet bench`).

use super::run_online;
use fleet_math::dmd::{Debias, DmdConfig, DmdError, Method, RankPolicy};
use fleet_math::process::synthetic::{table1_field, Table1Case, Table1Profile};
use serde::Serialize;
use std::time::Instant;

/// The paper's published seconds (Python on an i7-4770): `[batch, general, long-term]` per case.
pub const PAPER_NO_EIG: [[f64; 3]; 4] = [
    [5.038, 0.557, 0.304],
    [1.376, 0.975, 0.646],
    [3.715, 1.710, 2.969],
    [14.77, 3.343, 1.387],
];
pub const PAPER_EIG: [[f64; 3]; 4] = [
    [13.59, 0.537, 0.413],
    [2.756, 1.950, 1.319],
    [37.52, 3.411, 29.61],
    [28.82, 4.266, 17.03],
];

/// The rows we time: label, config, and which paper column it corresponds to (0 batch,
/// 1 general, 2 long-term).
pub fn methods() -> Vec<(&'static str, DmdConfig, usize)> {
    let c = |method, rank| DmdConfig {
        method,
        rank,
        debias: Debias::None,
        gamma: 1.0,
        forgetting: Default::default(),
    };
    vec![
        ("batch", c(Method::Batch, RankPolicy::Full), 0),
        ("general", c(Method::General, RankPolicy::Full), 1),
        ("general-r10", c(Method::General, RankPolicy::Fixed(10)), 1),
        ("long-term", c(Method::LongTerm, RankPolicy::Full), 2),
    ]
}

#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    pub case: usize,
    pub method: String,
    pub with_eig: bool,
    pub median_s: f64,
    pub min_s: f64,
    pub paper_s: f64,
}

/// One timed run: initial fit plus every update (plus decompositions when `with_eig`).
pub fn run_once(case: &Table1Case, cfg: &DmdConfig, with_eig: bool, z: faer::MatRef<'_, f64>) -> Result<f64, DmdError> {
    let t0 = Instant::now();
    let _ = run_online(cfg, z, case.init, case.tau, |m| {
        if with_eig {
            std::hint::black_box(m.decompose()?);
        }
        Ok(())
    })?;
    Ok(t0.elapsed().as_secs_f64())
}

/// Time every method on every case `repeats` times (after one warm-up run).
pub fn run(repeats: usize, mut progress: impl FnMut(&str)) -> Result<Vec<Timing>, DmdError> {
    let mut out = vec![];
    for (ci, case) in fleet_math::process::synthetic::TABLE1_CASES.iter().enumerate() {
        let field = table1_field(case, Table1Profile::Sech, 0.4, 1 + ci as u64);
        let z = field.snapshots.as_ref();
        for (label, cfg, col) in methods() {
            for with_eig in [false, true] {
                progress(&format!(
                    "case {} {label}{}",
                    ci + 1,
                    if with_eig { " +eig" } else { "" }
                ));
                run_once(case, &cfg, with_eig, z)?;
                let mut ts: Vec<f64> = (0..repeats.max(1))
                    .map(|_| run_once(case, &cfg, with_eig, z))
                    .collect::<Result<_, _>>()?;
                let min_s = ts.iter().copied().fold(f64::INFINITY, f64::min);
                let median_s = super::eig_study::median(&mut ts);
                let paper = if with_eig { PAPER_EIG } else { PAPER_NO_EIG };
                out.push(Timing {
                    case: ci + 1,
                    method: label.into(),
                    with_eig,
                    median_s,
                    min_s,
                    paper_s: paper[ci][col],
                });
            }
        }
    }
    Ok(out)
}
