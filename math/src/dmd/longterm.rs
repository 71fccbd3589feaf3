//! The paper's "long-term" online DMD (Sect. 4.3.2): the full operator `A = Q S`,
//! `Q = Y X^T`, `S = (X X^T)^-1`, updated by a batch Woodbury step with forgetting factor gamma.
//!
//! **Forgetting, two choices** ([`Forgetting`]):
//! - *unit*: per **batch** (the paper's reading, the default: each update multiplies what came
//!   before by gamma, and the pairs of a batch weigh the same) or per **pair** (weights
//!   `gamma^age` per snapshot pair, as odmd's rank-1 updates do; a batch of `tau` pairs then
//!   multiplies the past by `gamma^tau`);
//! - *directions*: forget only along the directions the new batch **excites** (the default;
//!   Kulhavy's directional forgetting), or along **all** directions (odmd's). Forgetting all
//!   directions is unbounded when the data does not excite every direction: in the unexcited
//!   ones `S` grows as `gamma^-updates` (1e22 after 100 updates at 0.95, NaN at 1,385) and
//!   rounding makes it indefinite. Forgetting only the excited ones leaves the information in
//!   the others as it was, so `S` stays bounded by its value at the start there, and tracks
//!   at rate gamma where the data is.
//!
//! With information `P = S^-1` and the batch's `X` (N x tau), weights `W` and forgetting
//! `phi` (gamma per batch, `gamma^tau` per pair), one update is:
//! - all directions: `S~ = S / phi`;
//! - excited directions: `P~ = P - (1 - phi) P X M^+ X^T P` with `M = X^T P X`, and by
//!   Woodbury `S~ = S + (1/phi - 1) X M^+ X^T` (`A` is unchanged by forgetting: `Q~ = A P~`);
//! - then `G = W^-1 + X^T S~ X`, `K = G^-1 X^T S~` (a Cholesky **solve**: forming `G^-1` cost
//!   6.5e-7 relative error in our numpy reference where a solve gave 3e-10),
//!   `A <- A + (Y - A X) K`, `S <- S~ - S~ X K`, and `P <- P~ + X W X^T`.
//!
//! For gamma = 1 this is the paper's `A' = A + (Y_new - A X_new) Gamma X_new^T S`,
//! `Gamma = (I + X_new^T S X_new)^-1`. `S` must stay positive definite: a `G` that is not, or
//! a non-positive diagonal of `S`, is an error (never a silent fallback).
//!
//! It keeps no snapshots, so it cannot debias nor revise a past step: late data can only be
//! folded in as if it were new (with gamma < 1 it then weighs as new data).

use super::linalg::{div_cols, eig, thin_svd};
use super::snapshots::check_pairs;
use super::{numerical_rank, Dmd, DmdError, Method, Modes};
use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};

/// What a forgetting factor multiplies at each update.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
    Default,
    strum::EnumString,
    strum::Display,
    strum::VariantNames,
    schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = forgettingunit_name_error)]
pub enum ForgettingUnit {
    /// Everything before an update, once per update (the paper's reading).
    #[default]
    Batch,
    /// Each snapshot pair by its age in pairs (odmd's).
    Pair,
}

/// Which directions of the data forgetting applies to.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
    Default,
    strum::EnumString,
    strum::Display,
    strum::VariantNames,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = forgettingdirections_name_error)]
pub enum ForgettingDirections {
    /// Only those the new batch excites (bounded).
    #[default]
    Excited,
    /// All of them (odmd's; unbounded on data that does not excite every direction).
    All,
}

/// How the long-term method forgets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct Forgetting {
    pub unit: ForgettingUnit,
    pub directions: ForgettingDirections,
}

impl From<ForgettingUnit> for Forgetting {
    fn from(unit: ForgettingUnit) -> Self {
        Self {
            unit,
            directions: ForgettingDirections::default(),
        }
    }
}

#[derive(Clone, Debug)]
pub struct LongTermDmd {
    a: Mat<f64>,
    s: Mat<f64>,
    /// The information `S^-1`, kept only for directional forgetting with gamma < 1.
    p: Option<Mat<f64>>,
    gamma: f64,
    forgetting: Forgetting,
    pairs: usize,
}

impl LongTermDmd {
    /// Start from pairs `(X, Y)`; `X` (N x m) must have full row rank N. Forgetting per pair,
    /// along all directions (odmd's); see [`Self::init_with`].
    pub fn init(x: MatRef<'_, f64>, y: MatRef<'_, f64>, gamma: f64) -> Result<Self, DmdError> {
        Self::init_with(
            x,
            y,
            gamma,
            Forgetting {
                unit: ForgettingUnit::Pair,
                directions: ForgettingDirections::All,
            },
        )
    }

    /// Start from pairs `(X, Y)` with the given forgetting (the initial pairs are one batch).
    pub fn init_with(
        x: MatRef<'_, f64>,
        y: MatRef<'_, f64>,
        gamma: f64,
        forgetting: Forgetting,
    ) -> Result<Self, DmdError> {
        check_pairs(x, y, None)?;
        if !(gamma > 0.0 && gamma <= 1.0) {
            return Err(DmdError::Gamma(gamma));
        }
        let (n, m) = (x.nrows(), x.ncols());
        // Per pair: weight column j by sqrt(gamma)^(m-1-j), the newest pair has weight 1. Per
        // batch: the initial pairs are one batch, all weight 1.
        let w: Vec<f64> = (0..m)
            .map(|j| {
                if forgetting.unit == ForgettingUnit::Pair {
                    gamma.sqrt().powi((m - 1 - j) as i32)
                } else {
                    1.0
                }
            })
            .collect();
        let xw = Mat::from_fn(n, m, |i, j| x[(i, j)] * w[j]);
        let yw = Mat::from_fn(n, m, |i, j| y[(i, j)] * w[j]);
        let information = |xw: &Mat<f64>| {
            (gamma < 1.0 && forgetting.directions == ForgettingDirections::Excited)
                .then(|| symmetrised(xw * xw.transpose()))
        };
        if m >= n {
            if let Some((a, s)) = by_qr(xw.as_ref(), yw.as_ref()) {
                return Ok(Self {
                    a,
                    s: symmetrised(s),
                    p: information(&xw),
                    gamma,
                    forgetting,
                    pairs: m,
                });
            }
        }
        let svd = thin_svd(xw.as_ref())?;
        let rank = numerical_rank(&svd.s, n, m);
        if m < n || rank < n {
            return Err(DmdError::NotFullRowRank { n, m, rank });
        }
        // X = U S V^T with U square: (X X^T)^-1 = U S^-2 U^T and A = Y V S^-1 U^T.
        let us = div_cols(svd.u.clone(), &svd.s);
        let s = &us * us.transpose();
        let a = div_cols(&yw * &svd.v, &svd.s) * svd.u.transpose();
        Ok(Self {
            a,
            s: symmetrised(s),
            p: information(&xw),
            gamma,
            forgetting,
            pairs: m,
        })
    }

    /// The full operator `A` (N x N).
    pub fn operator(&self) -> MatRef<'_, f64> {
        self.a.as_ref()
    }

    pub fn gamma(&self) -> f64 {
        self.gamma
    }

    /// `S = (X W X^T)^-1`, the inverse of the (weighted) information.
    pub fn s(&self) -> MatRef<'_, f64> {
        self.s.as_ref()
    }
}

/// `(A, S)` from a Householder QR `X^T = Q R` (backward stable, no squared condition number):
/// `X X^T = R^T R`, so `S = R^-1 R^-T` and `A = Y X^T S = (Y Q) R^-T`, about a third of the
/// work of the SVD. Only when `R` is far from singular: `kappa_F(R) = |R|_F |R^-1|_F` bounds
/// `cond(X)` from above, and must stay 1000x inside the numerical-rank tolerance; otherwise
/// `None`, and the SVD decides the rank.
fn by_qr(x: MatRef<'_, f64>, y: MatRef<'_, f64>) -> Option<(Mat<f64>, Mat<f64>)> {
    let (n, m) = (x.nrows(), x.ncols());
    let qr = x.transpose().qr();
    let r = qr.thin_R();
    let mut rinv = Mat::<f64>::zeros(n, n);
    faer::linalg::triangular_inverse::invert_upper_triangular(rinv.as_mut(), r, faer::get_global_parallelism());
    let kappa = r.norm_l2() * rinv.norm_l2();
    if !kappa.is_finite() || kappa * (n.max(m) as f64) * f64::EPSILON > 1e-3 {
        return None;
    }
    let s = &rinv * rinv.transpose();
    let a = (y * qr.compute_thin_Q()) * rinv.transpose();
    Some((a, s))
}

/// The pseudo-inverse of a small symmetric positive semi-definite matrix (its eigenvalues below
/// `1e-12` of the largest dropped): a batch whose columns are dependent excites fewer
/// directions than it has columns.
fn pseudo_inverse_spd(m: MatRef<'_, f64>) -> Result<Mat<f64>, DmdError> {
    let e = m
        .self_adjoint_eigen(faer::Side::Lower)
        .map_err(|err| DmdError::Numerical(format!("{err:?}")))?;
    let (u, d) = (e.U(), e.S().column_vector());
    let top = (0..d.nrows()).map(|i| d[i]).fold(0.0, f64::max);
    let inv: Vec<f64> = (0..d.nrows())
        .map(|i| if d[i] > 1e-12 * top { 1.0 / d[i] } else { 0.0 })
        .collect();
    let ud = Mat::from_fn(u.nrows(), u.ncols(), |i, j| u[(i, j)] * inv[j]);
    Ok(ud * u.transpose())
}

fn symmetrised(s: Mat<f64>) -> Mat<f64> {
    let st = s.transpose().to_owned();
    (s + st) * faer::Scale(0.5)
}

impl Dmd for LongTermDmd {
    fn method(&self) -> Method {
        Method::LongTerm
    }

    fn update(&mut self, x_new: MatRef<'_, f64>, y_new: MatRef<'_, f64>) -> Result<(), DmdError> {
        check_pairs(x_new, y_new, Some(self.a.nrows()))?;
        let tau = x_new.ncols();
        let g = self.gamma;
        let per_pair = self.forgetting.unit == ForgettingUnit::Pair;
        // What the past is multiplied by, and each new pair's weight.
        let phi = if per_pair { g.powi(tau as i32) } else { g };
        let w: Vec<f64> = (0..tau)
            .map(|j| if per_pair { g.powi((tau - 1 - j) as i32) } else { 1.0 })
            .collect();
        // Forget (A does not change: Q~ = A P~).
        let st = if g == 1.0 {
            self.s.clone()
        } else {
            match &mut self.p {
                None => &self.s * faer::Scale(1.0 / phi),
                Some(p) => {
                    let px = &*p * x_new; // N x tau
                    let m = x_new.transpose() * &px; // tau x tau
                    let minv = pseudo_inverse_spd(m.as_ref())?;
                    *p = symmetrised(&*p - &px * (&minv * faer::Scale(1.0 - phi)) * px.transpose());
                    &self.s + x_new * (&minv * faer::Scale(1.0 / phi - 1.0)) * x_new.transpose()
                }
            }
        };
        let sx = &st * x_new; // N x tau
        let mut gm = x_new.transpose() * &sx; // tau x tau
        for j in 0..tau {
            gm[(j, j)] += 1.0 / w[j];
        }
        let gm = symmetrised(gm);
        let llt = gm.llt(faer::Side::Lower).map_err(|_| {
            DmdError::Numerical(
                "the long-term update's G = W^-1 + X^T S X is not positive definite: S has lost positive definiteness"
                    .into(),
            )
        })?;
        let k = faer::linalg::solvers::Solve::solve(&llt, sx.transpose()); // tau x N
        let e = y_new - &self.a * x_new; // innovation
        self.a += &e * &k;
        self.s = symmetrised(st - &sx * &k);
        if let Some(p) = &mut self.p {
            let xw = Mat::from_fn(x_new.nrows(), tau, |i, j| x_new[(i, j)] * w[j]);
            *p = symmetrised(&*p + &xw * x_new.transpose());
        }
        if let Some(i) = (0..self.s.nrows()).find(|&i| !(self.s[(i, i)] > 0.0 && self.s[(i, i)].is_finite())) {
            return Err(DmdError::Numerical(format!(
                "S is no longer positive definite (S[{i},{i}] = {:e}) after {} pairs",
                self.s[(i, i)],
                self.pairs + tau
            )));
        }
        self.pairs += tau;
        Ok(())
    }

    fn decompose(&self) -> Result<Modes, DmdError> {
        let (eigenvalues, v) = eig(self.a.as_ref())?;
        Ok(Modes { eigenvalues, modes: v })
    }

    fn rank(&self) -> usize {
        self.a.nrows()
    }

    fn pairs(&self) -> usize {
        self.pairs
    }

    fn dim(&self) -> usize {
        self.a.nrows()
    }
}

/// A name that is not a [`ForgettingUnit`]'s.
fn forgettingunit_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!(
        "forgetting must be one of {}, got {got:?}",
        ForgettingUnit::VARIANTS.join(", ")
    )
}

/// A name that is not a [`ForgettingDirections`]'s.
fn forgettingdirections_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!(
        "forgetting directions must be one of {}, got {got:?}",
        ForgettingDirections::VARIANTS.join(", ")
    )
}
