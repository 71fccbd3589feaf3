//! Field sources: synthetic fields with known dynamics (and, later, the plasma-cloud simulator
//! and `.npy` datasets). Every source yields [`FieldSeries`]: snapshots as the columns of an
//! `N x T` matrix on a grid, a step `dt` apart.

pub mod dataset;
pub mod plasma;
pub mod synthetic;
pub mod truth;

use faer::Mat;

/// A field sampled on a `rows x cols` grid at `T` times: column `t` is the row-major snapshot.
#[derive(Clone, Debug)]
pub struct FieldSeries {
    pub rows: usize,
    pub cols: usize,
    /// Seconds between consecutive snapshots.
    pub dt: f64,
    pub snapshots: Mat<f64>,
}

impl FieldSeries {
    pub fn frames(&self) -> usize {
        self.snapshots.ncols()
    }

    pub fn dim(&self) -> usize {
        self.snapshots.nrows()
    }

    /// Every frame area-averaged onto a `rows x cols` raster of the same extent
    /// ([`crate::grid::area_average`]).
    pub fn area_averaged(&self, rows: usize, cols: usize) -> Result<FieldSeries, crate::grid::GridError> {
        let mut snapshots = Mat::zeros(rows * cols, self.frames());
        for k in 0..self.frames() {
            let col: Vec<f64> = self.snapshots.col(k).iter().copied().collect();
            for (i, v) in crate::grid::area_average(&col, self.rows, self.cols, rows, cols)?.into_iter().enumerate() {
                snapshots[(i, k)] = v;
            }
        }
        Ok(FieldSeries { rows, cols, dt: self.dt, snapshots })
    }
}
