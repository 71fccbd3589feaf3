//! The paper's evaluations, run offline and deterministically: the online-DMD studies of
//! Sect. 5 (eigenvalue accuracy, Fig. 7; execution time, Table 1).

pub mod claims;
pub mod comparison;
pub mod eig_study;
pub mod epoch_timing;
pub mod faults;
pub mod paper;
pub mod peers;
pub mod phases;
pub mod refit_timing;
pub mod sensing_timing;
pub mod stats;
pub mod table1;
pub mod team;

use faer::MatRef;
use fleet_math::dmd::{Dmd, DmdConfig, DmdError, Modes};

/// Fit `cfg` to the first `init` pairs of the snapshot sequence `z` (columns in time order),
/// then feed the remaining pairs in batches of `tau`, calling `after_each` with the model after
/// the initial fit and after every update.
pub fn run_online(
    cfg: &DmdConfig,
    z: MatRef<'_, f64>,
    init: usize,
    tau: usize,
    mut after_each: impl FnMut(&dyn Dmd) -> Result<(), DmdError>,
) -> Result<Box<dyn Dmd>, DmdError> {
    let pairs = z.ncols().saturating_sub(1);
    if init == 0 || init > pairs || tau == 0 {
        return Err(DmdError::Shape(format!(
            "need 1 <= init <= pairs and tau >= 1 (init {init}, pairs {pairs}, tau {tau})"
        )));
    }
    let mut model = cfg.init(z.subcols(0, init), z.subcols(1, init))?;
    after_each(model.as_ref())?;
    let mut m = init;
    while m < pairs {
        let t = tau.min(pairs - m);
        model.update(z.subcols(m, t), z.subcols(m + 1, t))?;
        after_each(model.as_ref())?;
        m += t;
    }
    Ok(model)
}

/// The dominant continuous-time eigenvalue `ln(lambda_max) / dt` of a decomposition.
pub fn dominant_continuous(modes: &Modes, dt: f64) -> Option<faer::c64> {
    modes.dominant().map(|i| modes.eigenvalues[i].ln() / dt)
}
