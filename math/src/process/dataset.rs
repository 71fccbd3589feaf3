//! `.npy` datasets as field sources: any float64 array of shape `(frames, rows, cols)` is a
//! truth field (what `fleet simulate` writes and numpy users load with `np.load`), and a JSON
//! sidecar beside it records how it was made.

use super::FieldSeries;
use crate::npy::{self, NpyError};
use faer::Mat;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("{path}: expected shape (frames, rows, cols), found {shape:?}")]
    Shape { path: String, shape: Vec<usize> },
    #[error("{path}: a dataset needs at least {min} frames and a non-empty grid, found shape {shape:?}")]
    TooSmall { path: String, shape: Vec<usize>, min: usize },
    #[error("writing {path}: {source}")]
    Io { path: String, source: std::io::Error },
}

/// Load a `(frames, rows, cols)` float64 `.npy`, checked for shape and finiteness. `dt` is
/// the time between frames (the file does not carry one).
pub fn load(path: impl AsRef<Path>, dt: f64) -> Result<FieldSeries, DatasetError> {
    let path = path.as_ref();
    let p = path.display().to_string();
    let a = npy::read(path)?;
    let &[t, rows, cols] = a.shape.as_slice() else {
        return Err(DatasetError::Shape { path: p, shape: a.shape });
    };
    if t < 1 || rows == 0 || cols == 0 {
        return Err(DatasetError::TooSmall { path: p, shape: a.shape, min: 1 });
    }
    a.check_finite(&p)?;
    let n = rows * cols;
    Ok(FieldSeries { rows, cols, dt, snapshots: Mat::from_fn(n, t, |i, j| a.data[j * n + i]) })
}

/// Write a field as a `(frames, rows, cols)` float64 `.npy`, plus `sidecar` as pretty JSON at
/// `<path>.json` when given.
pub fn save(path: impl AsRef<Path>, field: &FieldSeries, sidecar: Option<&serde_json::Value>) -> Result<(), DatasetError> {
    let path = path.as_ref();
    let (n, t) = (field.dim(), field.frames());
    let mut data = Vec::with_capacity(n * t);
    for k in 0..t {
        data.extend(field.snapshots.col(k).iter());
    }
    npy::write(path, &[t, field.rows, field.cols], &data)?;
    if let Some(meta) = sidecar {
        let side = sidecar_path(path);
        let text = serde_json::to_string_pretty(meta).expect("JSON values serialise");
        std::fs::write(&side, text).map_err(|source| DatasetError::Io { path: side.display().to_string(), source })?;
    }
    Ok(())
}

/// `cloud1.npy` -> `cloud1.json`.
pub fn sidecar_path(path: &Path) -> std::path::PathBuf {
    path.with_extension("json")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_rejections() {
        let dir = std::env::temp_dir().join(format!("hetfleet-ds-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = FieldSeries { rows: 2, cols: 3, dt: 0.5, snapshots: Mat::from_fn(6, 4, |i, j| (i * 10 + j) as f64) };
        let p = dir.join("f.npy");
        save(&p, &f, Some(&serde_json::json!({"a": 1}))).unwrap();
        let g = load(&p, 0.5).unwrap();
        assert_eq!((g.rows, g.cols, g.frames()), (2, 3, 4));
        assert_eq!(g.snapshots, f.snapshots);
        assert!(dir.join("f.json").exists());
        npy::write(dir.join("flat.npy"), &[6, 4], &[0.0; 24]).unwrap();
        assert!(matches!(load(dir.join("flat.npy"), 1.0), Err(DatasetError::Shape { .. })));
        npy::write(dir.join("nan.npy"), &[1, 2, 2], &[0.0, f64::NAN, 0.0, 0.0]).unwrap();
        assert!(load(dir.join("nan.npy"), 1.0).is_err());
        assert!(load(dir.join("missing.npy"), 1.0).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
