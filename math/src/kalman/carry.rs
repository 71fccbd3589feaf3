//! The filter carried forward without observations (its forecast `h` steps on, as a copy or as
//! the mean and variance per cell) and into a refitted model's basis and dynamics.

use super::{symmetrised, FilterError, ModalFilter};
use faer::Mat;
use std::sync::Arc;

impl ModalFilter {
    /// The field `h` steps ahead of the filter's state (0: the posterior) with its variance per
    /// cell: `diag(B P_h B^T) + s`.
    pub fn forecast(&self, h: usize) -> (Vec<f64>, Vec<f64>) {
        self.ahead(h).field()
    }

    /// The filter `h` steps of prediction ahead of this one (no data).
    pub fn ahead(&self, h: usize) -> Self {
        let mut f = self.clone();
        for _ in 0..h {
            f.predict();
        }
        f
    }

    /// The model changed (a refit): carry the state into the new basis and dynamics. The part
    /// of the old state the new basis cannot hold is not lost: its mean goes into the detail
    /// and its variance (the trace of what projects out, spread over the cells) into the
    /// detail's variance, so the field and its total variance are unchanged.
    pub fn reproject(&mut self, basis: impl Into<Arc<Mat<f64>>>, dynamics: Mat<f64>) -> Result<(), FilterError> {
        let basis = basis.into();
        let (n, q) = (basis.nrows(), basis.ncols());
        if n != self.basis.nrows() || dynamics.nrows() != q || dynamics.ncols() != q {
            return Err(FilterError::Input(format!(
                "a new basis of {n} x {q} with {} x {} dynamics",
                dynamics.nrows(),
                dynamics.ncols()
            )));
        }
        let t = basis.transpose() * (*self.basis).as_ref(); // q x q_old
        let m = Mat::from_fn(self.dim(), 1, |i, _| self.mean[i]);
        let mean: Vec<f64> = (t.as_ref() * m.as_ref()).col(0).iter().copied().collect();
        let cov = symmetrised(t.as_ref() * self.cov.as_ref() * t.transpose());
        let trace = |p: &Mat<f64>| (0..p.nrows()).map(|i| p[(i, i)]).sum::<f64>();
        let lost = (trace(&self.cov) - trace(&cov)).max(0.0) / n as f64;
        let old_field = (*self.basis).as_ref() * m.as_ref();
        let new_field = basis.as_ref() * Mat::from_fn(q, 1, |i, _| mean[i]).as_ref();
        for c in 0..n {
            self.detail[c] += old_field[(c, 0)] - new_field[(c, 0)];
            self.detail_var[c] += lost;
        }
        (self.basis, self.dynamics, self.mean, self.cov) = (basis, dynamics, mean, cov);
        self.changed();
        Ok(())
    }
}
