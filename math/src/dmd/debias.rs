//! Noise-robust eigenvalues. Sensor noise in `X` biases exact DMD's eigenvalues toward damping
//! (least squares attributes the noise energy in `X` to a smaller gain). Two standard cures,
//! both applied to the data projected on the model's POD basis `U_r` (`r x m` matrices):
//!
//! - **forward-backward** (Dawson et al. 2016): fit the forward operator `A_f` (X -> Y) and the
//!   backward one `A_b` (Y -> X); the noise bias of the two is opposite to first order, so
//!   `A = (A_f A_b^-1)^(1/2)`. Its eigenvectors are those of `A_f A_b^-1`, its eigenvalues the
//!   square roots nearer the forward operator's estimate along each eigenvector (the principal
//!   root would flip every eigenvalue with a negative real part); no matrix square root is
//!   formed.
//! - **total least squares** (Hemati et al. 2017): project `X` and `Y` onto the leading `r`
//!   right singular vectors of the stacked `[X; Y]`, which removes the noise subspace from both.
//!
//! Both return eigenvectors in the projected coordinates, so the modes are `U_r V` (projected
//! modes) rather than exact DMD modes.

use super::linalg::{eig, thin_svd};
use super::DmdError;
use faer::linalg::solvers::Solve;
use faer::{c64, Mat, MatRef};
use serde::{Deserialize, Serialize};

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
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = debias_name_error)]
pub enum Debias {
    /// Plain exact DMD.
    #[default]
    None,
    /// Forward-backward DMD.
    Fb,
    /// Total-least-squares DMD.
    Tls,
}

/// Eigenvalues and projected eigenvectors of the debiased `r x r` operator for projected data
/// `xt = U_r^T X`, `yt = U_r^T Y`.
pub fn debiased_eig(kind: Debias, xt: MatRef<'_, f64>, yt: MatRef<'_, f64>) -> Result<(Vec<c64>, Mat<c64>), DmdError> {
    let r = xt.nrows();
    if xt.ncols() < r {
        return Err(DmdError::Unsupported(format!(
            "debiasing needs at least as many snapshot pairs as the rank ({} < {r})",
            xt.ncols()
        )));
    }
    match kind {
        Debias::None => Err(DmdError::Unsupported(
            "debiased_eig called without a debias method".into(),
        )),
        Debias::Fb => {
            let af = least_squares_operator(xt, yt)?; // Y ~ A_f X
            let ab = least_squares_operator(yt, xt)?; // X ~ A_b Y
                                                      // M = A_f A_b^-1, via M^T = A_b^-T A_f^T (a solve, no inverse).
            let mt = ab.transpose().partial_piv_lu().solve(af.transpose());
            let m = mt.transpose().to_owned();
            let (mu, v) = eig(m.as_ref())?;
            // A square root has two signs; the right one is the one nearer the forward
            // operator's own estimate along the same eigenvector (its Rayleigh quotient). The
            // principal root alone turns every eigenvalue with a negative real part around.
            let afc = Mat::from_fn(r, r, |i, j| c64::new(af[(i, j)], 0.0));
            let lambda = mu
                .iter()
                .enumerate()
                .map(|(k, z)| {
                    let vk = v.col(k);
                    let forward = (vk.adjoint() * &afc * vk) / vk.norm_l2().powi(2).max(f64::MIN_POSITIVE);
                    let root = z.sqrt();
                    if (root - forward).norm() <= (-root - forward).norm() {
                        root
                    } else {
                        -root
                    }
                })
                .collect();
            Ok((lambda, v))
        }
        Debias::Tls => {
            let stacked = Mat::from_fn(
                2 * r,
                xt.ncols(),
                |i, j| if i < r { xt[(i, j)] } else { yt[(i - r, j)] },
            );
            let svd = thin_svd(stacked.as_ref())?;
            let vr = svd.v.subcols(0, r);
            let xb = xt * vr;
            let yb = yt * vr;
            // A = Yb Xb^-1  <=>  A^T = Xb^-T Yb^T
            let at = xb.transpose().partial_piv_lu().solve(yb.transpose());
            eig(at.transpose())
        }
    }
}

/// `B A^+` for `r x m` data of full row rank: the least-squares operator mapping the columns of
/// `a` to those of `b`, through the SVD of `a` (no normal equations, so no squared condition).
fn least_squares_operator(a: MatRef<'_, f64>, b: MatRef<'_, f64>) -> Result<Mat<f64>, DmdError> {
    let svd = thin_svd(a)?;
    let bv = super::linalg::div_cols(b * &svd.v, &svd.s);
    Ok(bv * svd.u.transpose())
}

/// A name that is not a [`Debias`]'s.
fn debias_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!("debias must be one of {}, got {got:?}", Debias::VARIANTS.join(", "))
}
