//! Gappy reconstruction (paper eq. gappy-pod): the full field from measurements at an index set
//! `L`, `x^ = Phi (C_L Phi)^+ x_L`, with the per-cell error variance from the error covariance
//! `K = sigma^2 [(C_L Phi)^T (C_L Phi)]^-1` propagated to the grid: `var_i = phi_i K phi_i^T`.

use super::SensingError;
use faer::linalg::solvers::SolveLstsq;
use faer::{Mat, MatRef};

/// A full-field estimate and its per-cell error variance.
#[derive(Debug, Clone)]
pub struct GappyEstimate {
    pub field: Vec<f64>,
    pub variance: Vec<f64>,
    /// Mode coefficients `a = (C_L Phi)^+ x_L`.
    pub coefficients: Vec<f64>,
}

/// Reconstruct from `values` measured at the cells `indices` of a basis `phi` (N x r, real;
/// see [`super::real_basis`] for DMD modes), with measurement noise variance `noise_var`.
/// Errors when the measured rows cannot determine the `r` coefficients.
pub fn reconstruct(
    phi: MatRef<'_, f64>,
    indices: &[usize],
    values: &[f64],
    noise_var: f64,
) -> Result<GappyEstimate, SensingError> {
    let (n, r) = (phi.nrows(), phi.ncols());
    if indices.len() != values.len() {
        return Err(SensingError::Input(format!(
            "{} indices but {} values",
            indices.len(),
            values.len()
        )));
    }
    if let Some(&i) = indices.iter().find(|&&i| i >= n) {
        return Err(SensingError::Input(format!("cell index {i} outside the {n}-cell grid")));
    }
    if let Some(v) = values.iter().find(|v| !v.is_finite()) {
        return Err(SensingError::Input(format!("non-finite measurement {v}")));
    }
    if !(noise_var.is_finite() && noise_var >= 0.0) {
        return Err(SensingError::Input(format!(
            "noise variance must be finite and >= 0, got {noise_var}"
        )));
    }
    let mut sorted = indices.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    let a = Mat::from_fn(indices.len(), r, |i, j| phi[(indices[i], j)]);
    let rank = if sorted.len() < r {
        sorted.len()
    } else {
        column_rank(a.as_ref())
    };
    if rank < r {
        return Err(SensingError::Underdetermined {
            rows: sorted.len(),
            rank,
            modes: r,
        });
    }
    let b = Mat::from_fn(values.len(), 1, |i, _| values[i]);
    let qr = a.qr();
    let coef = qr.solve_lstsq(&b);
    let coefficients: Vec<f64> = (0..r).map(|j| coef[(j, 0)]).collect();
    let field = (phi * &coef).col(0).iter().copied().collect();
    // (A^T A)^-1 = R^-1 R^-T, so var_i = sigma^2 |R^-T phi_i^T|^2: one triangular solve for all cells.
    let rt = qr.thin_R().transpose().to_owned();
    let mut z = phi.transpose().to_owned(); // r x N
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(rt.as_ref(), z.as_mut(), faer::Par::Seq);
    let variance = (0..n)
        .map(|i| noise_var * z.col(i).iter().map(|v| v * v).sum::<f64>())
        .collect();
    Ok(GappyEstimate {
        field,
        variance,
        coefficients,
    })
}

/// Condition number above which the measured rows are said not to determine the modes: the
/// estimate would amplify measurement noise by more than this.
pub const MAX_CONDITION: f64 = 1e10;

/// Column rank of a tall matrix: singular values above `s_0 / MAX_CONDITION`.
fn column_rank(a: MatRef<'_, f64>) -> usize {
    match a.singular_values() {
        Ok(s) => s
            .iter()
            .filter(|&&v| s.first().is_some_and(|&s0| s0 > 0.0 && v * MAX_CONDITION > s0))
            .count(),
        Err(_) => 0,
    }
}
