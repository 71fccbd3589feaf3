//! Thin wrappers over faer's decompositions with hetfleet's error type, so each DMD method
//! reads like the paper's equations.

use super::DmdError;
use faer::linalg::solvers::{DenseSolveCore, Solve, SolveLstsq};
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

pub fn thin_svd(a: MatRef<'_, f64>) -> Result<Svd, DmdError> {
    let svd = a.thin_svd().map_err(|e| DmdError::Numerical(format!("SVD did not converge: {e:?}")))?;
    let s = svd.S().column_vector().iter().copied().collect();
    Ok(Svd { u: svd.U().to_owned(), s, v: svd.V().to_owned() })
}

/// Eigenvalues and right eigenvectors of a real square matrix.
pub fn eig(a: MatRef<'_, f64>) -> Result<(Vec<c64>, Mat<c64>), DmdError> {
    let e = a.eigen().map_err(|e| DmdError::Numerical(format!("eigendecomposition did not converge: {e:?}")))?;
    let vals = e.S().column_vector().iter().copied().collect();
    Ok((vals, e.U().to_owned()))
}

/// Eigenvalues and right eigenvectors of a complex square matrix.
pub fn eig_complex(a: MatRef<'_, c64>) -> Result<(Vec<c64>, Mat<c64>), DmdError> {
    let e = a.eigen().map_err(|e| DmdError::Numerical(format!("eigendecomposition did not converge: {e:?}")))?;
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

/// Inverse of a small complex square matrix by LU (used once per decomposition on r x r).
pub fn inverse_complex(a: MatRef<'_, c64>) -> Mat<c64> {
    a.partial_piv_lu().inverse()
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

/// Frobenius norm of a real matrix.
pub fn fro(a: MatRef<'_, f64>) -> f64 {
    a.norm_l2()
}
