//! `.npy` input and output of float64 arrays, so numpy users can load what hetfleet writes and
//! hand it their own data. Little-endian float64 or float32 (widened exactly to float64) in C or
//! Fortran order is accepted; anything else is a clear error, never a panic.

use npyz::{Order, WriterBuilder};
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum NpyError {
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: expected float64 or float32 data, found dtype {dtype}")]
    DType { path: String, dtype: String },
    #[error("{path}: expected {expected}, found shape {shape:?}")]
    Shape {
        path: String,
        expected: String,
        shape: Vec<u64>,
    },
    #[error("{path}: {why}")]
    Header { path: String, why: String },
    #[error("{path}: value {index} is not finite ({value})")]
    NonFinite { path: String, index: usize, value: f64 },
}

/// A float64 array in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl Array {
    /// Check that every value is finite.
    pub fn check_finite(&self, path: &str) -> Result<(), NpyError> {
        match self.data.iter().position(|v| !v.is_finite()) {
            Some(index) => Err(NpyError::NonFinite {
                path: path.into(),
                index,
                value: self.data[index],
            }),
            None => Ok(()),
        }
    }
}

/// Most values one array may hold (8 GiB of float64): a header may not make us allocate more.
pub const MAX_VALUES: usize = 1 << 30;

/// The shape in a `.npy` file's header (the data is not read).
pub fn read_shape(path: impl AsRef<Path>) -> Result<Vec<usize>, NpyError> {
    let p = path.as_ref().display().to_string();
    let io = |source| NpyError::Io {
        path: p.clone(),
        source,
    };
    let f = std::io::BufReader::new(File::open(path.as_ref()).map_err(io)?);
    let npy = npyz::NpyFile::new(f).map_err(io)?;
    Ok(npy.shape().iter().map(|&s| s as usize).collect())
}

pub fn read(path: impl AsRef<Path>) -> Result<Array, NpyError> {
    let p = path.as_ref().display().to_string();
    let bytes = std::fs::read(path.as_ref()).map_err(|source| NpyError::Io {
        path: p.clone(),
        source,
    })?;
    from_bytes(&bytes, &p)
}

/// Parse a whole `.npy` file held in memory (`name` is for messages). The header's shape is
/// checked against the bytes that follow before anything is allocated from it.
pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Array, NpyError> {
    let io = |source| NpyError::Io {
        path: name.into(),
        source,
    };
    let npy = npyz::NpyFile::new(bytes).map_err(io)?;
    let dtype = npy.dtype();
    let width = match &dtype {
        npyz::DType::Plain(ts) if ts.to_string() == "<f8" => 8,
        npyz::DType::Plain(ts) if ts.to_string() == "<f4" => 4,
        npyz::DType::Plain(ts) => {
            return Err(NpyError::DType {
                path: name.into(),
                dtype: ts.to_string(),
            })
        }
        _ => {
            return Err(NpyError::DType {
                path: name.into(),
                dtype: "a structured or array dtype".into(),
            })
        }
    };
    let header = |why: String| NpyError::Header { path: name.into(), why };
    let total = npy
        .shape()
        .iter()
        .try_fold(1usize, |acc, &s| acc.checked_mul(usize::try_from(s).ok()?));
    let total = match total {
        Some(t) if t <= MAX_VALUES && t.saturating_mul(width) <= bytes.len() => t,
        _ => {
            return Err(header(format!(
                "the header's shape {:?} does not fit the file's {} bytes",
                npy.shape(),
                bytes.len()
            )))
        }
    };
    let shape: Vec<usize> = npy.shape().iter().map(|&s| s as usize).collect();
    let order = npy.order();
    let raw: Vec<f64> = if width == 8 {
        npy.into_vec().map_err(io)?
    } else {
        npy.into_vec::<f32>().map_err(io)?.into_iter().map(f64::from).collect()
    };
    if raw.len() != total {
        return Err(header(format!("{} values for shape {shape:?}", raw.len())));
    }
    let data = match order {
        Order::C => raw,
        Order::Fortran => fortran_to_c(&raw, &shape),
    };
    Ok(Array { shape, data })
}

fn fortran_to_c(raw: &[f64], shape: &[usize]) -> Vec<f64> {
    let n = raw.len();
    let mut out = vec![0.0; n];
    // Fortran strides: first axis fastest.
    let mut fstride = vec![1usize; shape.len()];
    for k in 1..shape.len() {
        fstride[k] = fstride[k - 1] * shape[k - 1];
    }
    let mut idx = vec![0usize; shape.len()];
    for o in out.iter_mut() {
        let f: usize = idx.iter().zip(&fstride).map(|(i, s)| i * s).sum();
        *o = raw[f];
        for k in (0..shape.len()).rev() {
            idx[k] += 1;
            if idx[k] < shape[k] {
                break;
            }
            idx[k] = 0;
        }
    }
    out
}

/// Write an array in C order: float64 (`<f8`) or complex128 (`<c16`: `np.load` gives
/// `complex128`), as the element type says.
pub fn write<T: npyz::AutoSerialize + Copy>(
    path: impl AsRef<Path>,
    shape: &[usize],
    data: &[T],
) -> Result<(), NpyError> {
    write_values(path, shape, data.len(), data.iter().copied())
}

/// [`write`] from `count` values as they come (no copy of the whole array in memory: a run's
/// every step at 384 x 768 is hundreds of megabytes).
pub fn write_values<T: npyz::AutoSerialize>(
    path: impl AsRef<Path>,
    shape: &[usize],
    count: usize,
    values: impl IntoIterator<Item = T>,
) -> Result<(), NpyError> {
    let p = path.as_ref().display().to_string();
    let expected: usize = shape.iter().product();
    if expected != count {
        return Err(NpyError::Shape {
            path: p,
            expected: format!("{expected} values"),
            shape: shape.iter().map(|&s| s as u64).collect(),
        });
    }
    let io = |source| NpyError::Io {
        path: p.clone(),
        source,
    };
    let file = File::create(path.as_ref()).map_err(io)?;
    let shape64: Vec<u64> = shape.iter().map(|&s| s as u64).collect();
    let mut w = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&shape64)
        .writer(BufWriter::new(file))
        .begin_nd()
        .map_err(io)?;
    w.extend(values.into_iter().take(count)).map_err(io)?;
    w.finish().map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let dir = std::env::temp_dir().join(format!("hetfleet-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("a.npy");
        let data: Vec<f64> = (0..24).map(|i| i as f64 * 0.5).collect();
        write(&f, &[2, 3, 4], &data).unwrap();
        let a = read(&f).unwrap();
        assert_eq!(a.shape, vec![2, 3, 4]);
        assert_eq!(a.data, data);
        assert!(write(&f, &[5], &data).is_err());
        assert!(matches!(read(dir.join("missing.npy")), Err(NpyError::Io { .. })));
        std::fs::write(dir.join("junk.npy"), b"not an npy file at all").unwrap();
        assert!(read(dir.join("junk.npy")).is_err());
        let nan = Array {
            shape: vec![2],
            data: vec![1.0, f64::NAN],
        };
        assert!(matches!(
            nan.check_finite("x"),
            Err(NpyError::NonFinite { index: 1, .. })
        ));
    }

    #[test]
    fn fortran_order_is_transposed_to_c() {
        // 2 x 3 array [[0, 1, 2], [3, 4, 5]] stored column-major: 0 3 1 4 2 5
        let c = fortran_to_c(&[0.0, 3.0, 1.0, 4.0, 2.0, 5.0], &[2, 3]);
        assert_eq!(c, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    }
}
