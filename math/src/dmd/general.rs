//! The paper's "general" online DMD (Sect. 4.3.1): Brand's incremental SVD of `X` with a batch
//! `X_new` of any size per update, then the projected operator from `Y W S^-1`.
//!
//! Per update, with `U` (N x r), `S`, and `YW = Y W` (N x r) maintained:
//! `L = U^T X_new`, `H = X_new - U L` (re-projected once more: "twice is enough"),
//! `H = J P` (QR of `H` and an SVD of its `R`, so `J` only holds the directions `H` really has),
//! `Z = [[S, L], [0, P]] = U' S' W'^T`, then `U <- [U J] U'_r`, `S <- S'_r`,
//! `YW <- YW W'_top + Y_new W'_bottom` (so `W` itself is never needed).
//!
//! **Orthogonality over thousands of updates.** Each update loses a little orthogonality of `U`
//! to rounding. Every [`REORTH_EVERY`] updates `max|U^T U - I|` is measured and, above
//! [`REORTH_TOL`], `U` is re-orthonormalised without changing the factorisation: `U = Q R`,
//! `R S = U_R S_R W_R^T`, `U <- Q U_R`, `S <- S_R`, `YW <- YW W_R` (exact, since
//! `X = U S W^T = Q U_R S_R (W W_R)^T`). The snapshots are kept, as the paper requires, both for
//! debiasing and for re-fitting when late data arrives.
//!
//! Rank: `Full` keeps every direction above the numerical-rank tolerance; `Fixed(r)` truncates to
//! `r` after the first fit and after every update (path dependent, like any truncated iSVD);
//! `Energy` and `Optimal` choose `r` from the full spectrum at the first fit and then hold it.

use super::batch::{exact_fit, ProjectedFit};
use super::debias::Debias;
use super::linalg::{div_cols, orthogonality_error, scale_cols_by, thin_svd};
use super::snapshots::check_pairs;
use super::{numerical_rank, Dmd, DmdError, Factored, Method, Modes, RankPolicy, SnapshotPairs};
use crate::par::{product, product_add};
use faer::{Mat, MatRef};

/// Updates between orthogonality checks of `U`.
pub const REORTH_EVERY: usize = 16;
/// Largest tolerated `max|U^T U - I|` before re-orthonormalising.
pub const REORTH_TOL: f64 = 1e-13;

#[derive(Clone, Debug)]
pub struct GeneralDmd {
    /// Every pair, kept only when the debiasing needs them (`Debias::None` does not: `yw`
    /// carries `Y W` along, so a mission's history of full fields is not held in memory, nor
    /// copied by every checkpoint); and how many pairs, of what dimension.
    pairs: Option<SnapshotPairs>,
    count: usize,
    dim: usize,
    /// The rank rule applied after each update (energy / optimal are frozen to a number at init).
    rank: RankPolicy,
    debias: Debias,
    u: Mat<f64>,
    s: Vec<f64>,
    yw: Mat<f64>,
    updates: usize,
    reorthogonalisations: usize,
}

impl GeneralDmd {
    pub fn init(x: MatRef<'_, f64>, y: MatRef<'_, f64>, rank: RankPolicy, debias: Debias) -> Result<Self, DmdError> {
        let pairs = SnapshotPairs::new(x, y)?;
        let (count, dim) = (pairs.len(), pairs.dim());
        let pairs = (debias != Debias::None).then_some(pairs);
        let (fit, _) = exact_fit(x, y, rank)?;
        let ProjectedFit { u, s, yws } = fit;
        let held = match rank {
            RankPolicy::Full | RankPolicy::Fixed(_) => rank,
            RankPolicy::Energy(_) | RankPolicy::Optimal => RankPolicy::Fixed(s.len()),
        };
        let yw = scale_cols_by(yws, &s);
        Ok(Self {
            pairs,
            count,
            dim,
            rank: held,
            debias,
            u,
            s,
            yw,
            updates: 0,
            reorthogonalisations: 0,
        })
    }

    /// Current singular values of `X`'s retained factorisation.
    pub fn singular_values(&self) -> &[f64] {
        &self.s
    }

    /// `max|U^T U - I|` now.
    pub fn orthogonality_error(&self) -> f64 {
        orthogonality_error(self.u.as_ref())
    }

    /// How many times `U` has been re-orthonormalised.
    pub fn reorthogonalisations(&self) -> usize {
        self.reorthogonalisations
    }

    fn projected(&self) -> ProjectedFit {
        ProjectedFit {
            u: self.u.clone(),
            s: self.s.clone(),
            yws: self.yws(),
        }
    }

    /// `F = Y W S^-1`, the factor the modes are made from (`A~ = U^T F`).
    fn yws(&self) -> Mat<f64> {
        div_cols(self.yw.clone(), &self.s)
    }

    fn reorthonormalise(&mut self) -> Result<(), DmdError> {
        let qr = self.u.qr();
        let q = qr.compute_thin_Q();
        let rs = scale_cols_by(qr.thin_R().to_owned(), &self.s);
        let svd = thin_svd(rs.as_ref())?;
        self.u = q * &svd.u;
        self.s = svd.s;
        self.yw = &self.yw * &svd.v;
        self.reorthogonalisations += 1;
        Ok(())
    }
}

/// `H ~ J P` with `J` orthonormal (N x k) and `k` the numerical rank of `H` (at most `max_k`):
/// a Householder QR of the tall, thin `H` and an SVD of its small `R`, `H = Q R = (Q U_R) S V_R^T`,
/// so `J = Q U_R` over the singular values above rounding and `P = S V_R^T` there. Each kept
/// column of `J` is `H v / s`, in the range of `H` (orthogonal to `U`); an unpivoted QR's `Q`
/// alone would not do, its extra columns for a rank-deficient `H` being arbitrary. (A
/// column-pivoted QR reveals the rank too, but faer's took 5-7 ms of a 73,728 x 5 `H`, a tenth
/// of the epoch at 192 x 384; the SVD of a 5 x 5 `R` is nothing.)
fn new_directions(h: MatRef<'_, f64>, s0: f64, max_k: usize) -> Result<(Mat<f64>, Mat<f64>), DmdError> {
    let (n, tau) = (h.nrows(), h.ncols());
    let qr = h.qr();
    let svd = thin_svd(qr.thin_R())?;
    let scale = s0.max(svd.s.first().copied().unwrap_or(0.0));
    let tol = (n.max(tau) as f64) * f64::EPSILON * scale;
    let k = svd.s.iter().take_while(|&&s| s > tol).count().min(max_k);
    let j = product(qr.compute_thin_Q().as_ref(), svd.u.subcols(0, k));
    let p = Mat::from_fn(k, tau, |i, c| svd.s[i] * svd.v[(c, i)]);
    Ok((j, p))
}

impl Dmd for GeneralDmd {
    fn method(&self) -> Method {
        Method::General
    }

    fn update(&mut self, x_new: MatRef<'_, f64>, y_new: MatRef<'_, f64>) -> Result<(), DmdError> {
        check_pairs(x_new, y_new, Some(self.dim))?;
        if let Some(p) = &mut self.pairs {
            p.push(x_new, y_new)?;
        }
        self.count += x_new.ncols();
        let (n, r, tau) = (self.u.nrows(), self.u.ncols(), x_new.ncols());
        let ut = self.u.transpose();
        let mut l = ut * x_new;
        let mut h = x_new.to_owned();
        product_add(h.as_mut(), self.u.as_ref(), l.as_ref(), -1.0);
        let l2 = ut * &h;
        product_add(h.as_mut(), self.u.as_ref(), l2.as_ref(), -1.0);
        l += &l2;

        // Directions of H that are really new (none when U already spans R^N), by a
        // rank-revealing (column-pivoted) QR: H P = J R, keeping the rows of R above rounding.
        let (j, p) = if r < n {
            new_directions(h.as_ref(), self.s.first().copied().unwrap_or(0.0), n - r)?
        } else {
            (Mat::zeros(n, 0), Mat::zeros(0, tau))
        };
        let k = j.ncols();

        let mut z = Mat::<f64>::zeros(r + k, r + tau);
        for i in 0..r {
            z[(i, i)] = self.s[i];
        }
        z.submatrix_mut(0, r, r, tau).copy_from(&l);
        z.submatrix_mut(r, r, k, tau).copy_from(&p);
        let zs = thin_svd(z.as_ref())?;
        let keep = match self.rank {
            RankPolicy::Full => numerical_rank(&zs.s, n, self.count),
            policy => policy.select(&zs.s, n, self.count),
        }
        .max(1);
        let zs = zs.truncate(keep);

        // Each sum made in place (the bits of the two products added).
        let mut u = product(self.u.as_ref(), zs.u.subrows(0, r));
        if k > 0 {
            product_add(u.as_mut(), j.as_ref(), zs.u.subrows(r, k), 1.0);
        }
        let mut yw = product(self.yw.as_ref(), zs.v.subrows(0, r));
        product_add(yw.as_mut(), y_new, zs.v.subrows(r, tau), 1.0);
        self.yw = yw;
        self.u = u;
        self.s = zs.s;
        self.updates += 1;
        if self.updates.is_multiple_of(REORTH_EVERY) && self.orthogonality_error() > REORTH_TOL {
            self.reorthonormalise()?;
        }
        Ok(())
    }

    fn decompose(&self) -> Result<Modes, DmdError> {
        self.projected().decompose(self.debias, self.pairs.as_ref(), None)
    }

    fn factored(&self) -> Result<Option<Factored>, DmdError> {
        let yws = std::borrow::Cow::Owned(self.yws());
        ProjectedFit::factored(&self.u, yws, self.debias, self.pairs.as_ref(), None).map(Some)
    }

    fn rank(&self) -> usize {
        self.s.len()
    }

    fn pairs(&self) -> usize {
        self.count
    }

    fn dim(&self) -> usize {
        self.dim
    }
}
