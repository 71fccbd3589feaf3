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
use super::linalg::{div_cols, leading_svd, orthogonality_error, orthonormal_factor, scale_cols_by, thin_svd};
use super::snapshots::{check_finite, check_pairs, check_shapes};
use super::{numerical_rank, Dmd, DmdError, Factored, Method, Modes, Prepared, RankPolicy, SnapshotPairs};
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

    /// The update's part that needs only `x_new` (checked): `U`'s and `S`'s new values and
    /// the right singular vectors `W'` that carry `YW` over, the model left as it is. `Y` is
    /// not in `Z = [[S, L], [0, P]]`, so a server can make all this beside the epoch's last
    /// filter step, whose result is only `y_new`'s last column ([`Dmd::prepare`]).
    fn ahead(&self, x_new: MatRef<'_, f64>) -> Result<Ahead, DmdError> {
        let count = self.count + x_new.ncols();
        let (n, r, tau) = (self.u.nrows(), self.u.ncols(), x_new.ncols());
        let ut = self.u.transpose();
        let mut l = ut * x_new;
        let mut h = x_new.to_owned();
        product_add(h.as_mut(), self.u.as_ref(), l.as_ref(), -1.0);
        let l2 = ut * &h;
        product_add(h.as_mut(), self.u.as_ref(), l2.as_ref(), -1.0);
        l += &l2;

        // Directions of H that are really new (none when U already spans R^N; all of U's
        // complement when the batch could fill it).
        let new = match (r < n, tau >= n - r) {
            (false, _) => NewDirections::none(n, tau),
            (true, true) => complement_directions(self.u.as_ref(), h.as_ref()),
            (true, false) => new_directions(h.as_ref(), self.s.first().copied().unwrap_or(0.0), n - r)?,
        };
        let (k, p) = (new.k(), &new.p);

        let mut z = Mat::<f64>::zeros(r + k, r + tau);
        for i in 0..r {
            z[(i, i)] = self.s[i];
        }
        z.submatrix_mut(0, r, r, tau).copy_from(&l);
        z.submatrix_mut(r, r, k, tau).copy_from(p);
        let leading = match self.rank {
            RankPolicy::Fixed(keep) => leading_svd(z.as_ref(), keep)?,
            _ => None,
        };
        let zs = match leading {
            Some(zs) => zs,
            None => {
                let zs = thin_svd(z.as_ref())?;
                let keep = match self.rank {
                    RankPolicy::Full => numerical_rank(&zs.s, n, count),
                    policy => policy.select(&zs.s, n, count),
                }
                .max(1);
                zs.truncate(keep)
            }
        };

        // Each sum made in place (the bits of the two products added).
        let mut u = product(self.u.as_ref(), zs.u.subrows(0, r));
        if k > 0 {
            // J W = Q (U_k W): the small product first.
            let w = match &new.u_k {
                Some(u_k) => u_k * zs.u.subrows(r, k),
                None => zs.u.subrows(r, k).to_owned(),
            };
            product_add(u.as_mut(), new.q.as_ref(), w.as_ref(), 1.0);
        }
        Ok(Ahead { u, s: zs.s, w: zs.v })
    }

    /// The update made whole with `y_new` (checked): the pairs kept, `YW <- YW W'_top +
    /// Y_new W'_bottom`, and what [`Self::ahead`] made put in place.
    fn finish(&mut self, ahead: Ahead, x_new: MatRef<'_, f64>, y_new: MatRef<'_, f64>) -> Result<(), DmdError> {
        if let Some(p) = &mut self.pairs {
            p.push(x_new, y_new)?;
        }
        let (r, tau) = (self.u.ncols(), x_new.ncols());
        self.count += tau;
        let mut yw = product(self.yw.as_ref(), ahead.w.subrows(0, r));
        product_add(yw.as_mut(), y_new, ahead.w.subrows(r, tau), 1.0);
        self.yw = yw;
        self.u = ahead.u;
        self.s = ahead.s;
        self.updates += 1;
        if self.updates.is_multiple_of(REORTH_EVERY) && self.orthogonality_error() > REORTH_TOL {
            self.reorthonormalise()?;
        }
        Ok(())
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

/// `H ~ J P` with `J = Q U_k` orthonormal (N x k) and `k` the numerical rank of `H` (at most
/// `max_k`): `H = Q R` ([`orthonormal_factor`]: CholeskyQR twice, Householder where `H` is too
/// ill-conditioned for it) and an SVD of the small `R`, `H = (Q U_R) S V_R^T`, so `U_k` is
/// `U_R` over the singular values above rounding and `P = S V_R^T` there. Each kept column of
/// `J` is `H v / s`, in the range of `H` (orthogonal to `U`); an unpivoted QR's `Q` alone would
/// not do, its extra columns for a rank-deficient `H` being arbitrary. `J` itself is never made:
/// the caller needs only `J W = Q (U_k W)` for a small `W`.
///
/// Why not a Householder QR of the tall, thin `H` always: with its `Q` formed and `Q U_R`
/// multiplied out it read and wrote `H` a dozen times, 4.4 of the update's 15 ms at
/// 73,728 x 5; CholeskyQR twice is two Gram matrices and two triangular solves. (A
/// column-pivoted QR reveals the rank too, but faer's took 5-7 ms of the same `H`.)
fn new_directions(h: MatRef<'_, f64>, s0: f64, max_k: usize) -> Result<NewDirections, DmdError> {
    let (n, tau) = (h.nrows(), h.ncols());
    let (q, r) = orthonormal_factor(h);
    if (SKIP_SVD_OF_R_FROM..=max_k).contains(&tau)
        && surely_full_rank(r.as_ref(), (n.max(tau) as f64) * f64::EPSILON, s0)
    {
        return Ok(NewDirections { q, u_k: None, p: r });
    }
    let svd = thin_svd(r.as_ref())?;
    let scale = s0.max(svd.s.first().copied().unwrap_or(0.0));
    let tol = (n.max(tau) as f64) * f64::EPSILON * scale;
    let k = svd.s.iter().take_while(|&&s| s > tol).count().min(max_k);
    let p = Mat::from_fn(k, tau, |i, c| svd.s[i] * svd.v[(c, i)]);
    Ok(NewDirections {
        q,
        u_k: Some(svd.u.subcols(0, k).to_owned()),
        p,
    })
}

/// The batch width from which [`new_directions`] skips the SVD of `R` when `R` is surely of
/// full rank ([`surely_full_rank`]): below it that SVD is microseconds, and the server's
/// updates (a boat epoch's few snapshots) keep the bits they have always had.
const SKIP_SVD_OF_R_FROM: usize = 32;

/// `J` an orthonormal basis of all of `U`'s complement (N x (N - r)) and `P = J^T H`, for a
/// batch at least as wide as that complement (Table 1's case 2 at rank 10: 90 directions left,
/// 100 snapshots a batch): `H` lies in it, so `H = J P` exactly whatever `H`'s rank, and no
/// factorisation of `H` is needed to find its directions. The complement is the last `N - r`
/// columns of the full `Q` of a Householder QR of `U` (N^2 r flops).
fn complement_directions(u: MatRef<'_, f64>, h: MatRef<'_, f64>) -> NewDirections {
    let (n, r) = (u.nrows(), u.ncols());
    let q = u.qr().compute_Q().subcols(r, n - r).to_owned();
    let p = q.transpose() * h;
    NewDirections { q, u_k: None, p }
}

/// Whether every singular value of the triangular `r` is surely above the rank tolerance,
/// `eps_n` times the larger of `s0` and `r`'s largest singular value, without an SVD of `r`:
/// `1 / ||r^-1||_F` is below the smallest singular value and `||r||_F` above the largest, so
/// when the first exceeds `eps_n` times the second (or `s0`), the SVD would keep every direction
/// too. Then `J = Q`, `P = R` stand for `Q U_R`, `S_R V_R^T`: the rotation `U_R` changes no
/// span, and `Z`'s SVD absorbs it (`[U, Q U_R] U_Z' = [U, Q] U_Z`). That SVD of a tau x tau
/// `R` was half of a rank-10 update at tau = 100 (Table 1's cases 2-4), where numpy's
/// reference takes one SVD, of `Z`; the triangular inverse costs tau^3 / 3 flops, a tenth of
/// it or less.
fn surely_full_rank(r: MatRef<'_, f64>, eps_n: f64, s0: f64) -> bool {
    let tau = r.nrows();
    if r.ncols() != tau || (0..tau).any(|i| !(r[(i, i)] != 0.0)) {
        return false;
    }
    let mut inv = Mat::<f64>::identity(tau, tau);
    faer::linalg::triangular_solve::solve_upper_triangular_in_place(r, inv.as_mut(), faer::Par::Seq);
    let (norm, inv_norm) = (r.norm_l2(), inv.norm_l2());
    inv_norm.is_finite() && 1.0 / inv_norm > eps_n * s0.max(norm)
}

/// [`new_directions`]' answer: `J = Q U_k` (N x k, not made; `U_k` `None` for the identity)
/// and `P` (k x tau).
struct NewDirections {
    q: Mat<f64>,
    u_k: Option<Mat<f64>>,
    p: Mat<f64>,
}

impl NewDirections {
    /// None (when `U` already spans R^N).
    fn none(n: usize, tau: usize) -> Self {
        Self {
            q: Mat::zeros(n, 0),
            u_k: None,
            p: Mat::zeros(0, tau),
        }
    }

    fn k(&self) -> usize {
        self.p.nrows()
    }
}

/// [`GeneralDmd::ahead`]'s answer: the new `U` and `S`, and the right singular vectors `W'`
/// of `Z` (r + tau rows) that carry `YW` over.
#[derive(Debug, Clone)]
pub(super) struct Ahead {
    u: Mat<f64>,
    s: Vec<f64>,
    w: Mat<f64>,
}

impl Dmd for GeneralDmd {
    fn method(&self) -> Method {
        Method::General
    }

    fn update(&mut self, x_new: MatRef<'_, f64>, y_new: MatRef<'_, f64>) -> Result<(), DmdError> {
        check_pairs(x_new, y_new, Some(self.dim))?;
        let ahead = self.ahead(x_new)?;
        self.finish(ahead, x_new, y_new)
    }

    fn prepare(&self, x_new: MatRef<'_, f64>) -> Option<Prepared> {
        check_shapes(x_new, x_new, Some(self.dim)).ok()?;
        check_finite(x_new).ok()?;
        let ahead = self.ahead(x_new).ok()?;
        Some(Prepared {
            x: x_new.to_owned(),
            updates: self.updates,
            ahead,
        })
    }

    fn update_prepared(
        &mut self,
        prepared: Option<Prepared>,
        x_new: MatRef<'_, f64>,
        y_new: MatRef<'_, f64>,
    ) -> Result<(), DmdError> {
        match prepared {
            // `x_new` is the prepared one, checked when it was prepared: `y_new` is left.
            Some(p) if p.updates == self.updates && p.x.as_ref() == x_new => {
                check_shapes(x_new, y_new, Some(self.dim))?;
                check_finite(y_new)?;
                self.finish(p.ahead, x_new, y_new)
            }
            _ => self.update(x_new, y_new),
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dmd::Debias;

    fn snapshots(n: usize, m: usize, phase: f64) -> Mat<f64> {
        Mat::from_fn(n, m, |i, j| {
            (i as f64 * 0.37 + j as f64 * phase).sin() + 0.1 * ((i * (j + 1)) as f64 * 0.01).cos()
        })
    }

    fn same(a: &GeneralDmd, b: &GeneralDmd) -> bool {
        a.u == b.u && a.s == b.s && a.yw == b.yw && (a.count, a.updates) == (b.count, b.updates)
    }

    /// An update made with what `prepare` made ahead is the update made whole, to the bit; what
    /// was prepared for other snapshots, or before the model last changed, is not taken; and
    /// snapshots the update would refuse get nothing prepared.
    #[test]
    fn a_prepared_update_is_the_whole_update_to_the_bit() {
        let z = snapshots(300, 12, 0.3);
        let model = GeneralDmd::init(z.subcols(0, 8), z.subcols(1, 8), RankPolicy::Fixed(4), Debias::None).unwrap();
        let (x, y) = (z.subcols(8, 3), z.subcols(9, 3));
        let mut whole = model.clone();
        whole.update(x, y).unwrap();

        let mut ahead = model.clone();
        let prepared = ahead.prepare(x);
        assert!(prepared.is_some());
        ahead.update_prepared(prepared, x, y).unwrap();
        assert!(same(&ahead, &whole));

        let mut other = model.clone();
        let prepared = other.prepare(snapshots(300, 3, 0.7).as_ref());
        other.update_prepared(prepared, x, y).unwrap();
        assert!(same(&other, &whole), "prepared for other snapshots, and taken");

        let mut stale = model.clone();
        let prepared = stale.prepare(x);
        stale.update(x, y).unwrap();
        stale.update_prepared(prepared, x, y).unwrap();
        let mut twice = whole.clone();
        twice.update(x, y).unwrap();
        assert!(same(&stale, &twice), "prepared before the model changed, and taken");

        let mut bad = x.to_owned();
        bad[(3, 1)] = f64::NAN;
        assert!(model.prepare(bad.as_ref()).is_none());
    }
}
