//! What a decomposition gives: modes `Phi`, eigenvalues `Lambda`, and, once fitted to a
//! snapshot, amplitudes `alpha` for reconstruction and forecast `x(t) = Phi Lambda^t alpha`.

use super::linalg::lstsq_complex;
use super::DmdError;
use faer::{c64, Mat};
use serde::Serialize;

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
            lstsq_complex(self.modes.as_ref(), &b)
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
