//! A Kalman filter in a DMD model's modal coordinates: the fused map as a posterior.
//!
//! The field is `x_t = B a_t + e_t`: `B` (N x q) an orthonormal real basis of the model's
//! modes, `a_t` the modal state with linear dynamics `a_{t+1} = A a_t + w_t`, `w ~ N(0, q I)`
//! (process noise), and `e_t ~ N(0, s I)` what the modes cannot represent (model error),
//! independent from cell to cell and step to step. Every source observes cells of `x_t` with
//! its own noise variance per cell: `y = x[cells] + v`. Marginalising `e`, an observation is
//! `y = B[cells] a + (e + v)` with variance `var_i + s`, a linear-Gaussian model in `a`, so the
//! posterior is the Kalman filter's.
//!
//! The part the modes cannot hold is not forgotten from one step to the next: the filter
//! keeps its posterior per cell (`detail`, with variance `detail_var`), which persists as an
//! AR(1) process, `e_{t+1} = rho e_t + u`, stationary variance `s` (`persistence` = rho; 0 is
//! white model error). Cells are independent and `e` is taken independent of `a`, so the
//! modal update sees `y - detail` with variance `var + detail_var` and the detail is then
//! updated per cell from the residuals of the posterior modal mean: an approximation (the
//! cross-covariance of `a` and `e` is dropped), exact when `rho = 0`.
//!
//! The update is in information form, `P+ = P (I + J P)^-1` with `J = H^T R^-1 H` (q x q): an
//! aerial frame observes every cell (N in the thousands) and the filter still solves only
//! q x q systems, with no inverse of `P` (which may be singular).

use faer::linalg::matmul::matmul;
use faer::{c64, Accum, Mat, MatRef, Par};
use std::sync::{Arc, OnceLock};

mod carry;
mod displacement;
mod learning;
mod lookahead;
pub use displacement::displacement_variance;
pub use lookahead::{Lookahead, Scheduled};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FilterError {
    #[error("filter input: {0}")]
    Input(String),
    #[error("filter numerics: {0}")]
    Numerical(String),
}

/// Cells one source saw at one step, with the noise variance of each value.
#[derive(Debug, Clone, Copy)]
pub struct Observation<'a> {
    pub cells: &'a [usize],
    pub values: &'a [f64],
    pub variance: &'a [f64],
}

impl Observation<'_> {
    /// As many values and variances as cells.
    pub fn check_lengths(&self) -> Result<(), FilterError> {
        if self.cells.len() == self.values.len() && self.cells.len() == self.variance.len() {
            return Ok(());
        }
        Err(FilterError::Input(format!(
            "{} cells, {} values, {} variances",
            self.cells.len(),
            self.values.len(),
            self.variance.len()
        )))
    }
}

/// A column of an owned matrix as a slice (faer's `Mat` stores columns contiguously).
fn column(m: MatRef<'_, f64>, k: usize) -> &[f64] {
    m.col(k)
        .try_as_col_major()
        .expect("a Mat's columns are contiguous")
        .as_slice()
}

/// Per row `i`, `sum_k a[(i, k)] * b[(i, k)]`, each row's terms added in column order as a
/// per-row dot product adds them (so the same to the bit), but computed a column at a time,
/// reading the N x q matrices contiguously: a row of a column-major N x q matrix is q cache
/// lines apart.
fn row_dots(a: MatRef<'_, f64>, b: MatRef<'_, f64>, out: &mut [f64]) {
    out.fill(-0.0);
    for k in 0..a.ncols() {
        out.iter_mut()
            .zip(column(a, k))
            .zip(column(b, k))
            .for_each(|((o, x), y)| *o += x * y);
    }
}

/// The modal part's mean and variance per cell, `B a` and `diag(B P B^T)`, made a block of
/// cells at a time on every core, each block in pieces of [`SUB_ROWS`] rows through one
/// buffer (each row as the whole product makes it): a block's `B P` made whole was a fresh
/// matrix per block, out of cache by the time its row sums read it.
fn modal_of(basis: MatRef<'_, f64>, cov: MatRef<'_, f64>, mean: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let modal_mean = modal_mean_of(basis, mean);
    let weight = cov.ncols().pow(2);
    let rows = crate::par::block_rows(basis.nrows(), weight);
    let mut variance = vec![0.0; basis.nrows()];
    crate::par::chunks_mut(&mut variance, rows, weight, |k, out| {
        let mut bp = Mat::<f64>::zeros(SUB_ROWS.min(out.len()), cov.ncols());
        for (s, out) in out.chunks_mut(SUB_ROWS).enumerate() {
            let b = basis.subrows(k * rows + s * SUB_ROWS, out.len());
            matmul(
                bp.as_mut().subrows_mut(0, out.len()),
                Accum::Replace,
                b,
                cov,
                1.0,
                Par::Seq,
            );
            row_dots(bp.as_ref().subrows(0, out.len()), b, out);
            out.iter_mut().for_each(|x| *x = x.max(0.0));
        }
    });
    (modal_mean, variance)
}

/// Rows of the basis per piece of [`modal_of`]'s products: `B P` of that many rows stays in
/// the first cache levels until its row sums read it (20 KB at rank 10).
const SUB_ROWS: usize = 256;

/// One value `y` (noise variance `a`) at a cell into the cell's detail `(d, v)`, where the
/// modal part is `modal` with variance `modal_var`. The value corrects the field at the cell,
/// whose forecast is uncertain by the modal posterior's variance as well as the detail's: a
/// gain on the detail's alone trusted a poorly fitted model's modes between the data.
fn detail_step((d, v): (f64, f64), modal: f64, modal_var: f64, y: f64, a: f64) -> (f64, f64) {
    let prior = modal_var + v;
    let gain = prior / (prior + a);
    (
        d + gain * (y - modal - d),
        (prior * a / (prior + a) - modal_var).max(v * a / (v + a)),
    )
}

/// A variance `v` grown by `factor` (> 1), never past `cap`, and not lowered to it when it is
/// already above (a flat field's cap of 0 must not zero it).
fn grown(v: f64, factor: f64, cap: f64) -> f64 {
    (v * factor).min(cap.max(v))
}

/// The modal part's mean per cell, `B a` (N q).
fn modal_mean_of(basis: MatRef<'_, f64>, mean: &[f64]) -> Vec<f64> {
    let m = Mat::from_fn(mean.len(), 1, |i, _| mean[i]);
    crate::par::product(basis, m.as_ref()).col(0).iter().copied().collect()
}

/// The modal part's mean and variance at each of `cells`, `b a` and `b P b^T` for the cell's
/// row `b` of the basis (q^2 products a cell): for the cells a test or a source looks at,
/// where [`modal_of`]'s whole field (N q^2) would be wasted. A block of cells at a time on
/// every core ([`modal_block`]).
fn modal_at_cells(basis: MatRef<'_, f64>, cov: MatRef<'_, f64>, mean: &[f64], cells: &[usize]) -> Vec<(f64, f64)> {
    const BLOCK: usize = 512;
    let q = basis.ncols();
    let blocks = crate::par::map(cells.len().div_ceil(BLOCK), BLOCK * q * q, |k| {
        let block = &cells[k * BLOCK..((k + 1) * BLOCK).min(cells.len())];
        modal_block(basis, cov, mean, block)
    });
    blocks.concat()
}

/// [`modal_at_cells`] of a block of cells: their rows of the basis gathered a column at a
/// time (a row of the column-major N x q basis is q cache lines apart; a disk's cells are
/// near one another in each column), then every sum made across the cells at once, four
/// lanes at a time, each cell's terms added in the order one cell alone adds them
/// (`sum_k a_k b_k`, and `sum_k b_k (sum_j P_jk b_j)`): the values do not depend on which
/// cells are asked with it.
fn modal_block(basis: MatRef<'_, f64>, cov: MatRef<'_, f64>, mean: &[f64], cells: &[usize]) -> Vec<(f64, f64)> {
    let (m, q) = (cells.len(), basis.ncols());
    // Column by column into one buffer: a flat_map's per-value branch cost more than the sums
    // (1.7 ms against 1.0 ms for 25,000 cells at rank 10).
    let mut rows = Vec::with_capacity(m * q);
    for k in 0..q {
        let col = column(basis, k);
        rows.extend(cells.iter().map(|&c| col[c]));
    }
    let b = |k: usize| &rows[k * m..(k + 1) * m];
    let (mut modal, mut var, mut inner) = (vec![0.0; m], vec![0.0; m], vec![0.0; m]);
    for (k, &a) in mean.iter().enumerate().take(q) {
        modal.iter_mut().zip(b(k)).for_each(|(s, &x)| *s += x * a);
        inner.fill(0.0);
        for (j, &p) in column(cov, k).iter().enumerate() {
            inner.iter_mut().zip(b(j)).for_each(|(t, &x)| *t += p * x);
        }
        var.iter_mut()
            .zip(b(k))
            .zip(&inner)
            .for_each(|((s, &x), &t)| *s += x * t);
    }
    modal.into_iter().zip(var).map(|(a, v)| (a, v.max(0.0))).collect()
}

/// A modal posterior, mean and covariance, and the innovations that made it.
type Conditioned = (Vec<f64>, Mat<f64>, Vec<f64>);

/// The filter's state: modal mean and covariance, and the two noise levels.
#[derive(Debug, Clone)]
pub struct ModalFilter {
    /// Shared, not copied, by the filter's clones (a look ahead, a test without the boats).
    basis: Arc<Mat<f64>>,
    dynamics: Mat<f64>,
    mean: Vec<f64>,
    cov: Mat<f64>,
    /// Process noise variance per modal coordinate and step.
    process: f64,
    /// Model-error variance per cell (what `B` cannot represent): the stationary variance of
    /// the detail.
    model_error: f64,
    /// How much of the detail carries over one step (0: none, white model error; < 1).
    persistence: f64,
    /// The detail's posterior mean and variance per cell.
    detail: Vec<f64>,
    detail_var: Vec<f64>,
    /// The dense source's residuals against the modal forecast at its last step (NaN where it
    /// did not look), and the running lag-one moments of those residuals (for
    /// [`Self::learn_persistence`]).
    last_residual: Vec<(f64, f64)>,
    moments: (f64, f64),
    /// The modal part's mean and variance per cell, `B a` and `diag(B P B^T)`, computed once
    /// per modal state (an N x q x q product): a step reads them five times between changes of
    /// `a` and `P`. Emptied wherever the basis, the mean or the covariance change.
    modal: OnceLock<(Vec<f64>, Vec<f64>)>,
    /// Which modal state this is: a number never used before, drawn wherever `modal` is
    /// emptied, so a [`Prior`] made at this state can tell it is still current.
    state: u64,
}

/// A number no modal state has had ([`ModalFilter::state`]).
fn fresh_state() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

fn check_finite(what: &str, v: impl IntoIterator<Item = f64>) -> Result<(), FilterError> {
    if v.into_iter().all(f64::is_finite) {
        Ok(())
    } else {
        Err(FilterError::Input(format!("{what} is not finite")))
    }
}

impl ModalFilter {
    /// A filter over `basis` (N x q, orthonormal columns) with `dynamics` (q x q), starting at
    /// `mean` with covariance `cov`.
    pub fn new(
        basis: impl Into<Arc<Mat<f64>>>,
        dynamics: Mat<f64>,
        mean: Vec<f64>,
        cov: Mat<f64>,
        process: f64,
        model_error: f64,
    ) -> Result<Self, FilterError> {
        let basis = basis.into();
        let q = basis.ncols();
        if dynamics.nrows() != q || dynamics.ncols() != q || mean.len() != q || cov.nrows() != q || cov.ncols() != q {
            return Err(FilterError::Input(format!(
                "a basis of {q} columns needs {q} x {q} dynamics and covariance and a mean of {q}"
            )));
        }
        if !(process >= 0.0 && model_error >= 0.0) {
            return Err(FilterError::Input("noise variances must be >= 0".into()));
        }
        check_finite(
            "the basis",
            basis.col_iter().flat_map(|c| c.iter().copied().collect::<Vec<_>>()),
        )?;
        check_finite("the mean", mean.iter().copied())?;
        let n = basis.nrows();
        Ok(Self {
            basis,
            dynamics,
            mean,
            cov,
            process,
            model_error,
            persistence: 0.0,
            detail: vec![0.0; n],
            detail_var: vec![model_error; n],
            last_residual: vec![(f64::NAN, 0.0); n],
            moments: (0.0, 0.0),
            modal: OnceLock::new(),
            state: fresh_state(),
        })
    }

    /// The modal state's mean and covariance.
    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    pub fn cov(&self) -> MatRef<'_, f64> {
        self.cov.as_ref()
    }

    /// The process noise variance per modal coordinate and step.
    pub fn process(&self) -> f64 {
        self.process
    }

    /// The detail's stationary variance (the model error per cell).
    pub fn model_error(&self) -> f64 {
        self.model_error
    }

    /// How much of the detail carries over one step.
    pub fn persistence(&self) -> f64 {
        self.persistence
    }

    /// The detail's persistence set, not learned (a benchmark's or a test's filter).
    pub fn with_persistence(mut self, rho: f64) -> Self {
        self.persistence = rho.clamp(0.0, 0.999);
        self
    }

    /// The detail's mean and variance per cell.
    pub fn detail(&self) -> &[f64] {
        &self.detail
    }

    pub fn detail_var(&self) -> &[f64] {
        &self.detail_var
    }

    /// The forecast before an update, which innovations are measured against: its mean
    /// everywhere (N q), its variances at `cells` only (q^2 a cell, not the field's N q^2).
    pub fn prior_at(&self, cells: &[usize]) -> Prior {
        let modal = match self.modal.get() {
            Some((m, _)) => m.clone(),
            None => modal_mean_of((*self.basis).as_ref(), &self.mean),
        };
        let (basis, cov) = ((*self.basis).as_ref(), self.cov.as_ref());
        let at = modal_at_cells(basis, cov, &self.mean, cells);
        let variance = at
            .iter()
            .zip(cells)
            .map(|((_, v), &c)| v + self.detail_var[c])
            .collect();
        Prior {
            mean: modal.iter().zip(&self.detail).map(|(m, d)| m + d).collect(),
            cells: cells.to_vec(),
            variance,
            detail_var: cells.iter().map(|&c| self.detail_var[c]).collect(),
            modal: (self.state, at),
        }
    }

    pub fn dim(&self) -> usize {
        self.basis.ncols()
    }

    pub fn basis(&self) -> MatRef<'_, f64> {
        (*self.basis).as_ref()
    }

    pub fn dynamics(&self) -> MatRef<'_, f64> {
        self.dynamics.as_ref()
    }

    /// One step of the dynamics: `a = A a`, `P = A P A^T + q I`; the detail decays towards
    /// 0 and its variance towards `s`.
    pub fn predict(&mut self) {
        let rho = self.persistence;
        self.detail.iter_mut().for_each(|d| *d *= rho);
        self.detail_var = self.detail_var.iter().map(|&v| self.predicted_detail(v)).collect();
        let m = Mat::from_fn(self.dim(), 1, |i, _| self.mean[i]);
        self.mean = (self.dynamics.as_ref() * m).col(0).iter().copied().collect();
        self.cov = self.predicted_cov(self.cov.as_ref());
        self.changed();
    }

    /// The basis, the modal mean or the covariance changed: what was made of them is stale.
    fn changed(&mut self) {
        self.modal.take();
        self.state = fresh_state();
    }

    /// Condition on every observation of one step. Returns the innovations (observed minus
    /// predicted value, before the update) in the order given.
    pub fn update(&mut self, obs: &[Observation<'_>]) -> Result<Vec<f64>, FilterError> {
        let (mean, cov, innovations) = self.conditioned(obs)?;
        (self.mean, self.cov) = (mean, cov);
        self.changed();
        Ok(innovations)
    }

    /// [`Self::update`]'s posterior modal mean and covariance, and the innovations, with the
    /// filter left as it was.
    fn conditioned(&self, obs: &[Observation<'_>]) -> Result<Conditioned, FilterError> {
        let (n, q) = (self.basis.nrows(), self.dim());
        // H^T R^-1 H by rows of q (a slice the compiler runs 4 lanes at a time, divisions
        // too: each entry's terms the same, in the same order, as one at a time), the upper
        // triangle only (`h_a h_b` is `h_b h_a` to the bit, so the lower is the same sums).
        let mut jf = vec![0.0; q * q];
        let mut g = vec![0.0; q]; // H^T R^-1 (y - H a)
        let mut h = vec![0.0; q]; // the cell's row of the basis
        let mut innovations = vec![];
        for o in obs {
            o.check_lengths()?;
            for ((&c, &y), &v) in o.cells.iter().zip(o.values).zip(o.variance) {
                if c >= n {
                    return Err(FilterError::Input(format!("cell {c} outside the grid of {n}")));
                }
                let r = v + self.detail_var[c];
                if !(y.is_finite() && r > 0.0 && r.is_finite()) {
                    return Err(FilterError::Input(format!("cell {c}: value {y} with variance {r}")));
                }
                h.iter_mut().enumerate().for_each(|(k, x)| *x = self.basis[(c, k)]);
                let predicted: f64 = (0..q).map(|k| h[k] * self.mean[k]).sum();
                let d = y - self.detail[c] - predicted;
                innovations.push(d);
                for (a, row) in jf.chunks_exact_mut(q.max(1)).enumerate() {
                    let ha = h[a];
                    g[a] += ha * d / r;
                    row[a..].iter_mut().zip(&h[a..]).for_each(|(x, &hb)| *x += ha * hb / r);
                }
            }
        }
        let j = Mat::from_fn(q, q, |a, b| jf[a.min(b) * q + a.max(b)]);
        // P+ = P (I + J P)^-1, i.e. (I + J P)^T P+^T = P^T, solved as (I + P J) P+ = P.
        let mut m = self.cov.as_ref() * j.as_ref();
        for i in 0..q {
            m[(i, i)] += 1.0;
        }
        let lu = m.partial_piv_lu();
        let post = symmetrised(faer::linalg::solvers::Solve::solve(&lu, self.cov.as_ref()));
        let gm = Mat::from_fn(q, 1, |i, _| g[i]);
        let step = post.as_ref() * gm.as_ref();
        let mut mean = self.mean.clone();
        for i in 0..q {
            mean[i] += step[(i, 0)];
        }
        check_finite(
            "the posterior",
            mean.iter()
                .copied()
                .chain(post.col_iter().flat_map(|c| c.iter().copied().collect::<Vec<_>>())),
        )
        .map_err(|_| FilterError::Numerical("the update lost finiteness (an ill-conditioned I + P J)".into()))?;
        Ok((mean, post, innovations))
    }

    /// The field and its variance at `cells` as they would be after [`Self::update`] with
    /// `modes` and [`Self::update_detail`] with `detail`, the filter left as it was: a test of
    /// the filter without some source looks at a few cells, and the whole field's variance
    /// (N q^2) would be wasted on it. The same arithmetic per cell as the two updates, but
    /// for the modal variance, summed by hand rather than by a matrix product (the last bits
    /// may differ).
    pub fn field_at_after(
        &self,
        modes: &[Observation<'_>],
        detail: &[Observation<'_>],
        cells: &[usize],
    ) -> Result<(Vec<f64>, Vec<f64>), FilterError> {
        let n = self.basis.nrows();
        if let Some(&c) = cells.iter().find(|&&c| c >= n) {
            return Err(FilterError::Input(format!("cell {c} outside the grid of {n}")));
        }
        let (mean, cov, _) = self.conditioned(modes)?;
        let basis = (*self.basis).as_ref();
        // Per wanted cell: its modal mean and variance, and its detail as the values update it
        // (`slot`: where a cell's are in `at`).
        let mut at: Vec<(f64, f64, f64, f64)> = modal_at_cells(basis, cov.as_ref(), &mean, cells)
            .into_iter()
            .zip(cells)
            .map(|((m, v), &c)| (m, v, self.detail[c], self.detail_var[c]))
            .collect();
        let mut slot = vec![u32::MAX; n];
        cells.iter().enumerate().for_each(|(i, &c)| slot[c] = i as u32);
        for o in detail {
            o.check_lengths()?;
            for ((&c, &y), &a) in o.cells.iter().zip(o.values).zip(o.variance) {
                let Some((modal, modal_var, d, v)) = slot.get(c).and_then(|&i| at.get_mut(i as usize)) else {
                    continue;
                };
                if !(y.is_finite() && a > 0.0 && a.is_finite()) {
                    return Err(FilterError::Input(format!("cell {c}: value {y} with variance {a}")));
                }
                (*d, *v) = detail_step((*d, *v), *modal, *modal_var, y, a);
            }
        }
        Ok(cells
            .iter()
            .map(|&c| {
                let (m, mv, d, v) = at[slot[c] as usize];
                (m + d, mv + v)
            })
            .unzip())
    }

    /// Set the field at `obs.cells` to an estimate made elsewhere (with what the filter already
    /// knew, as the between-lattice estimate is): the detail takes its difference from the
    /// modal mean, and the variance the modal part leaves of it (floored: the reported
    /// variance is never below the modal part's).
    pub fn assign(&mut self, obs: &Observation<'_>) -> Result<(), FilterError> {
        let n = self.basis.nrows();
        obs.check_lengths()?;
        let (basis, cov, mean) = ((*self.basis).as_ref(), self.cov.as_ref(), &self.mean);
        let (modal, modal_var) = self.modal.get_or_init(|| modal_of(basis, cov, mean));
        for ((&c, &y), &a) in obs.cells.iter().zip(obs.values).zip(obs.variance) {
            if c >= n || !(y.is_finite() && a >= 0.0 && a.is_finite()) {
                return Err(FilterError::Input(format!("cell {c}: value {y} with variance {a}")));
            }
            self.detail[c] = y - modal[c];
            self.detail_var[c] = (a - modal_var[c]).max(1e-12);
        }
        Ok(())
    }

    /// The modal part of the field, `B a`.
    pub fn modal_mean(&self) -> &[f64] {
        &self.modal().0
    }

    /// The modal part's variance per cell, `diag(B P B^T)`.
    pub fn modal_variance(&self) -> &[f64] {
        &self.modal().1
    }

    fn modal(&self) -> &(Vec<f64>, Vec<f64>) {
        self.modal
            .get_or_init(|| modal_of((*self.basis).as_ref(), self.cov.as_ref(), &self.mean))
    }

    /// The field of the current state and its variance per cell.
    pub fn field(&self) -> (Vec<f64>, Vec<f64>) {
        let add = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x + y).collect();
        let (mean, variance) = self.modal();
        (add(mean, &self.detail), add(variance, &self.detail_var))
    }
}

/// How far one step's values fell from the forecast, against how far the filter expected
/// (its variance there plus the values' noise): the normalised innovation squared, mean over
/// the values (1 when the reported variance is right; above, the filter is overconfident). Needs
/// no truth: it is how a run in the field checks its own uncertainty.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Innovation {
    /// Mean of `(value - forecast)^2 / (forecast variance + noise variance)`.
    pub nis: f64,
    /// Values it is the mean over.
    pub values: usize,
}

impl Innovation {
    /// The innovations of `values` at the prior's cells (noise variances `noise_var`) against
    /// `prior`.
    pub fn of(prior: &Prior, values: &[f64], noise_var: &[f64]) -> Self {
        let cells = &prior.cells;
        let sum: f64 = cells
            .iter()
            .zip(&prior.variance)
            .zip(values)
            .zip(noise_var)
            .map(|(((&c, p), v), r)| (v - prior.mean[c]).powi(2) / (p + r).max(1e-300))
            .sum();
        Self {
            nis: sum / cells.len().max(1) as f64,
            values: cells.len(),
        }
    }
}

/// The forecast before an update: its mean per cell of the grid, and at `cells` (the values
/// it is tested against) its variance and its detail's variance, in the order of `cells`.
#[derive(Debug, Clone)]
pub struct Prior {
    pub mean: Vec<f64>,
    pub cells: Vec<usize>,
    pub variance: Vec<f64>,
    pub detail_var: Vec<f64>,
    /// The modal mean and variance at `cells`, and the filter's state they are of
    /// ([`ModalFilter::detail_fit_at_prior`] takes them while that state lasts).
    modal: (u64, Vec<(f64, f64)>),
}

/// The variance of a set of values (0 for none).
pub fn variance_of(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64
}

fn symmetrised(p: Mat<f64>) -> Mat<f64> {
    Mat::from_fn(p.nrows(), p.ncols(), |i, j| 0.5 * (p[(i, j)] + p[(j, i)]))
}

/// A DMD model's dynamics in an orthonormal real basis `B` of its modes: `B^T Phi Lambda
/// Phi^+ B`, real part (exactly real when the modes come in conjugate pairs).
pub fn modal_dynamics(
    modes: MatRef<'_, c64>,
    eigenvalues: &[c64],
    basis: MatRef<'_, f64>,
) -> Result<Mat<f64>, FilterError> {
    let (n, r, q) = (modes.nrows(), modes.ncols(), basis.ncols());
    if basis.nrows() != n || eigenvalues.len() != r {
        return Err(FilterError::Input(
            "modes, eigenvalues and basis disagree in size".into(),
        ));
    }
    let bc = Mat::from_fn(n, q, |i, j| c64::new(basis[(i, j)], 0.0));
    let gram = modes.adjoint() * modes; // r x r
    let c = modes.adjoint() * bc.as_ref(); // r x q
    let lu = gram.partial_piv_lu();
    let coef = faer::linalg::solvers::Solve::solve(&lu, c.as_ref()); // Phi^+ B
    let scaled = Mat::from_fn(r, q, |i, j| eigenvalues[i] * coef[(i, j)]);
    // B^H Phi = (Phi^H B)^H = c^H: the N x q x r product is already made.
    let a = c.adjoint() * scaled.as_ref(); // q x q
    let out = Mat::from_fn(q, q, |i, j| a[(i, j)].re);
    check_finite(
        "the modal dynamics",
        out.col_iter().flat_map(|c| c.iter().copied().collect::<Vec<_>>()),
    )
    .map_err(|_| FilterError::Numerical("the modes are linearly dependent".into()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// One cell's modal mean and variance, its terms added one at a time in order: what
    /// [`modal_block`]'s lanes must give to the bit.
    fn one_cell(b: &[f64], cov: MatRef<'_, f64>, mean: &[f64]) -> (f64, f64) {
        let modal = b.iter().zip(mean).fold(0.0, |s, (x, m)| s + x * m);
        let var = (0..b.len()).fold(0.0, |s, k| {
            s + b[k] * column(cov, k).iter().zip(b).fold(0.0, |t, (p, x)| t + p * x)
        });
        (modal, var.max(0.0))
    }

    /// A random N x q basis, a random covariance `L L^T` and a random mean, from `seed`.
    fn random_modal_state(n: usize, q: usize, seed: u64) -> (Mat<f64>, Mat<f64>, Vec<f64>) {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let normal = Normal::new(0.0, 1.0).unwrap();
        let basis = Mat::from_fn(n, q, |_, _| normal.sample(&mut rng));
        let l = Mat::from_fn(q, q, |_, _| normal.sample(&mut rng));
        let mean: Vec<f64> = (0..q).map(|_| normal.sample(&mut rng)).collect();
        (basis, &l * l.transpose(), mean)
    }

    /// The modal mean and variance at a set of cells are the whole field's ([`modal_of`]) at
    /// those cells, to rounding (1e-12 relative: q = 7 terms), and each cell's the bits of the
    /// cell alone, its terms added one at a time, whichever other cells are asked with it and
    /// in whatever order (the filter's results do not depend on which cells a test looks at).
    /// 40,000 cells: shared between the cores.
    #[test]
    fn the_modal_part_at_cells_is_the_fields_whatever_cells_are_asked() {
        let (n, q) = (40_000, 7);
        let (basis, cov, mean) = random_modal_state(n, q, 3);
        let (field_mean, field_var) = modal_of(basis.as_ref(), cov.as_ref(), &mean);
        let cells: Vec<usize> = (0..n).rev().step_by(3).chain(0..50).collect();
        let at = modal_at_cells(basis.as_ref(), cov.as_ref(), &mean, &cells);
        for (&c, &(m, v)) in cells.iter().zip(&at) {
            assert!(
                (m - field_mean[c]).abs() <= 1e-12 * (1.0 + field_mean[c].abs()),
                "mean at {c}"
            );
            assert!(
                (v - field_var[c]).abs() <= 1e-12 * (1.0 + field_var[c]),
                "variance at {c}"
            );
            let row: Vec<f64> = basis.row(c).iter().copied().collect();
            let (rm, rv) = one_cell(&row, cov.as_ref(), &mean);
            assert_eq!((m.to_bits(), v.to_bits()), (rm.to_bits(), rv.to_bits()), "cell {c}");
        }
    }

    /// The field's modal variance made in pieces of [`SUB_ROWS`] rows, on both cores, is the
    /// one whole product `B P` and its row sums to the bit: 40,003 cells (neither the cores'
    /// blocks nor the pieces divide it).
    #[test]
    fn the_modal_variance_in_pieces_is_the_whole_products() {
        let (n, q) = (40_003, 9);
        let (basis, cov, mean) = random_modal_state(n, q, 5);
        let (_, pieces) = modal_of(basis.as_ref(), cov.as_ref(), &mean);
        let mut whole = vec![0.0; n];
        let mut bp = Mat::<f64>::zeros(n, q);
        matmul(bp.as_mut(), Accum::Replace, basis.as_ref(), cov.as_ref(), 1.0, Par::Seq);
        row_dots(bp.as_ref(), basis.as_ref(), &mut whole);
        for (c, (a, b)) in pieces.iter().zip(&whole).enumerate() {
            assert_eq!(a.to_bits(), b.max(0.0).to_bits(), "cell {c}");
        }
    }

    /// Values drawn with exactly the spread the filter expects (its variance plus each value's
    /// noise) give a normalised innovation of 1: within 4 standard errors (the ratio of a
    /// Gaussian square to its variance has variance 2) over 20,000 values; twice the spread
    /// gives 4.
    #[test]
    fn the_normalised_innovation_is_one_when_the_variance_is_right() {
        let n = 20_000;
        let prior = Prior {
            mean: (0..n).map(|i| (i as f64).sin()).collect(),
            cells: (0..n).collect(),
            variance: (0..n).map(|i| 0.01 + 0.001 * (i % 7) as f64).collect(),
            detail_var: vec![0.0; n],
            modal: (u64::MAX, vec![]),
        };
        let noise: Vec<f64> = (0..n).map(|i| 0.0004 * (1 + i % 3) as f64).collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let z = Normal::new(0.0, 1.0).unwrap();
        let draw = |scale: f64, rng: &mut rand_chacha::ChaCha8Rng| -> Vec<f64> {
            (0..n)
                .map(|c| prior.mean[c] + scale * (prior.variance[c] + noise[c]).sqrt() * z.sample(rng))
                .collect()
        };
        let right = Innovation::of(&prior, &draw(1.0, &mut rng), &noise);
        assert_eq!(right.values, n);
        assert!((right.nis - 1.0).abs() < 4.0 * (2.0 / n as f64).sqrt(), "{}", right.nis);
        let wide = Innovation::of(&prior, &draw(2.0, &mut rng), &noise);
        assert!(
            (wide.nis - 4.0).abs() < 4.0 * 4.0 * (2.0 / n as f64).sqrt(),
            "{}",
            wide.nis
        );
    }

    /// A 3-mode rotation-and-decay system on 40 cells with an orthonormal basis.
    fn system(n: usize) -> (Mat<f64>, Mat<f64>) {
        let raw = Mat::from_fn(n, 3, |i, j| {
            ((i + 1) as f64 * (j + 1) as f64 * 0.37).sin() + if j == 2 { 0.5 } else { 0.0 }
        });
        let qr = raw.qr();
        let b = qr.compute_thin_Q();
        let (c, s) = (0.95 * 0.3f64.cos(), 0.95 * 0.3f64.sin());
        let a = Mat::from_fn(3, 3, |i, j| match (i, j) {
            (0, 0) | (1, 1) => c,
            (0, 1) => -s,
            (1, 0) => s,
            (2, 2) => 0.9,
            _ => 0.0,
        });
        (b, a)
    }

    /// The textbook Kalman filter, covariance form with the m x m innovation covariance.
    fn textbook(
        b: MatRef<f64>,
        a: MatRef<f64>,
        (mean, cov): (&mut Mat<f64>, &mut Mat<f64>),
        (q, s): (f64, f64),
        o: Observation<'_>,
    ) {
        let (cells, y, var) = (o.cells, o.values, o.variance);
        let k = a.nrows();
        *mean = a * mean.as_ref();
        *cov = a * cov.as_ref() * a.transpose() + Mat::<f64>::identity(k, k) * faer::Scale(q);
        let h = Mat::from_fn(cells.len(), k, |i, j| b[(cells[i], j)]);
        let r = Mat::from_fn(cells.len(), cells.len(), |i, j| if i == j { var[i] + s } else { 0.0 });
        let sm = h.as_ref() * cov.as_ref() * h.transpose() + r;
        let ym = Mat::from_fn(cells.len(), 1, |i, _| y[i]);
        let innov = ym - h.as_ref() * mean.as_ref();
        let lu = sm.partial_piv_lu();
        let kt = faer::linalg::solvers::Solve::solve(&lu, (h.as_ref() * cov.as_ref()).as_ref()); // S^-1 H P
        *mean = mean.as_ref() + kt.transpose() * innov.as_ref();
        *cov = cov.as_ref() - kt.transpose() * (h.as_ref() * cov.as_ref());
    }

    #[test]
    fn with_the_true_model_the_posterior_is_the_kalman_filters() {
        let n = 40;
        let (b, a) = system(n);
        let (q, s) = (1e-3, 2e-4);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 1.0).unwrap();
        let p0 = Mat::<f64>::identity(3, 3);
        let mut f = ModalFilter::new(b.clone(), a.clone(), vec![0.0; 3], p0.clone(), q, s).unwrap();
        let (mut tm, mut tp) = (Mat::<f64>::zeros(3, 1), p0);
        let mut worst: f64 = 0.0;
        for t in 0..30 {
            // Steps alternate between a dense coarse source and a small precise one, or none.
            let cells: Vec<usize> = match t % 3 {
                0 => (0..n).step_by(2).collect(),
                1 => (10..16).collect(),
                _ => vec![],
            };
            let var: Vec<f64> = cells
                .iter()
                .map(|&c| if t % 3 == 0 { 0.01 + 1e-4 * c as f64 } else { 1e-4 })
                .collect();
            let y: Vec<f64> = cells
                .iter()
                .map(|&c| (c as f64 * 0.1 + t as f64 * 0.2).sin() + noise.sample(&mut rng) * 0.05)
                .collect();
            f.predict();
            f.update(&[Observation {
                cells: &cells,
                values: &y,
                variance: &var,
            }])
            .unwrap();
            textbook(
                b.as_ref(),
                a.as_ref(),
                (&mut tm, &mut tp),
                (q, s),
                Observation {
                    cells: &cells,
                    values: &y,
                    variance: &var,
                },
            );
            for i in 0..3 {
                worst = worst.max((f.mean[i] - tm[(i, 0)]).abs());
                for j in 0..3 {
                    worst = worst.max((f.cov[(i, j)] - tp[(i, j)]).abs());
                }
            }
        }
        // Two algebraically equal forms in double precision over 30 steps of O(1) quantities:
        // round-off of order 1e-14 per step; 1e-10 leaves room and still fails any real slip.
        println!("information form vs textbook Kalman filter, largest difference over 30 steps: {worst:e}");
        assert!(worst < 1e-10, "information form vs textbook Kalman filter: {worst:e}");
    }

    #[test]
    fn reported_variance_matches_a_monte_carlo_of_the_error() {
        // Truth drawn from the filter's own model; the mean over cells and runs of
        // error^2 / reported variance is 1 in expectation.
        let n = 30;
        let (b, a) = system(n);
        let (q, s) = (2e-3, 1e-3);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let std = Normal::new(0.0, 1.0).unwrap();
        let (mut ratio_sum, mut count) = (0.0, 0usize);
        for _ in 0..400 {
            let mut state: Vec<f64> = (0..3).map(|_| std.sample(&mut rng)).collect();
            let mut f = ModalFilter::new(b.clone(), a.clone(), vec![0.0; 3], Mat::identity(3, 3), q, s).unwrap();
            for t in 0..8 {
                let next: Vec<f64> = (0..3)
                    .map(|i| (0..3).map(|j| a[(i, j)] * state[j]).sum::<f64>() + q.sqrt() * std.sample(&mut rng))
                    .collect();
                state = next;
                let x: Vec<f64> = (0..n)
                    .map(|c| (0..3).map(|k| b[(c, k)] * state[k]).sum::<f64>() + s.sqrt() * std.sample(&mut rng))
                    .collect();
                let cells: Vec<usize> = if t % 2 == 0 {
                    (0..n).step_by(3).collect()
                } else {
                    vec![4, 5, 6]
                };
                let var: Vec<f64> = cells.iter().map(|_| 0.02).collect();
                let y: Vec<f64> = cells
                    .iter()
                    .map(|&c| x[c] + 0.02f64.sqrt() * std.sample(&mut rng))
                    .collect();
                f.predict();
                f.update(&[Observation {
                    cells: &cells,
                    values: &y,
                    variance: &var,
                }])
                .unwrap();
                if t == 7 {
                    let (m, v) = f.field();
                    for c in 0..n {
                        ratio_sum += (m[c] - x[c]).powi(2) / v[c];
                        count += 1;
                    }
                }
            }
        }
        let ratio = ratio_sum / count as f64;
        // 400 runs x 30 correlated cells: the ratio's standard error is a few per cent, so the
        // 10% band is a real test of the variances (a filter that ignored s or q fails it).
        println!("Monte Carlo: mean error^2 / reported variance = {ratio:.4} over {count} cells");
        assert!((ratio - 1.0).abs() < 0.1, "mean error^2 / variance = {ratio}");
    }

    /// Truth with a persistent detail (AR(1), `rho`, stationary variance `s`, independent per
    /// cell) beside the modal state; the filter told the true `rho`, `q` and `s`. Returns the
    /// mean error^2 / reported variance and the mean error^2 at the last step over `runs`.
    fn persistent_run(rho_filter: f64, runs: usize) -> (f64, f64) {
        let n = 30;
        let (b, a) = system(n);
        let (q, s, rho): (f64, f64, f64) = (2e-3, 4e-3, 0.9);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let std = Normal::new(0.0, 1.0).unwrap();
        let (mut ratio, mut err2, mut count) = (0.0, 0.0, 0usize);
        for _ in 0..runs {
            let mut state: Vec<f64> = (0..3).map(|_| std.sample(&mut rng)).collect();
            let mut e: Vec<f64> = (0..n).map(|_| s.sqrt() * std.sample(&mut rng)).collect();
            let mut f = ModalFilter::new(b.clone(), a.clone(), vec![0.0; 3], Mat::identity(3, 3), q, s).unwrap();
            f.persistence = rho_filter;
            for t in 0..12 {
                state = (0..3)
                    .map(|i| (0..3).map(|j| a[(i, j)] * state[j]).sum::<f64>() + q.sqrt() * std.sample(&mut rng))
                    .collect();
                e = e
                    .iter()
                    .map(|x| rho * x + ((1.0 - rho * rho) * s).sqrt() * std.sample(&mut rng))
                    .collect();
                let x: Vec<f64> = (0..n)
                    .map(|c| (0..3).map(|k| b[(c, k)] * state[k]).sum::<f64>() + e[c])
                    .collect();
                let cells: Vec<usize> = if t % 2 == 0 {
                    (0..n).step_by(3).collect()
                } else {
                    (4..12).collect()
                };
                let var: Vec<f64> = cells.iter().map(|_| if t % 2 == 0 { 0.01 } else { 1e-3 }).collect();
                let y: Vec<f64> = cells
                    .iter()
                    .zip(&var)
                    .map(|(&c, v)| x[c] + v.sqrt() * std.sample(&mut rng))
                    .collect();
                f.predict();
                let o = Observation {
                    cells: &cells,
                    values: &y,
                    variance: &var,
                };
                f.update(&[o]).unwrap();
                f.update_detail(&[o]).unwrap();
                if t == 11 {
                    let (m, v) = f.field();
                    for c in 0..n {
                        ratio += (m[c] - x[c]).powi(2) / v[c];
                        err2 += (m[c] - x[c]).powi(2);
                        count += 1;
                    }
                }
            }
        }
        (ratio / count as f64, err2 / count as f64)
    }

    #[test]
    fn a_persistent_detail_is_carried_and_its_variance_is_calibrated() {
        let (ratio, err) = persistent_run(0.9, 400);
        let (_, white) = persistent_run(0.0, 400);
        // The detail filter drops the cross-covariance of modes and detail, so it is not the
        // exact posterior: a 15% band on the ratio (standard error a few per cent) still fails
        // a filter that forgot the detail's persistence in its variance (ratio well off 1).
        println!(
            "persistent detail: mean error^2 / variance = {ratio:.4}; MSE {err:.3e} with rho, {white:.3e} as \
            white noise"
        );
        assert!((ratio - 1.0).abs() < 0.15, "mean error^2 / variance = {ratio}");
        assert!(
            err < 0.95 * white,
            "carrying the detail must help: {err:e} vs {white:e}"
        );
    }

    /// A pure, white detail (rho = 0) of true variance 1 seen densely every step (400 cells,
    /// noise 0.1) by a filter that starts believing the model error `start`: each step's
    /// forecast fit ratio (before `after` acts on it with the filter), over 40 steps.
    fn white_detail_fits(
        start: f64,
        seed: u64,
        mut after: impl FnMut(&mut ModalFilter, f64),
    ) -> (Vec<f64>, ModalFilter) {
        let n = 400;
        let (b, a) = system(n);
        let std = Normal::new(0.0, 1.0).unwrap();
        let noise = 0.1f64;
        let cells: Vec<usize> = (0..n).collect();
        let var = vec![noise; n];
        let mut f = ModalFilter::new(b, a, vec![0.0; 3], Mat::zeros(3, 3), 0.0, start).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut ratios = vec![];
        for _ in 0..40 {
            f.predict();
            let y: Vec<f64> = (0..n)
                .map(|_| std.sample(&mut rng) + noise.sqrt() * std.sample(&mut rng))
                .collect();
            let o = Observation {
                cells: &cells,
                values: &y,
                variance: &var,
            };
            let ratio = f.detail_fit(&o).unwrap().unwrap();
            ratios.push(ratio);
            after(&mut f, ratio);
        }
        (ratios, f)
    }

    #[test]
    fn a_detail_variance_set_wrong_is_rescaled_until_it_fits() {
        // Pure detail, white (rho = 0) with true variance s = 1, seen densely every step with
        // noise 0.1; the filter starts believing s = 0.01 (100x too small) or 100 (100x too
        // big). The fit ratio rescales the forecast's detail variance each step: the factor
        // settles, and the variance it reports is then the true one within the estimate's
        // noise (400 cells a step).
        let n = 400;
        let (b, a) = system(n);
        let s = 1.0f64;
        for (start, seed) in [(0.01, 21), (100.0, 22)] {
            let (ratios, f) = white_detail_fits(start, seed, |f, ratio| {
                f.rescale_detail(ratio, 1e6, 0..n);
                // (The detail's own forecast variance is what is checked: no update here.)
                f.model_error = f.detail_var[0];
            });
            let settled = ratios[30..].iter().sum::<f64>() / 10.0;
            println!(
                "start s = {start}: fit ratio {:.3} at first, {settled:.3} settled; detail variance {:.3}",
                ratios[0], f.detail_var[0]
            );
            assert!(
                (ratios[0] - 1.0 / start).abs() < 0.2 / start,
                "the first fit says how far off the start is: {}",
                ratios[0]
            );
            assert!((settled - 1.0).abs() < 0.15, "settled fit {settled}");
            assert!(
                (f.detail_var[0] - s).abs() < 0.15,
                "detail variance {}",
                f.detail_var[0]
            );
        }
        // The cap holds.
        let mut f = ModalFilter::new(b, a, vec![0.0; 3], Mat::zeros(3, 3), 0.0, 1.0).unwrap();
        f.rescale_detail(4.0, 1.5, 0..10);
        assert!(
            f.detail_var[..10].iter().all(|&v| v == 1.5) && f.detail_var[10..].iter().all(|&v| v == 1.0),
            "only the cells given, capped"
        );
        f.rescale_detail(4.0, 1.5, 0..n);
        f.rescale_detail(f64::NAN, 1.5, 0..n);
        assert!(
            f.detail_var.iter().all(|&v| v == 1.5),
            "a ratio that is not a number changes nothing"
        );
        // A cap below the variance (a flat field: 0) neither raises nor lowers it; shrinking is
        // by the factor alone.
        f.rescale_detail(4.0, 0.0, 0..n);
        assert!(
            f.detail_var.iter().all(|&v| v == 1.5),
            "a cap of 0 does not zero the detail"
        );
        f.rescale_detail(0.25, 0.0, 0..n);
        assert!(f.detail_var.iter().all(|&v| v == 0.75), "a ratio of 1/4 halves it");
    }

    /// A white detail (rho = 0) whose model error starts 100x too small: the lattice's fit
    /// ratio raises the model error until the forecast's detail variance fits. Without the
    /// raise, each predict returns the variance to the model error and the fit stays ~100x
    /// off (the 500 hPa height's first epochs).
    #[test]
    fn a_model_error_too_small_is_raised_by_the_lattices_fit() {
        let (n, s) = (400, 1.0);
        let settled = |raise: bool| {
            let (ratios, f) = white_detail_fits(0.01, 23, |f, ratio| {
                f.rescale_detail(ratio, 1e6, 0..n);
                if raise {
                    f.raise_model_error(ratio, 1e6);
                }
            });
            (ratios[30..].iter().sum::<f64>() / 10.0, f.model_error)
        };
        let (with, model_error) = settled(true);
        let (without, _) = settled(false);
        println!("settled fit {with:.3} (model error {model_error:.3}), {without:.1} without the raise");
        // The raise stops where the fit is 1 or below: within the estimate's noise of 1 (400
        // cells a step), and the model error near the true 1.
        assert!((with - 1.0).abs() < 0.25, "settled fit {with}");
        assert!((model_error - s).abs() < 0.3, "model error {model_error}");
        assert!(without > 20.0, "without the raise the fit stays off: {without}");
        // Only raising, capped; a ratio that is not a number changes nothing.
        let (b, a) = system(n);
        let mut f = ModalFilter::new(b, a, vec![0.0; 3], Mat::zeros(3, 3), 0.0, 1.0).unwrap();
        f.raise_model_error(0.25, 1e6);
        f.raise_model_error(f64::NAN, 1e6);
        assert_eq!(f.model_error, 1.0);
        f.raise_model_error(16.0, 1.5);
        assert_eq!(f.model_error, 1.5);
    }

    /// A field that changes at once: the detail's variance and the model error 10,000x too
    /// small (a first fit on calm frames, then the event). The lattice's fit catches up within
    /// 4 steps (its ratio under 2); growing by at most 2x a step, as until 2026-12-02, took 13.
    #[test]
    fn a_variance_ten_thousand_times_too_small_is_caught_up_in_four_steps() {
        let n = 400;
        let (ratios, _) = white_detail_fits(1e-4, 24, |f, ratio| {
            f.rescale_detail(ratio, 1e6, 0..n);
            f.raise_model_error(ratio, 1e6);
        });
        let caught = ratios.iter().position(|r| *r < 2.0).unwrap();
        println!("fit ratios {:.1?}: under 2 at step {caught}", &ratios[..6]);
        assert!(caught <= 4, "under 2 only at step {caught}");
        assert!(
            ratios[caught..].iter().all(|r| *r < 2.0),
            "and stays there: {ratios:.2?}"
        );
    }

    #[test]
    fn persistence_is_learned_from_a_dense_source() {
        // Pure detail (the modal mean stays 0): AR(1) with rho = 0.8 on 400 cells seen every
        // step with noise; the lag-one moments recover rho.
        let n = 400;
        let (b, a) = system(n);
        let mut f = ModalFilter::new(b, a, vec![0.0; 3], Mat::zeros(3, 3), 0.0, 1.0).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let std = Normal::new(0.0, 1.0).unwrap();
        let (rho, s, noise): (f64, f64, f64) = (0.8, 1.0, 0.1);
        let mut e: Vec<f64> = (0..n).map(|_| std.sample(&mut rng)).collect();
        let cells: Vec<usize> = (0..n).collect();
        let var = vec![noise; n];
        let mut got = 0.0;
        for _ in 0..50 {
            e = e
                .iter()
                .map(|x| rho * x + ((1.0 - rho * rho) * s).sqrt() * std.sample(&mut rng))
                .collect();
            let y: Vec<f64> = e.iter().map(|x| x + noise.sqrt() * std.sample(&mut rng)).collect();
            got = f
                .learn_persistence(
                    &Observation {
                        cells: &cells,
                        values: &y,
                        variance: &var,
                    },
                    1.0,
                )
                .unwrap();
        }
        // 49 x 400 pairs: the estimate's standard error is under 0.01.
        assert!((got - rho).abs() < 0.03, "learned rho {got}");
    }

    #[test]
    fn reprojection_keeps_the_field_and_its_total_variance() {
        let n = 25;
        let (b, a) = system(n);
        let mut f = ModalFilter::new(
            b.clone(),
            a.clone(),
            vec![1.0, -2.0, 0.5],
            Mat::identity(3, 3),
            1e-3,
            1e-3,
        )
        .unwrap();
        let (before, var_before) = f.field();
        // A new basis sharing only the first two directions.
        let nb = b.subcols(0, 2).to_owned();
        f.reproject(nb, a.submatrix(0, 0, 2, 2).to_owned()).unwrap();
        let (after, var_after) = f.field();
        let worst = before
            .iter()
            .zip(&after)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-12, "the field moved by {worst:e}");
        let (tb, ta) = (var_before.iter().sum::<f64>(), var_after.iter().sum::<f64>());
        assert!((tb - ta).abs() < 1e-12 * tb, "total variance {tb} -> {ta}");
    }

    /// The detail's check at a prior's cells takes the prior's modal part only while the
    /// filter's modal state is the one the prior was made at: then it is the fresh check to the
    /// bit (a rescaled detail variance does not change the modal state); after an update, or
    /// at other cells, it makes the modal part afresh (and the prior's stale one would differ).
    #[test]
    fn a_detail_check_takes_the_priors_modal_part_only_while_it_is_current() {
        let n = 40;
        let (b, a) = system(n);
        let cov = Mat::from_fn(3, 3, |i, j| if i == j { 0.5 } else { 0.1 });
        let mut f = ModalFilter::new(b, a, vec![1.0, -2.0, 0.5], cov, 1e-3, 2e-2).unwrap();
        f.predict();
        let cells = [3, 7, 10, 22, 39];
        let y: Vec<f64> = cells.iter().map(|&c| (c as f64 * 0.3).cos()).collect();
        let v = vec![0.01; cells.len()];
        let obs = Observation {
            cells: &cells,
            values: &y,
            variance: &v,
        };
        let bits = |x: Option<f64>| x.unwrap().to_bits();
        let prior = f.prior_at(&cells);
        assert_eq!(
            bits(f.detail_fit_at_prior(&prior, &obs).unwrap()),
            bits(f.detail_fit(&obs).unwrap())
        );
        f.rescale_detail(1.7, 10.0, 0..n);
        assert_eq!(
            bits(f.detail_fit_at_prior(&prior, &obs).unwrap()),
            bits(f.detail_fit(&obs).unwrap())
        );
        let fewer = Observation {
            cells: &cells[..4],
            values: &y[..4],
            variance: &v[..4],
        };
        assert_eq!(
            bits(f.detail_fit_at_prior(&prior, &fewer).unwrap()),
            bits(f.detail_fit(&fewer).unwrap())
        );
        f.update(std::slice::from_ref(&obs)).unwrap();
        let fresh = f.detail_fit(&obs).unwrap();
        assert_eq!(bits(f.detail_fit_at_prior(&prior, &obs).unwrap()), bits(fresh));
        let stale = f.detail_fit_with(&obs, Some(&prior.modal.1)).unwrap();
        assert_ne!(bits(stale), bits(fresh), "the update left the modal part as it was");
    }

    /// The look at a few cells without updating ([`ModalFilter::field_at_after`],
    /// [`ModalFilter::prior_at`]) is what the update leaves there and what the field was: the
    /// same posterior and per-cell arithmetic, the modal variance summed by hand rather than by
    /// faer's product (a few ulps of values of order 1: 1e-12). The filter is not changed.
    #[test]
    fn a_look_at_a_few_cells_is_what_the_update_leaves_there() {
        let n = 40;
        let (b, a) = system(n);
        let cov = Mat::from_fn(3, 3, |i, j| if i == j { 0.5 } else { 0.1 });
        let mut f = ModalFilter::new(b, a, vec![1.0, -2.0, 0.5], cov, 1e-3, 2e-2)
            .unwrap()
            .with_persistence(0.6);
        f.predict();
        let lattice: Vec<usize> = (0..n).step_by(5).collect();
        let lat_y: Vec<f64> = lattice.iter().map(|&c| (c as f64 * 0.3).sin()).collect();
        let dense: Vec<usize> = (0..n).filter(|c| c % 7 != 3).collect();
        let dense_y: Vec<f64> = dense.iter().map(|&c| (c as f64 * 0.3).sin() + 0.05).collect();
        let (lat_v, dense_v) = (vec![0.01; lattice.len()], vec![0.03; dense.len()]);
        let modes = [Observation {
            cells: &lattice,
            values: &lat_y,
            variance: &lat_v,
        }];
        let detail = [Observation {
            cells: &dense,
            values: &dense_y,
            variance: &dense_v,
        }];
        let wanted = [3, 7, 10, 22, 39, 7];
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-12 * x.abs().max(1.0);
        let (field, variance) = f.field();
        let prior = f.prior_at(&wanted);
        for (i, &c) in wanted.iter().enumerate() {
            assert!(
                close(prior.mean[c], field[c]) && close(prior.variance[i], variance[c]),
                "prior at {c}"
            );
        }
        let before = f.field();
        let (mean, var) = f.field_at_after(&modes, &detail, &wanted).unwrap();
        assert_eq!(f.field(), before, "the look changed the filter");
        f.update(&modes).unwrap();
        f.update_detail(&detail).unwrap();
        let (field, variance) = f.field();
        for (i, &c) in wanted.iter().enumerate() {
            assert!(close(mean[i], field[c]), "mean at {c}: {} vs {}", mean[i], field[c]);
            assert!(
                close(var[i], variance[c]),
                "variance at {c}: {} vs {}",
                var[i],
                variance[c]
            );
        }
    }

    #[test]
    fn dynamics_of_conjugate_modes_are_recovered_in_a_real_basis() {
        let n = 20;
        let (b, a) = system(n);
        // Modes of A in B's coordinates: A = V L V^-1 with a complex pair and a real mode.
        let evd = a.eigen().unwrap();
        let v = evd.U();
        let lam: Vec<c64> = (0..3).map(|i| evd.S()[i]).collect();
        let bc = Mat::from_fn(n, 3, |i, j| c64::new(b[(i, j)], 0.0));
        let modes = bc.as_ref() * v;
        let got = modal_dynamics(modes.as_ref(), &lam, b.as_ref()).unwrap();
        let err = (0..3)
            .flat_map(|i| (0..3).map(move |j| (i, j)))
            .map(|(i, j)| (got[(i, j)] - a[(i, j)]).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-12, "{err:e}");
    }

    #[test]
    fn bad_observations_are_refused_not_absorbed() {
        let (b, a) = system(10);
        let mut f = ModalFilter::new(b, a, vec![0.0; 3], Mat::identity(3, 3), 0.0, 0.0).unwrap();
        assert!(f
            .update(&[Observation {
                cells: &[11],
                values: &[1.0],
                variance: &[1.0]
            }])
            .is_err());
        assert!(f
            .update(&[Observation {
                cells: &[1],
                values: &[f64::NAN],
                variance: &[1.0]
            }])
            .is_err());
        assert!(f
            .update(&[Observation {
                cells: &[1],
                values: &[1.0],
                variance: &[0.0]
            }])
            .is_err());
        assert_eq!(f.mean, vec![0.0; 3], "a refused update changes nothing");
    }
}
