//! Why a field file cannot become a field, whichever its format (`.npy` or NetCDF): one error
//! type both readers return ([`super::dataset`] loads either; [`super::netcdf`] reads the second),
//! so it lives below both.

use crate::npy::NpyError;

#[derive(Debug, thiserror::Error, strum::VariantNames)]
pub enum DatasetError {
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("{path}: expected shape (frames, rows, cols), found {shape:?}")]
    Shape { path: String, shape: Vec<usize> },
    #[error("{path}: a dataset needs at least {min} frames and a non-empty grid, found shape {shape:?}")]
    TooSmall {
        path: String,
        shape: Vec<usize>,
        min: usize,
    },
    #[error("writing {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: not a readable NetCDF file ({why})")]
    NetCdf { path: String, why: String },
    #[error("{path}: no variable {variable:?} (it has: {have})")]
    NoVariable {
        path: String,
        variable: String,
        have: String,
    },
    /// What the file says about the variable cannot make a field (CF attributes, dimensions,
    /// coordinates, values missing everywhere).
    #[error("{path} ({variable}): {why}")]
    Cf {
        path: String,
        variable: String,
        why: String,
    },
    #[error("{path}: {why}")]
    Holes { path: String, why: String },
    /// Values in units the estimator does not hold exactly ([`super::units`]).
    #[error("{path}: {why}")]
    Units { path: String, why: String },
}
