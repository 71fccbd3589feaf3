//! A growable, column-major store of snapshot pairs `(x_j, y_j)` with `y_j = A x_j`.
//!
//! The batch method keeps every pair (it re-fits from them at every update); the general method
//! only when its debiasing needs them (it carries `Y W` along, the paper's eq. 12).

use super::DmdError;
use faer::{Mat, MatRef};

#[derive(Clone, Debug)]
pub struct SnapshotPairs {
    x: Mat<f64>,
    y: Mat<f64>,
}

impl SnapshotPairs {
    pub fn new(x: MatRef<'_, f64>, y: MatRef<'_, f64>) -> Result<Self, DmdError> {
        check_pairs(x, y, None)?;
        Ok(Self {
            x: x.to_owned(),
            y: y.to_owned(),
        })
    }

    pub fn push(&mut self, x: MatRef<'_, f64>, y: MatRef<'_, f64>) -> Result<(), DmdError> {
        check_pairs(x, y, Some(self.dim()))?;
        append_cols(&mut self.x, x);
        append_cols(&mut self.y, y);
        Ok(())
    }

    /// State dimension `N`.
    pub fn dim(&self) -> usize {
        self.x.nrows()
    }

    /// Number of pairs `m`.
    pub fn len(&self) -> usize {
        self.x.ncols()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn x(&self) -> MatRef<'_, f64> {
        self.x.as_ref()
    }

    pub fn y(&self) -> MatRef<'_, f64> {
        self.y.as_ref()
    }
}

fn append_cols(dst: &mut Mat<f64>, src: MatRef<'_, f64>) {
    let (n, m) = (dst.nrows(), dst.ncols());
    dst.resize_with(n, m + src.ncols(), |i, j| src[(i, j - m)]);
}

/// Shapes agree, there is at least one pair, and every value is finite.
pub fn check_pairs(x: MatRef<'_, f64>, y: MatRef<'_, f64>, dim: Option<usize>) -> Result<(), DmdError> {
    check_shapes(x, y, dim)?;
    check_finite(x)?;
    check_finite(y)
}

/// [`check_pairs`]' shapes: `X` and `Y` alike, not empty, of `dim` rows when given.
pub fn check_shapes(x: MatRef<'_, f64>, y: MatRef<'_, f64>, dim: Option<usize>) -> Result<(), DmdError> {
    if x.nrows() != y.nrows() || x.ncols() != y.ncols() {
        return Err(DmdError::Shape(format!(
            "X is {} x {} but Y is {} x {}; they must match",
            x.nrows(),
            x.ncols(),
            y.nrows(),
            y.ncols()
        )));
    }
    if x.ncols() == 0 || x.nrows() == 0 {
        return Err(DmdError::Shape("no snapshot pairs given".into()));
    }
    match dim {
        Some(n) if x.nrows() != n => Err(DmdError::Shape(format!(
            "new snapshots have {} rows, the model has {n}",
            x.nrows()
        ))),
        _ => Ok(()),
    }
}

/// [`check_pairs`]' values: the first one not finite, by column.
pub fn check_finite(m: MatRef<'_, f64>) -> Result<(), DmdError> {
    for j in 0..m.ncols() {
        if let Some(i) = m.col(j).iter().position(|v| !v.is_finite()) {
            return Err(DmdError::NonFinite { row: i, col: j });
        }
    }
    Ok(())
}
