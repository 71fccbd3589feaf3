//! Exact DMD recomputed from all stored pairs (paper eqs. 2-8), the baseline the online methods
//! are measured against:
//! `X = U S W^T`, `A~ = U^T Y W S^-1`, `A~ V = V Lambda`, `Phi = Y W S^-1 V`.

use super::debias::{debiased_eig, Debias};
use super::linalg::{div_cols, eig, leading_svd, pod, scale_rows};
use super::{Dmd, DmdError, Factored, Method, ModeFactors, Modes, RankPolicy, SnapshotPairs};
use faer::{Mat, MatRef};

/// The projected pieces of one exact-DMD fit.
#[derive(Clone, Debug)]
pub(crate) struct ProjectedFit {
    /// POD basis `U_r` (N x r).
    pub u: Mat<f64>,
    /// Singular values `s_r`.
    pub s: Vec<f64>,
    /// `Y W S^-1` (N x r): exact modes are this times the eigenvectors of `A~`.
    pub yws: Mat<f64>,
}

impl ProjectedFit {
    pub fn rank(&self) -> usize {
        self.s.len()
    }

    /// `A~ = U^T (Y W S^-1)`.
    pub fn atilde(&self) -> Mat<f64> {
        atilde(self.u.as_ref(), self.yws.as_ref())
    }

    /// Eigenvalues and modes: exact DMD, or a debiased operator on the projected data.
    pub fn decompose(
        &self,
        debias: Debias,
        pairs: Option<&SnapshotPairs>,
        xt: Option<MatRef<'_, f64>>,
    ) -> Result<Modes, DmdError> {
        let (eigenvalues, v, on_u) = eigenvectors(self.u.as_ref(), self.yws.as_ref(), debias, pairs, xt)?;
        let real = if on_u { &self.u } else { &self.yws };
        let modes = super::linalg::to_complex(real.as_ref()) * v;
        Ok(Modes { eigenvalues, modes })
    }

    /// The eigenvalues of [`Self::decompose`] and its modes' factors, from `U` and
    /// `F = Y W S^-1`: an owned `F` is given up as the factor, a borrowed one copied only when
    /// it is the factor (the online method's `U` is not copied at all when the modes are
    /// `F C`). The modes themselves are [`ModeFactors::modes`].
    pub fn factored(
        u: &Mat<f64>,
        yws: std::borrow::Cow<'_, Mat<f64>>,
        debias: Debias,
        pairs: Option<&SnapshotPairs>,
        xt: Option<MatRef<'_, f64>>,
    ) -> Result<Factored, DmdError> {
        let (eigenvalues, v, on_u) = eigenvectors(u.as_ref(), yws.as_ref().as_ref(), debias, pairs, xt)?;
        let real = if on_u { u.clone() } else { yws.into_owned() };
        Ok(Factored {
            eigenvalues,
            factors: ModeFactors { real, coefficients: v },
        })
    }
}

/// `A~ = U^T F`, the operator projected on `U` (`F = Y W S^-1`).
fn atilde(u: MatRef<'_, f64>, yws: MatRef<'_, f64>) -> Mat<f64> {
    u.transpose() * yws
}

/// The eigenvalues and eigenvectors `C` of `A~ = U^T F` (`F = Y W S^-1`), or of a debiased
/// operator on the projected pairs, and whether the modes are then `U C` (debiased) rather
/// than `F C`.
fn eigenvectors(
    u: MatRef<'_, f64>,
    yws: MatRef<'_, f64>,
    debias: Debias,
    pairs: Option<&SnapshotPairs>,
    xt: Option<MatRef<'_, f64>>,
) -> Result<(Vec<faer::c64>, Mat<faer::c64>, bool), DmdError> {
    match debias {
        Debias::None => {
            let (eigenvalues, v) = eig(atilde(u, yws).as_ref())?;
            Ok((eigenvalues, v, false))
        }
        kind => {
            let pairs = pairs.ok_or_else(|| DmdError::Unsupported("debiasing without the stored pairs".into()))?;
            let computed;
            let xt = match xt {
                Some(xt) => xt,
                None => {
                    computed = u.transpose() * pairs.x();
                    computed.as_ref()
                }
            };
            let yt = u.transpose() * pairs.y();
            let (eigenvalues, v) = debiased_eig(kind, xt, yt.as_ref())?;
            Ok((eigenvalues, v, true))
        }
    }
}

/// Exact DMD of `(X, Y)` truncated by `rank`.
pub(crate) fn exact_fit(
    x: MatRef<'_, f64>,
    y: MatRef<'_, f64>,
    rank: RankPolicy,
) -> Result<(ProjectedFit, Mat<f64>), DmdError> {
    // A fixed rank of a matrix that is not tall (Table 1's square first fits) needs only the
    // leading triplets; tall data keeps the method of snapshots (`pod`), the bits it has had.
    let leading = match rank {
        RankPolicy::Fixed(r) if x.nrows() < 4 * x.ncols() => leading_svd(x, r)?,
        _ => None,
    };
    let svd = match leading {
        Some(svd) => svd,
        None => pod(x, |s| rank.select(s, x.nrows(), x.ncols()))?,
    };
    if svd.s.is_empty() {
        return Err(DmdError::ZeroRank);
    }
    let yws = div_cols(y * &svd.v, &svd.s);
    // U^T X = S W^T, kept for debiasing without another product with X.
    let xt = scale_rows(svd.v.transpose().to_owned(), &svd.s);
    Ok((
        ProjectedFit {
            u: svd.u,
            s: svd.s,
            yws,
        },
        xt,
    ))
}

/// Batch exact DMD: every update re-fits from all pairs.
#[derive(Clone, Debug)]
pub struct BatchDmd {
    pairs: SnapshotPairs,
    rank: RankPolicy,
    debias: Debias,
    fit: ProjectedFit,
    xt: Mat<f64>,
}

impl BatchDmd {
    pub fn fit(x: MatRef<'_, f64>, y: MatRef<'_, f64>, rank: RankPolicy, debias: Debias) -> Result<Self, DmdError> {
        let pairs = SnapshotPairs::new(x, y)?;
        let (fit, xt) = exact_fit(x, y, rank)?;
        Ok(Self {
            pairs,
            rank,
            debias,
            fit,
            xt,
        })
    }

    /// POD singular values of the current fit.
    pub fn singular_values(&self) -> &[f64] {
        &self.fit.s
    }

    /// The projected operator `A~` (r x r).
    pub fn atilde(&self) -> Mat<f64> {
        self.fit.atilde()
    }
}

impl Dmd for BatchDmd {
    fn method(&self) -> Method {
        Method::Batch
    }

    fn update(&mut self, x_new: MatRef<'_, f64>, y_new: MatRef<'_, f64>) -> Result<(), DmdError> {
        self.pairs.push(x_new, y_new)?;
        let (fit, xt) = exact_fit(self.pairs.x(), self.pairs.y(), self.rank)?;
        self.fit = fit;
        self.xt = xt;
        Ok(())
    }

    fn decompose(&self) -> Result<Modes, DmdError> {
        self.fit
            .decompose(self.debias, Some(&self.pairs), Some(self.xt.as_ref()))
    }

    fn factored(&self) -> Result<Option<Factored>, DmdError> {
        let yws = std::borrow::Cow::Borrowed(&self.fit.yws);
        ProjectedFit::factored(&self.fit.u, yws, self.debias, Some(&self.pairs), Some(self.xt.as_ref())).map(Some)
    }

    fn rank(&self) -> usize {
        self.fit.rank()
    }

    fn pairs(&self) -> usize {
        self.pairs.len()
    }

    fn dim(&self) -> usize {
        self.pairs.dim()
    }
}
