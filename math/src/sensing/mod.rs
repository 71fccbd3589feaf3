//! Where to sense next, from the model's spatial modes (paper Sect. 4.2.1): gappy
//! reconstruction from sparse measurements, greedy pivoted-QR point selection (Alg. 1), and
//! block pivoted QR over sensing disks of radius k (Alg. 2) with a D-optimal alternative.
//!
//! Everything works on a real basis `Phi` (N x r) and never forms the N x N matrix
//! `Phi Phi^T`: its column `p` is `Q (R phi_p^T)` for `Phi = Q R`, so its norms and its
//! deflations live in r dimensions. DMD modes are complex; [`real_basis`] turns them into an
//! orthonormal real basis of the same real span (`[Re Phi, Im Phi]`).

pub mod assign;
pub mod coverage;
pub mod gappy;
pub mod horizon;
pub mod qr;

use crate::dmd::linalg::thin_svd;
use crate::dmd::OrthogonalModes;
use faer::{Mat, MatRef};
use thiserror::Error;

/// Where the boats' disks may go on the grid (one flag per cell in each; empty: none).
///
/// - `outside`: cells no disk may touch: beyond the site's fence, where a boat may not drive.
/// - `dry`: cells with no water (land, for an ocean field). Disks go in open water (touching
///   no land) while any is left; then a disk may reach the coast: centred on water, it holds
///   only its wet cells (a boat measures the water around it up to the coast, as the sensor
///   model clips it, `mission::vehicle::sense_cells`), and two disks may reach one stretch of
///   coast. So a strait or an archipelago narrower than a disk still gets its boats (disks
///   kept off every land cell left such a field with none), and a field with open water
///   places as it did. Open water first because coastal disks were measured to cost the fused
///   map on the Pacific SST (docs/guide/fields.md, "Water narrower than a disk").
#[derive(Debug, Clone, Copy, Default)]
pub struct Room<'a> {
    pub outside: &'a [bool],
    pub dry: &'a [bool],
}

impl<'a> Room<'a> {
    /// No fence and no land: every disk anywhere on the grid.
    pub const OPEN: Room<'static> = Room { outside: &[], dry: &[] };

    /// Whether `cell` is dry.
    pub fn is_dry(&self, cell: usize) -> bool {
        self.dry.get(cell).copied().unwrap_or(false)
    }

    /// Whether any cell is dry (a second, coastal pass can follow the open-water one).
    pub fn has_land(&self) -> bool {
        self.dry.iter().any(|&d| d)
    }

    /// Whether `cell` is beyond the fence.
    pub fn is_outside(&self, cell: usize) -> bool {
        self.outside.get(cell).copied().unwrap_or(false)
    }

    /// The wet cells of `cells` (a disk as the grid draws it).
    pub fn wet(&self, cells: Vec<usize>) -> Vec<usize> {
        if self.dry.is_empty() {
            return cells;
        }
        cells.into_iter().filter(|&c| !self.is_dry(c)).collect()
    }

    /// Both flag lists fit `grid` (or are empty).
    pub fn check(&self, grid: &crate::grid::Grid) -> Result<(), SensingError> {
        for (what, flags) in [("fence", self.outside), ("land", self.dry)] {
            if !(flags.is_empty() || flags.len() == grid.len()) {
                return Err(SensingError::Input(format!(
                    "{} {what} flags for {} cells",
                    flags.len(),
                    grid.len()
                )));
            }
        }
        Ok(())
    }
}

#[derive(Debug, Error)]
pub enum SensingError {
    #[error(
        "{rows} measured cells of rank {rank} cannot determine {modes} modes; measure more (or more varied) cells \
        or lower the rank"
    )]
    Underdetermined { rows: usize, rank: usize, modes: usize },
    #[error("{0}")]
    Input(String),
    #[error("numerical failure: {0}")]
    Numerical(String),
}

/// An orthonormal real basis (N x q) of the real span of complex modes: the left singular
/// vectors of `[Re Phi, Im Phi]` above the numerical-rank tolerance (a conjugate pair gives two
/// directions, a real mode one).
pub fn real_basis(modes: MatRef<'_, faer::c64>) -> Result<Mat<f64>, SensingError> {
    let (n, r) = (modes.nrows(), modes.ncols());
    let stacked = Mat::from_fn(
        n,
        2 * r,
        |i, j| if j < r { modes[(i, j)].re } else { modes[(i, j - r)].im },
    );
    let svd = thin_svd(stacked.as_ref()).map_err(|e| SensingError::Numerical(e.to_string()))?;
    let q = crate::dmd::numerical_rank(&svd.s, n, 2 * r);
    Ok(svd.truncate(q).u)
}

/// [`real_basis`] of modes given as `Phi = Q M` ([`OrthogonalModes`], Q orthonormal N x r, M
/// r x r): `[Re Phi, Im Phi] = Q [Re M, Im M]`, so its singular values are those of the r x 2r
/// `[Re M, Im M]` and its left singular vectors `Q` times that matrix's. The same span,
/// numerical rank and tolerance as [`real_basis`], for one N x r product instead of an N x 2r
/// SVD (at 192 x 384, 57 ms an epoch before).
pub fn real_basis_factored(modes: &OrthogonalModes) -> Result<Mat<f64>, SensingError> {
    Ok(crate::par::product(
        modes.q.as_ref(),
        real_basis_coordinates(modes)?.as_ref(),
    ))
}

/// The coordinates `U` (r x q, orthonormal columns) of [`real_basis_factored`]'s basis in `Q`:
/// the basis is `Q U`, so what is asked of the basis and the modes together (their Gram
/// matrices, `Phi^H B = M^H U`) is r x r work.
pub fn real_basis_coordinates(modes: &OrthogonalModes) -> Result<Mat<f64>, SensingError> {
    let (n, r) = (modes.q.nrows(), modes.m.ncols());
    let m = &modes.m;
    let stacked = Mat::from_fn(
        m.nrows(),
        2 * r,
        |i, j| if j < r { m[(i, j)].re } else { m[(i, j - r)].im },
    );
    let svd = thin_svd(stacked.as_ref()).map_err(|e| SensingError::Numerical(e.to_string()))?;
    let keep = crate::dmd::numerical_rank(&svd.s, n, 2 * r);
    Ok(svd.u.subcols(0, keep).to_owned())
}
