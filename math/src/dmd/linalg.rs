//! Thin wrappers over faer's decompositions with hetfleet's error type, so each DMD method
//! reads like the paper's equations.

use super::DmdError;
use faer::linalg::solvers::{Solve, SolveLstsq};
use faer::{c64, Mat, MatRef, Side};

/// Thin SVD `A = U diag(s) V^T` with `s` non-increasing.
pub struct Svd {
    pub u: Mat<f64>,
    pub s: Vec<f64>,
    pub v: Mat<f64>,
}

impl Svd {
    /// Keep the leading `r` triplets.
    pub fn truncate(mut self, r: usize) -> Self {
        let (n, m) = (self.u.nrows(), self.v.nrows());
        self.u.truncate(n, r);
        self.v.truncate(m, r);
        self.s.truncate(r);
        self
    }
}

/// Smallest kept singular value, relative to the largest, for which [`pod`] may take the
/// method-of-snapshots path: there the error of `s_i` from the Gram matrix is about
/// `eps (s_0 / s_i)^2 <= 2e-8` relative.
pub const SNAPSHOT_METHOD_MIN_RATIO: f64 = 1e-4;

/// Truncated SVD `A ~ U_r diag(s_r) V_r^T` with `r = select(all singular values)`.
///
/// For tall data (`rows >= 4 cols`, the usual grid-by-snapshots case) it uses Sirovich's
/// method of snapshots: the eigendecomposition of the small Gram matrix `A^T A` gives `s` and
/// `V`, then `U_r = A V_r / s_r` is re-orthonormalised exactly (QR, then an `r x r` SVD). That is
/// 2-3x faster than a full thin SVD, and exact to ~1e-8 relative as long as every kept singular
/// value is at least [`SNAPSHOT_METHOD_MIN_RATIO`] of the largest; otherwise (or for wide data) it
/// falls back to the thin SVD.
pub fn pod(a: MatRef<'_, f64>, select: impl Fn(&[f64]) -> usize) -> Result<Svd, DmdError> {
    let (n, m) = (a.nrows(), a.ncols());
    if n >= 4 * m && m > 0 {
        let gram = a.transpose() * a;
        let evd = gram
            .self_adjoint_eigen(Side::Lower)
            .map_err(|e| DmdError::Numerical(format!("Gram eigendecomposition did not converge: {e:?}")))?;
        // Ascending eigenvalues -> descending singular values.
        let s_all: Vec<f64> = (0..m)
            .rev()
            .map(|i| evd.S().column_vector()[i].max(0.0).sqrt())
            .collect();
        let r = select(&s_all);
        if r > 0 && s_all[r - 1] >= SNAPSHOT_METHOD_MIN_RATIO * s_all[0] {
            let v = Mat::from_fn(m, r, |i, j| evd.U()[(i, m - 1 - j)]);
            let u = div_cols(a * &v, &s_all[..r]);
            // Exact re-orthonormalisation: U = Q R, R S = U_R S_R W_R^T.
            let qr = u.qr();
            let rs = scale_cols_by(qr.thin_R().to_owned(), &s_all[..r]);
            let small = thin_svd(rs.as_ref())?;
            return Ok(Svd {
                u: qr.compute_thin_Q() * &small.u,
                s: small.s,
                v: v * &small.v,
            });
        }
    }
    let svd = thin_svd(a)?;
    let r = select(&svd.s);
    Ok(svd.truncate(r))
}

/// `a * diag(d)`.
pub fn scale_cols_by(mut a: Mat<f64>, d: &[f64]) -> Mat<f64> {
    for (j, &dj) in d.iter().enumerate() {
        for x in a.col_mut(j).iter_mut() {
            *x *= dj;
        }
    }
    a
}

pub fn thin_svd(a: MatRef<'_, f64>) -> Result<Svd, DmdError> {
    let svd = a
        .thin_svd()
        .map_err(|e| DmdError::Numerical(format!("SVD did not converge: {e:?}")))?;
    let s = svd.S().column_vector().iter().copied().collect();
    Ok(Svd {
        u: svd.U().to_owned(),
        s,
        v: svd.V().to_owned(),
    })
}

/// The leading `r` singular triplets of `a` without its whole SVD, for a truncation to a rank
/// well below `a`'s size (the rank-r iSVD's `Z`, 110 x 110 at rank 10 in Table 1's cases 2-4,
/// where faer's whole SVD took 2.2 ms and LAPACK's 1.6): the eigenvectors of the Gram matrix
/// of `a`'s shorter side span the leading singular subspace, and an SVD of `a` projected on
/// them (Rayleigh-Ritz: `a^T U_1 = U_w S_w V_w^T`, so `u = U_1 V_w`, `s = S_w`, `v = U_w`) gives
/// triplets as accurate as the subspace. Its angle to the true one is about
/// `eps lambda_0 / (lambda_{r-1} - lambda_r)` for the Gram's eigenvalues `lambda`, so the path is
/// taken only when that gap is above [`LEADING_GAP`] of `lambda_0` (an angle below about
/// 1e-10) and the r-th singular value is above the Gram's rounding floor; `None` otherwise, and
/// for a matrix under [`LEADING_FROM`] on its shorter side or under 4 r, where the whole SVD
/// costs little.
pub fn leading_svd(a: MatRef<'_, f64>, r: usize) -> Result<Option<Svd>, DmdError> {
    let (m, n) = (a.nrows(), a.ncols());
    if m.min(n) < LEADING_FROM || m.min(n) < 4 * r || r == 0 {
        return Ok(None);
    }
    if m > n {
        return Ok(leading_svd(a.transpose(), r)?.map(|t| Svd { u: t.v, s: t.s, v: t.u }));
    }
    let gram = a * a.transpose();
    let evd = gram
        .self_adjoint_eigen(Side::Lower)
        .map_err(|e| DmdError::Numerical(format!("Gram eigendecomposition did not converge: {e:?}")))?;
    // Ascending eigenvalues: the leading r are the last.
    let lambda = |i: usize| evd.S().column_vector()[m - 1 - i];
    let floor = (m as f64) * f64::EPSILON * lambda(0);
    if !(lambda(0) > 0.0) || lambda(r - 1) - lambda(r) <= LEADING_GAP * lambda(0) || lambda(r - 1) <= 1e3 * floor {
        return Ok(None);
    }
    let u1 = Mat::from_fn(m, r, |i, j| evd.U()[(i, m - 1 - j)]);
    let w = thin_svd((a.transpose() * &u1).as_ref())?;
    Ok(Some(Svd {
        u: u1 * &w.v,
        s: w.s,
        v: w.u,
    }))
}

/// The shorter side from which [`leading_svd`] may replace a whole SVD.
pub const LEADING_FROM: usize = 64;
/// The smallest gap between the r-th and (r+1)-th Gram eigenvalues, relative to the largest,
/// at which [`leading_svd`] trusts the Gram's leading subspace.
pub const LEADING_GAP: f64 = 1e-6;

/// Eigenvalues and right eigenvectors of a real square matrix.
pub fn eig(a: MatRef<'_, f64>) -> Result<(Vec<c64>, Mat<c64>), DmdError> {
    let e = a
        .eigen()
        .map_err(|e| DmdError::Numerical(format!("eigendecomposition did not converge: {e:?}")))?;
    let vals = e.S().column_vector().iter().copied().collect();
    Ok((vals, e.U().to_owned()))
}

pub fn to_complex(a: MatRef<'_, f64>) -> Mat<c64> {
    Mat::from_fn(a.nrows(), a.ncols(), |i, j| c64::new(a[(i, j)], 0.0))
}

/// `a * diag(d)^-1`, i.e. each column divided by its entry of `d`.
pub fn div_cols(mut a: Mat<f64>, d: &[f64]) -> Mat<f64> {
    for (j, &dj) in d.iter().enumerate() {
        for x in a.col_mut(j).iter_mut() {
            *x /= dj;
        }
    }
    a
}

/// `diag(d) * a`, each row scaled.
pub fn scale_rows(mut a: Mat<f64>, d: &[f64]) -> Mat<f64> {
    for j in 0..a.ncols() {
        for (i, x) in a.col_mut(j).iter_mut().enumerate() {
            *x *= d[i];
        }
    }
    a
}

/// Least-squares solution of `a x = b` for complex `a` (tall or square) by Householder QR.
pub fn lstsq_complex(a: MatRef<'_, c64>, b: &[c64]) -> Vec<c64> {
    let rhs = Mat::from_fn(b.len(), 1, |i, _| b[i]);
    let x = a.qr().solve_lstsq(&rhs);
    (0..a.ncols()).map(|i| x[(i, 0)]).collect()
}

/// Solve `g x = b` for a symmetric positive definite `g` by Cholesky; falls back to LU with
/// partial pivoting when rounding has made `g` numerically indefinite.
pub fn solve_spd(g: MatRef<'_, f64>, b: MatRef<'_, f64>) -> Mat<f64> {
    match g.llt(Side::Lower) {
        Ok(llt) => llt.solve(b),
        Err(_) => g.partial_piv_lu().solve(b),
    }
}

/// `max |a^T a - I|`, how far the columns of `a` are from orthonormal.
pub fn orthogonality_error(a: MatRef<'_, f64>) -> f64 {
    let g = a.transpose() * a;
    let mut e: f64 = 0.0;
    for j in 0..g.ncols() {
        for i in 0..g.nrows() {
            let target = if i == j { 1.0 } else { 0.0 };
            e = e.max((g[(i, j)] - target).abs());
        }
    }
    e
}

/// `F = Q R` with orthonormal `Q` (N x r) and upper-triangular `R`: CholeskyQR twice (a Gram
/// matrix and a triangular solve each, all matrix products; the second pass takes the first's
/// loss of orthogonality, `eps cond(F)^2`, back to rounding), or Householder QR when `F` is too
/// ill-conditioned for Cholesky (its factor's diagonal spans more than 1e6) or rank-deficient.
pub fn orthonormal_factor(f: MatRef<'_, f64>) -> (Mat<f64>, Mat<f64>) {
    let twice = cholesky_qr(f.to_owned()).and_then(|(q1, r1)| cholesky_qr(q1).map(|(q, r2)| (q, r2 * r1)));
    twice.unwrap_or_else(|| {
        let qr = f.qr();
        (qr.compute_thin_Q(), qr.thin_R().to_owned())
    })
}

/// One CholeskyQR pass on `f`, in place: `R` the Cholesky factor of `F^T F`, `Q = F R^-1`;
/// `None` when the Gram matrix is too ill-conditioned for it ([`gram_cholesky`]).
fn cholesky_qr(mut q: Mat<f64>) -> Option<(Mat<f64>, Mat<f64>)> {
    let l = gram_cholesky(q.as_ref())?;
    right_solve_lower_transposed(l.as_ref(), q.as_mut());
    Some((q, l.transpose().to_owned()))
}

/// `F <- F L^-T` in place, each row of `F` solved as `L x = f^T`, a block of rows at a time
/// on every core: rows are independent, so each gets the bits one solve of all of them gives
/// (solved on `F`'s transposed view, no N x r transpose is copied: two strided copies of `F`
/// were once most of the factor's time).
fn right_solve_lower_transposed(l: MatRef<'_, f64>, f: faer::MatMut<'_, f64>) {
    use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
    use rayon::prelude::*;
    let rows = crate::par::block_rows(f.nrows(), l.nrows() * l.nrows());
    f.par_row_chunks_mut(rows)
        .for_each(|block| solve_lower_triangular_in_place(l, block.transpose_mut(), faer::Par::Seq));
}

/// The lower Cholesky factor `L` of the small Gram matrix `F^T F` (so `L^T` is the `R` of a QR
/// of `F`, 3-5x cheaper than one on a tall `F`); `None` when its diagonal spans more than 1e6
/// (condition above 1e12 of the Gram matrix), where the squared condition makes it inaccurate
/// and a Householder QR is the answer.
pub fn gram_cholesky(f: MatRef<'_, f64>) -> Option<Mat<f64>> {
    let gram = f.transpose() * f;
    let llt = gram.llt(faer::Side::Lower).ok()?;
    let l = llt.L();
    let (lo, hi) = (0..l.nrows())
        .map(|i| l[(i, i)].abs())
        .fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
    (lo > 1e-6 * hi).then(|| l.to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn randn(r: usize, c: usize, seed: u64) -> Mat<f64> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        Mat::from_fn(r, c, |_, _| StandardNormal.sample(&mut rng))
    }

    /// `U diag(s) V^T` with random orthonormal `U` (m x k) and `V` (n x k).
    fn with_singular_values(m: usize, n: usize, s: &[f64], seed: u64) -> Mat<f64> {
        let k = s.len();
        let u = randn(m, k, seed).qr().compute_thin_Q();
        let v = randn(n, k, seed + 1).qr().compute_thin_Q();
        scale_cols_by(u, s) * v.transpose()
    }

    /// A matrix of known singular values (1, 0.9, ..., then a gap, then a tail): the leading 10
    /// triplets from the Gram's subspace are the SVD's, values to 1e-13 relative (the Ritz values
    /// are exact to rounding once the subspace is: its angle here is eps / gap, about 1e-15) and
    /// `u s v^T` the best rank-10 approximation to 1e-12; wide and tall alike.
    #[test]
    fn the_leading_triplets_are_the_svds_where_the_gap_allows() {
        let s: Vec<f64> = (0..100)
            .map(|i| {
                if i < 10 {
                    1.0 - 0.05 * i as f64
                } else {
                    0.1 / (i as f64)
                }
            })
            .collect();
        for (m, n) in [(100, 110), (120, 100)] {
            let a = with_singular_values(m, n, &s, 5);
            let got = leading_svd(a.as_ref(), 10)
                .unwrap()
                .expect("a clear gap: the leading path");
            for (g, t) in got.s.iter().zip(&s) {
                assert!((g - t).abs() < 1e-13, "{m} x {n}: {g} against {t}");
            }
            let full = thin_svd(a.as_ref()).unwrap().truncate(10);
            let best = scale_cols_by(full.u, &full.s) * full.v.transpose();
            let ours = scale_cols_by(got.u.clone(), &got.s) * got.v.transpose();
            assert!(
                (&best - &ours).norm_max() < 1e-12,
                "{m} x {n}: rank-10 approximations differ"
            );
            assert!(orthogonality_error(got.u.as_ref()) < 1e-13 && orthogonality_error(got.v.as_ref()) < 1e-13);
        }
    }

    /// Where the 10th and 11th singular values are equal the leading subspace is not determined,
    /// and a small matrix costs little whole: both go to the whole SVD (`None`).
    #[test]
    fn the_leading_triplets_are_refused_without_a_gap_or_for_a_small_matrix() {
        let mut s: Vec<f64> = (0..80).map(|i| 1.0 / (1.0 + i as f64)).collect();
        s[10] = s[9];
        assert!(leading_svd(with_singular_values(80, 90, &s, 7).as_ref(), 10)
            .unwrap()
            .is_none());
        let small = with_singular_values(30, 30, &s[..30], 8);
        assert!(leading_svd(small.as_ref(), 5).unwrap().is_none());
    }

    #[test]
    fn method_of_snapshots_agrees_with_the_thin_svd_on_tall_data() {
        // Rank-8 signal with decaying scales plus small noise, 2000 x 60.
        let scales = Mat::from_fn(8, 8, |i, j| if i == j { 10f64.powi(-(i as i32) / 2) } else { 0.0 });
        let a = &randn(2000, 8, 1) * &scales * &randn(8, 60, 2) + randn(2000, 60, 3) * faer::Scale(1e-6);
        let pod = pod(a.as_ref(), |_| 8).unwrap();
        let svd = thin_svd(a.as_ref()).unwrap().truncate(8);
        for (p, s) in pod.s.iter().zip(&svd.s) {
            assert!((p - s).abs() < 1e-9 * s, "{p} vs {s}");
        }
        assert!(orthogonality_error(pod.u.as_ref()) < 1e-13);
        assert!(orthogonality_error(pod.v.as_ref()) < 1e-12);
        // Same subspaces: the singular values of U_pod^T U_svd are all 1.
        let overlap = thin_svd((pod.u.transpose() * &svd.u).as_ref()).unwrap();
        for c in overlap.s {
            assert!((c - 1.0).abs() < 1e-9, "principal cosine {c}");
        }
        // Reconstruction: U S V^T equals the rank-8 truncation.
        let rec = super::scale_cols_by(pod.u.clone(), &pod.s) * pod.v.transpose();
        let rec2 = super::scale_cols_by(svd.u.clone(), &svd.s) * svd.v.transpose();
        assert!((&rec - &rec2).norm_l2() < 1e-9 * rec2.norm_l2());
    }

    #[test]
    fn method_of_snapshots_falls_back_when_a_kept_value_is_too_small() {
        // Exactly rank 3 asked for rank 5: the 4th and 5th values are ~0, so the SVD is used and
        // reports them accurately (tiny), where the Gram matrix could only give ~1e-8 s0.
        let a = &randn(500, 3, 4) * &randn(3, 40, 5);
        let pod = pod(a.as_ref(), |_| 5).unwrap();
        assert_eq!(pod.s.len(), 5);
        assert!(pod.s[3] < 1e-12 * pod.s[0], "{:?}", pod.s);
    }

    /// The row blocks' solves give every row the bits of one solve of the whole matrix.
    #[test]
    fn a_triangular_solve_by_row_blocks_is_the_whole_solve() {
        for n in [7, crate::par::MIN_WORK / 50 + 13] {
            let f = randn(n, 10, 6);
            let l = randn(10, 10, 7);
            let l = Mat::from_fn(10, 10, |i, j| match i.cmp(&j) {
                std::cmp::Ordering::Less => 0.0,
                std::cmp::Ordering::Equal => 2.0 + l[(i, j)].abs(),
                std::cmp::Ordering::Greater => l[(i, j)],
            });
            let mut want = f.clone();
            faer::linalg::triangular_solve::solve_lower_triangular_in_place(
                l.as_ref(),
                want.as_mut().transpose_mut(),
                faer::Par::Seq,
            );
            let mut got = f.clone();
            right_solve_lower_transposed(l.as_ref(), got.as_mut());
            assert!(got == want, "{n} rows");
        }
    }
}
