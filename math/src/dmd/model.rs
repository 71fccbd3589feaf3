//! What a decomposition gives: modes `Phi`, eigenvalues `Lambda`, and, once fitted to a
//! snapshot, amplitudes `alpha` for reconstruction and forecast `x(t) = Phi Lambda^t alpha`.

use super::linalg::lstsq_complex;
use super::DmdError;
use faer::{c64, Mat};
use serde::Serialize;

/// Modes as a real N x r matrix times complex r x r coefficients, `Phi = F C`, as exact DMD
/// makes them (`F = Y W S^-1` and `C` the eigenvectors of `A~`; debiased: `F = U`). Past one
/// thin factorisation of `F`, what is asked of the modes' span is r x r work
/// ([`crate::sensing::real_basis_factored`]).
#[derive(Debug, Clone)]
pub struct ModeFactors {
    pub real: Mat<f64>,
    pub coefficients: Mat<c64>,
}

/// A decomposition whose modes are left as their factors ([`super::Dmd::factored`]).
#[derive(Debug, Clone)]
pub struct Factored {
    pub eigenvalues: Vec<c64>,
    pub factors: ModeFactors,
}

impl ModeFactors {
    /// The modes `Phi = F C` (N x r complex), a block of rows at a time on every core.
    pub fn modes(&self) -> Mat<c64> {
        crate::par::real_times_complex(self.real.as_ref(), self.coefficients.as_ref())
    }

    /// `Phi = F C = Q (R C)` with `F = Q R`, Q orthonormal.
    pub fn orthogonal(&self) -> OrthogonalModes {
        let (q, r) = super::linalg::orthonormal_factor(self.real.as_ref());
        let m = super::linalg::to_complex(r.as_ref()) * &self.coefficients;
        OrthogonalModes { q, m }
    }
}

/// Modes as `Phi = Q M`: `Q` (N x r) orthonormal, `M` (r x r) complex.
#[derive(Debug, Clone)]
pub struct OrthogonalModes {
    pub q: Mat<f64>,
    pub m: Mat<c64>,
}

/// Eigenvalues (discrete time, one step) and modes (columns, `N x r`) of a DMD operator.
#[derive(Debug, Clone)]
pub struct Modes {
    pub eigenvalues: Vec<c64>,
    pub modes: Mat<c64>,
}

impl Modes {
    /// Continuous-time eigenvalues `ln(lambda) / dt` (principal branch).
    pub fn continuous_eigenvalues(&self, dt: f64) -> Vec<c64> {
        self.eigenvalues.iter().map(|l| l.ln() / dt).collect()
    }

    /// Index of the eigenvalue of largest modulus (the slowest-decaying / fastest-growing mode).
    pub fn dominant(&self) -> Option<usize> {
        (0..self.eigenvalues.len()).max_by(|&a, &b| self.eigenvalues[a].norm().total_cmp(&self.eigenvalues[b].norm()))
    }

    /// Fit amplitudes by least squares so that `Phi alpha ~= x_ref`, making step `t` of the model
    /// the snapshot `t` steps after `x_ref` (PyDMD fits to the first snapshot; an online model
    /// fits to its newest one to forecast forward).
    pub fn model(self, x_ref: &[f64], dt: f64) -> Result<DmdModel, DmdError> {
        self.model_with(x_ref, dt, |modes, b| lstsq_complex(modes.modes.as_ref(), b))
    }

    /// [`Self::model`] with the modes as `Q M` (`self.modes` must equal `Q M`): the least
    /// squares `min |Q M alpha - x|` is `min |M alpha - Q^T x|` (the part of `x` off Q's span
    /// is the same residual for every `alpha`), an r x r problem.
    pub fn model_on(self, factored: &OrthogonalModes, x_ref: &[f64], dt: f64) -> Result<DmdModel, DmdError> {
        if factored.q.nrows() != self.modes.nrows() || factored.m.ncols() != self.modes.ncols() {
            return Err(DmdError::Shape("the factored modes are not these modes' shape".into()));
        }
        self.model_with(x_ref, dt, |_, b| {
            let x = Mat::from_fn(b.len(), 1, |i, _| b[i].re);
            let qtx = factored.q.transpose() * x;
            let rhs: Vec<c64> = (0..qtx.nrows()).map(|i| c64::new(qtx[(i, 0)], 0.0)).collect();
            lstsq_complex(factored.m.as_ref(), &rhs)
        })
    }

    fn model_with(
        self,
        x_ref: &[f64],
        dt: f64,
        solve: impl FnOnce(&Self, &[c64]) -> Vec<c64>,
    ) -> Result<DmdModel, DmdError> {
        if x_ref.len() != self.modes.nrows() {
            return Err(DmdError::Shape(format!(
                "reference snapshot has {} values, the modes {}",
                x_ref.len(),
                self.modes.nrows()
            )));
        }
        if let Some(i) = x_ref.iter().position(|v| !v.is_finite()) {
            return Err(DmdError::NonFinite { row: i, col: 0 });
        }
        let b: Vec<c64> = x_ref.iter().map(|&v| c64::new(v, 0.0)).collect();
        let amplitudes = if self.modes.ncols() == 0 {
            vec![]
        } else {
            solve(&self, &b)
        };
        Ok(DmdModel {
            modes: self,
            amplitudes,
            dt,
        })
    }

    /// Eigenvalues sorted by descending modulus, then descending imaginary part (the order of
    /// the peer references), as `[re, im]` pairs.
    pub fn sorted_eigenvalues(&self) -> Vec<[f64; 2]> {
        sort_eigenvalues(&self.eigenvalues)
    }
}

/// Sort by descending modulus (rounded to 12 decimals so conjugate pairs stay together), then
/// descending imaginary part.
pub fn sort_eigenvalues(l: &[c64]) -> Vec<[f64; 2]> {
    let mut v: Vec<c64> = l.to_vec();
    let key = |z: &c64| (z.norm() * 1e12).round();
    v.sort_by(|a, b| key(b).total_cmp(&key(a)).then(b.im.total_cmp(&a.im)));
    v.iter().map(|z| [z.re, z.im]).collect()
}

/// A DMD model that can reconstruct and forecast: `x(t) = Re(Phi Lambda^t alpha)`.
#[derive(Debug, Clone)]
pub struct DmdModel {
    pub modes: Modes,
    pub amplitudes: Vec<c64>,
    /// Time step between snapshots (for continuous-time eigenvalues).
    pub dt: f64,
}

impl DmdModel {
    /// The state `t` steps after the reference snapshot (negative `t` goes back).
    pub fn predict(&self, t: f64) -> Vec<f64> {
        let n = self.modes.modes.nrows();
        let mut out = vec![0.0; n];
        for (j, (&lam, &a)) in self.modes.eigenvalues.iter().zip(&self.amplitudes).enumerate() {
            let c = if t == 0.0 { a } else { lam.powf(t) * a };
            let col = self.modes.modes.col(j);
            for (o, phi) in out.iter_mut().zip(col.iter()) {
                *o += (phi * c).re;
            }
        }
        out
    }

    /// [`Self::predict`] at `cells` only (in their order), with the same arithmetic per cell
    /// (the same bits): a test that looks at a few hundred cells need not forecast them all.
    pub fn predict_at(&self, t: f64, cells: &[usize]) -> Vec<f64> {
        let coefficients: Vec<c64> = self
            .modes
            .eigenvalues
            .iter()
            .zip(&self.amplitudes)
            .map(|(&lam, &a)| if t == 0.0 { a } else { lam.powf(t) * a })
            .collect();
        let modes = &self.modes.modes;
        cells
            .iter()
            .map(|&c| {
                coefficients
                    .iter()
                    .enumerate()
                    .fold(0.0, |o, (j, &k)| o + (modes[(c, j)] * k).re)
            })
            .collect()
    }

    pub fn continuous_eigenvalues(&self) -> Vec<c64> {
        self.modes.continuous_eigenvalues(self.dt)
    }

    pub fn summary(&self) -> ModelSummary {
        let ct = self.continuous_eigenvalues();
        let mut idx: Vec<usize> = (0..ct.len()).collect();
        idx.sort_by(|&a, &b| {
            self.modes.eigenvalues[b]
                .norm()
                .total_cmp(&self.modes.eigenvalues[a].norm())
        });
        ModelSummary {
            rank: self.modes.eigenvalues.len(),
            dt: self.dt,
            eigenvalues: idx
                .iter()
                .map(|&i| [self.modes.eigenvalues[i].re, self.modes.eigenvalues[i].im])
                .collect(),
            continuous_eigenvalues: idx.iter().map(|&i| [ct[i].re, ct[i].im]).collect(),
            amplitude_moduli: idx.iter().map(|&i| self.amplitudes[i].norm()).collect(),
        }
    }
}

/// The numbers of a model a person reads: eigenvalues by descending modulus.
#[derive(Debug, Clone, Serialize)]
pub struct ModelSummary {
    pub rank: usize,
    pub dt: f64,
    pub eigenvalues: Vec<[f64; 2]>,
    pub continuous_eigenvalues: Vec<[f64; 2]>,
    pub amplitude_moduli: Vec<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The forecast at a few cells is the whole forecast's value at each, to the bit (the
    /// filter's calibration reads the boats' cells alone and must see what it saw before).
    #[test]
    fn the_forecast_at_cells_is_the_whole_forecasts_there() {
        let (n, r) = (257, 4);
        let modes = Mat::from_fn(n, r, |i, j| {
            c64::new(((i * 7 + j) as f64).sin(), ((i + 3 * j) as f64).cos() * 0.3)
        });
        let eigenvalues = vec![
            c64::new(0.9, 0.2),
            c64::new(0.9, -0.2),
            c64::new(1.01, 0.0),
            c64::new(-0.5, 0.1),
        ];
        let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.05).sin()).collect();
        let model = Modes { eigenvalues, modes }.model(&x, 1.0).unwrap();
        let cells = [200, 3, 0, 256, 3, 99];
        for t in [0.0, 1.0, 2.5, -1.0] {
            let whole = model.predict(t);
            let want: Vec<f64> = cells.iter().map(|&c| whole[c]).collect();
            assert_eq!(model.predict_at(t, &cells), want, "t = {t}");
        }
    }

    /// The modes made from a decomposition's factors are its modes (the refit makes them beside
    /// the basis, from the factors alone), for the batch and the online general method, and
    /// with debiased operators (modes on `U`). An exact rank-4 system (a damped rotation and
    /// two decays) seen through 40 cells. Tolerance: the two products sum the same r = 4 terms
    /// per entry in another order, so they differ by a few ulps of the largest term, far below
    /// 1e-12 of the largest mode.
    #[test]
    fn the_modes_of_the_factors_are_the_decompositions() {
        use crate::dmd::{Debias, DmdConfig, Method, RankPolicy};
        let (n, steps) = (40, 30);
        let a = Mat::from_fn(4, 4, |i, j| match (i, j) {
            (0, 0) | (1, 1) => 0.95 * 0.3f64.cos(),
            (0, 1) => -0.95 * 0.3f64.sin(),
            (1, 0) => 0.95 * 0.3f64.sin(),
            (2, 2) => 0.8,
            (3, 3) => 0.5,
            _ => 0.0,
        });
        let lift = Mat::from_fn(n, 4, |i, j| ((i * (j + 2)) as f64 * 0.37).sin() + 0.1 * j as f64);
        let mut z = Mat::from_fn(4, steps, |i, j| if j == 0 { 1.0 + i as f64 } else { 0.0 });
        for k in 1..steps {
            let next = &a * z.col(k - 1);
            z.col_mut(k).copy_from(&next);
        }
        let x = &lift * &z;
        for (method, debias) in [
            (Method::Batch, Debias::None),
            (Method::General, Debias::None),
            (Method::Batch, Debias::Tls),
            (Method::General, Debias::Fb),
        ] {
            let cfg = DmdConfig {
                method,
                rank: RankPolicy::Fixed(4),
                debias,
                ..DmdConfig::default()
            };
            let model = cfg.init(x.subcols(0, 20), x.subcols(1, 20)).unwrap();
            let factored = model.factored().unwrap().expect("exact DMD's factors");
            let whole = model.decompose().unwrap();
            assert_eq!(factored.eigenvalues, whole.eigenvalues, "{method:?} {debias:?}");
            let made = factored.factors.modes();
            let entries = (0..n).flat_map(|i| (0..4).map(move |j| (i, j)));
            let largest = entries
                .clone()
                .map(|(i, j)| whole.modes[(i, j)].norm())
                .fold(0.0, f64::max);
            for (i, j) in entries {
                let d = (made[(i, j)] - whole.modes[(i, j)]).norm();
                assert!(d <= 1e-12 * largest, "{method:?} {debias:?} ({i}, {j}): {d:e}");
            }
        }
    }
}
