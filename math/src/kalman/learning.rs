//! What the filter learns of its own error model from the observations it is given: the
//! observation noise adapted to the innovations, the model error's level where the modes miss
//! (its detail, refitted and rescaled), and how long that error persists from step to step.
//! Each is a method on [`ModalFilter`]; the filter's equations are in the parent's doc.

use super::{detail_step, grown, modal_at_cells, modal_of, variance_of, FilterError, ModalFilter, Observation, Prior};

impl ModalFilter {
    /// Covariance matching: the model error and the process noise re-estimated from one
    /// source's innovations against the forecast `prior` (values of noise variance `noise_var`
    /// at `cells`). Their expected square is the modal variance + the detail's + the noise:
    /// the model error by the ratio of the detail's part, the process noise by `sqrt(NIS)`
    /// with NIS clamped to [1/4, 4]; both smoothed and clamped to the variance of the values
    /// themselves, so neither can run away.
    pub fn adapt_noise(&mut self, prior: &Prior, values: &[f64], noise_var: f64) {
        let cells = &prior.cells;
        if cells.is_empty() {
            return;
        }
        let mean_at = |v: &[f64]| v.iter().sum::<f64>() / cells.len() as f64;
        let field_var = variance_of(values).max(1e-12);
        let d2 = cells
            .iter()
            .zip(values)
            .map(|(&c, v)| (v - prior.mean[c]).powi(2))
            .sum::<f64>()
            / cells.len() as f64;
        let (detail_part, expected) = (
            mean_at(&prior.detail_var).max(1e-12),
            mean_at(&prior.variance) + noise_var,
        );
        let modal_part = expected - noise_var - detail_part;
        let s_hat = (self.model_error * (d2 - modal_part - noise_var) / detail_part).clamp(0.0, field_var);
        self.model_error = (0.7 * self.model_error + 0.3 * s_hat).clamp(1e-12, field_var);
        let nis = (d2 / expected).clamp(0.25, 4.0);
        self.process = (self.process * nis.sqrt()).clamp(1e-12, field_var);
    }

    /// How the forecast's detail variance fared against `obs` (call before [`Self::update`],
    /// with that step's observation): the ratio of what the detail had to cover, the mean over
    /// the observed cells of the innovation's square less the value's noise and the modal
    /// variance there, to the detail variance forecast there. 1 when the forecast's variance is
    /// right; `None` without cells.
    pub fn detail_fit(&self, obs: &Observation<'_>) -> Result<Option<f64>, FilterError> {
        self.detail_fit_with(obs, None)
    }

    /// [`Self::detail_fit`] of `obs` at the cells of `prior` (made by [`Self::prior_at`]),
    /// taking the modal part there from the prior while the modal state it was made at lasts
    /// (the same values: a boat step checks the detail at the disks' cells right after it
    /// measured the innovations there, 100,000 cells at 384 x 768), else made afresh.
    pub fn detail_fit_at_prior(&self, prior: &Prior, obs: &Observation<'_>) -> Result<Option<f64>, FilterError> {
        let current = prior.modal.0 == self.state && prior.cells == obs.cells;
        self.detail_fit_with(obs, current.then_some(&prior.modal.1[..]))
    }

    pub(super) fn detail_fit_with(
        &self,
        obs: &Observation<'_>,
        modal: Option<&[(f64, f64)]>,
    ) -> Result<Option<f64>, FilterError> {
        obs.check_lengths()?;
        if obs.cells.is_empty() {
            return Ok(None);
        }
        let n = self.basis.nrows();
        let (basis, cov) = ((*self.basis).as_ref(), self.cov.as_ref());
        let observed = obs.cells.iter().zip(obs.values).zip(obs.variance);
        if let Some(((c, y), v)) = observed
            .clone()
            .find(|((&c, y), v)| c >= n || !y.is_finite() || !(**v >= 0.0))
        {
            return Err(FilterError::Input(format!("cell {c}: value {y} with variance {v}")));
        }
        let made;
        let modal = match modal {
            Some(m) => m,
            None => {
                made = modal_at_cells(basis, cov, &self.mean, obs.cells);
                &made[..]
            }
        };
        let (mut covered, mut forecast) = (0.0, 0.0);
        for (((&c, &y), &v), &(modal, modal_var)) in observed.zip(modal) {
            covered += (y - modal - self.detail[c]).powi(2) - v - modal_var;
            forecast += self.detail_var[c];
        }
        Ok(Some(covered / forecast.max(1e-300)))
    }

    /// Rescale the detail's variance at `cells` by a [`Self::detail_fit`] ratio: by its square
    /// root, shrinking by at most 2x a step; growing, never past `cap` (the field's own
    /// variance; a variance already above it is not raised, nor lowered to it: a flat field's
    /// cap of 0 must not zero the detail). A damped feedback (adaptive covariance inflation):
    /// the next fit is taken against the rescaled variance, so the factor settles at 1 when
    /// the variance is right; the square root closes half the (logarithmic) distance a step,
    /// so it does not overshoot, and the cap keeps it from running away.
    ///
    /// Growing is not limited to 2x a step (it was, until 2026-12-02): a field that changes at
    /// once (a calm start, then the event; a first fit on frames unlike the rest) left the
    /// filter 10,000x surer of its forecast than the lattice said, and at 2x a step it took 13
    /// steps to believe the aerials, with a map 35x worse than theirs meanwhile; by the square
    /// root alone it takes 4.
    pub fn rescale_detail(&mut self, ratio: f64, cap: f64, cells: impl IntoIterator<Item = usize>) {
        if !ratio.is_finite() {
            return;
        }
        let factor = ratio.max(0.25).sqrt();
        for c in cells {
            if let Some(v) = self.detail_var.get_mut(c) {
                *v = if factor > 1.0 {
                    grown(*v, factor, cap)
                } else {
                    *v * factor
                }
                .max(1e-12);
            }
        }
    }

    /// Raise the model error by a [`Self::detail_fit`] ratio above 1 (by its square root, never
    /// past `cap` nor lowered to it; not limited to 2x a step, as [`Self::rescale_detail`]
    /// says why); a ratio of 1 or less changes nothing.
    ///
    /// The detail's forecast variance relaxes to the model error at the rate `1 - rho^2` a
    /// step ([`Self::predict`]), so at a low persistence (a field whose winters are
    /// independent) [`Self::rescale_detail`]'s correction is undone by the next predict, and
    /// the model error, re-estimated at boat steps only and smoothed, took many boat epochs to
    /// reach the forecast's error: meanwhile the filter weighed a forecast 40x worse than it
    /// believed against the aerials' values on their own lattice, and its map there was worse
    /// than theirs. Only raising: the lattice's cells, corrected every step, are the best
    /// forecast ones; a forecast too good there says nothing of the cells between them
    /// (lowering it too was measured: the default mission's MSE +5.7%).
    pub fn raise_model_error(&mut self, ratio: f64, cap: f64) {
        if !(ratio > 1.0) || !ratio.is_finite() {
            return;
        }
        self.model_error = grown(self.model_error, ratio.sqrt(), cap);
    }

    /// Estimate the detail's persistence from a source that looks at many cells every step
    /// (call before [`Self::update`], with that step's observation). Its residual against the
    /// modal forecast, `z = y - B a`, is the detail plus the forecast's error plus noise; the
    /// lag-one moment `sum z_t z_{t-1}` over cells seen at both steps estimates `rho` times the
    /// residual's variance, and `sum (z_{t-1}^2 - noise variance)` that variance (the noise is
    /// independent from step to step, so it drops out of the first and is taken out of the
    /// second). Both sums are running, decaying by `memory` per step; `rho` is their ratio,
    /// clamped to `[0, 0.999]` (1 would freeze the detail's variance).
    pub fn learn_persistence(&mut self, obs: &Observation<'_>, memory: f64) -> Result<f64, FilterError> {
        let (n, q) = (self.basis.nrows(), self.dim());
        obs.check_lengths()?;
        let (mut cross, mut var) = (0.0, 0.0);
        let mut residual = vec![(f64::NAN, 0.0); n];
        for ((&c, &y), &v) in obs.cells.iter().zip(obs.values).zip(obs.variance) {
            if c >= n || !y.is_finite() || !(v >= 0.0) {
                return Err(FilterError::Input(format!("cell {c}: value {y} with variance {v}")));
            }
            residual[c] = (y - (0..q).map(|k| self.basis[(c, k)] * self.mean[k]).sum::<f64>(), v);
        }
        for c in obs.cells {
            let ((z, _), (z0, v0)) = (residual[*c], self.last_residual[*c]);
            if z0.is_finite() {
                cross += z * z0;
                var += z0 * z0 - v0;
            }
        }
        self.moments = (memory * self.moments.0 + cross, memory * self.moments.1 + var);
        self.last_residual = residual;
        if self.moments.1 > 0.0 {
            self.persistence = (self.moments.0 / self.moments.1).clamp(0.0, 0.999);
        }
        Ok(self.persistence)
    }

    /// Condition the detail on observations, cell by cell, from their residuals against the
    /// posterior modal mean (call after [`Self::update`]): a scalar Kalman update per value.
    pub fn update_detail(&mut self, obs: &[Observation<'_>]) -> Result<(), FilterError> {
        let n = self.basis.nrows();
        let (basis, cov, mean) = ((*self.basis).as_ref(), self.cov.as_ref(), &self.mean);
        let (modal_mean, modal_var) = self.modal.get_or_init(|| modal_of(basis, cov, mean));
        for o in obs {
            o.check_lengths()?;
            for ((&c, &y), &a) in o.cells.iter().zip(o.values).zip(o.variance) {
                if c >= n || !(y.is_finite() && a > 0.0 && a.is_finite()) {
                    return Err(FilterError::Input(format!("cell {c}: value {y} with variance {a}")));
                }
                let dv = (self.detail[c], self.detail_var[c]);
                (self.detail[c], self.detail_var[c]) = detail_step(dv, modal_mean[c], modal_var[c], y, a);
            }
        }
        Ok(())
    }
}
