//! Field sources: synthetic fields with known dynamics (and, later, the plasma-cloud simulator
//! and `.npy` datasets). Every source yields [`FieldSeries`]: snapshots as the columns of an
//! `N x T` matrix on a grid, a step `dt` apart.

pub mod dataset;
pub mod error;
pub mod frames;
pub mod netcdf;
pub mod plasma;
pub mod synthetic;
pub mod truth;
pub mod units;

use faer::Mat;

/// Refuse a field too large to hold: more values than a `.npy` may carry
/// ([`crate::npy::MAX_VALUES`]) or, in bytes, more than this machine has available. Call before
/// allocating a field whose size comes from the command line or a file.
pub fn check_size(rows: usize, cols: usize, frames: usize) -> Result<(), String> {
    let values = rows.checked_mul(cols).and_then(|n| n.checked_mul(frames));
    let gib = |b: f64| b / (1u64 << 30) as f64;
    match values {
        Some(v) if v <= crate::npy::MAX_VALUES => {}
        _ => {
            return Err(format!(
                "{frames} frames of {rows} x {cols} is more than the {} values a field may hold (8 GiB)",
                crate::npy::MAX_VALUES
            ))
        }
    }
    let bytes = values.unwrap_or(usize::MAX) as f64 * 8.0;
    if let Some(avail) = available_memory() {
        if bytes > avail as f64 {
            return Err(format!(
                "{frames} frames of {rows} x {cols} need {:.1} GiB, and this machine has {:.1} GiB available",
                gib(bytes),
                gib(avail as f64)
            ));
        }
    }
    Ok(())
}

/// `MemAvailable` from /proc/meminfo (bytes), where there is one.
fn available_memory() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    line.split_whitespace().nth(1)?.parse::<u64>().ok().map(|kb| kb * 1024)
}

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
    /// `(rows, cols, frames)`.
    pub fn shape(&self) -> (usize, usize, usize) {
        (self.rows, self.cols, self.frames())
    }

    pub fn frames(&self) -> usize {
        self.snapshots.ncols()
    }

    pub fn dim(&self) -> usize {
        self.snapshots.nrows()
    }

    /// The cells with no value in any frame (NaN throughout: land in an ocean field), in order.
    /// They are off the model grid: nothing is placed, modelled or scored there.
    pub fn land(&self) -> Vec<u32> {
        (0..self.dim())
            .filter(|&i| (0..self.frames()).all(|k| self.snapshots[(i, k)].is_nan()))
            .map(|i| i as u32)
            .collect()
    }

    /// Every frame area-averaged onto a `rows x cols` raster of the same extent
    /// ([`crate::grid::area_average`]).
    pub fn area_averaged(&self, rows: usize, cols: usize) -> Result<FieldSeries, crate::grid::GridError> {
        let mut snapshots = Mat::zeros(rows * cols, self.frames());
        for k in 0..self.frames() {
            let col: Vec<f64> = self.snapshots.col(k).iter().copied().collect();
            for (i, v) in crate::grid::area_average(&col, self.rows, self.cols, rows, cols)?
                .into_iter()
                .enumerate()
            {
                snapshots[(i, k)] = v;
            }
        }
        Ok(FieldSeries {
            rows,
            cols,
            dt: self.dt,
            snapshots,
        })
    }
}
