//! A float64 `.npy` of shape `(steps, rows, cols)` that grows a step at a time and can be cut
//! back (a re-fit from a checkpoint redoes its steps): the model server's `estimate.npy` and
//! `variance.npy`, written as the steps are made instead of held in memory to the end.
//!
//! The header has a fixed size ([`HEADER`] bytes, numpy's format 1.0 padded with spaces), so
//! the step count is rewritten in place after every change: the file is a valid `.npy` at every
//! moment, and a server that dies mid-mission leaves every step it made readable by `np.load`.
//! Writes are positioned (`pwrite`), so the file has no cursor to get out of step.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// The header's size: magic, version, length, and the dictionary padded to it (a multiple of
/// 64, as numpy aligns it; room for three sizes of 20 digits).
const HEADER: usize = 192;

/// An appendable `(steps, rows, cols)` float64 array on disk.
#[derive(Debug)]
pub struct StepFile {
    file: File,
    path: PathBuf,
    rows: usize,
    cols: usize,
    steps: usize,
}

impl StepFile {
    /// A new file of no steps (an existing one is replaced).
    pub fn create(path: impl AsRef<Path>, rows: usize, cols: usize) -> std::io::Result<Self> {
        let path = path.as_ref().to_path_buf();
        let file = File::options()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&path)?;
        let f = Self {
            file,
            path,
            rows,
            cols,
            steps: 0,
        };
        f.write_header()?;
        Ok(f)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn steps(&self) -> usize {
        self.steps
    }

    fn step_bytes(&self) -> usize {
        self.rows * self.cols * 8
    }

    fn offset(&self, step: usize) -> u64 {
        (HEADER + step * self.step_bytes()) as u64
    }

    /// One step's values after the last (little-endian float64; `rows * cols` of them).
    pub fn append(&mut self, values: impl ExactSizeIterator<Item = f64>) -> std::io::Result<()> {
        if values.len() != self.rows * self.cols {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("{} values for a {} x {} step", values.len(), self.rows, self.cols),
            ));
        }
        let bytes: Vec<u8> = values.flat_map(f64::to_le_bytes).collect();
        self.file.write_all_at(&bytes, self.offset(self.steps))?;
        self.steps += 1;
        self.write_header()
    }

    /// Keep the first `steps` steps only.
    pub fn truncate(&mut self, steps: usize) -> std::io::Result<()> {
        if steps >= self.steps {
            return Ok(());
        }
        self.steps = steps;
        self.write_header()?;
        self.file.set_len(self.offset(steps))
    }

    /// Step `k`'s values, read back.
    pub fn read(&self, k: usize) -> std::io::Result<Vec<f64>> {
        if k >= self.steps {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                format!("step {k} of {}", self.steps),
            ));
        }
        read_step(&self.file, self.step_bytes(), k)
    }

    /// A handle that reads steps on another thread (the same open file: it follows a rename).
    pub fn reader(&self) -> std::io::Result<StepReader> {
        Ok(StepReader {
            file: self.file.try_clone()?,
            step_bytes: self.step_bytes(),
        })
    }

    fn write_header(&self) -> std::io::Result<()> {
        self.file.write_all_at(&header(self.steps, self.rows, self.cols), 0)
    }
}

/// Reads the steps of a [`StepFile`] written elsewhere (the caller knows how many there are).
#[derive(Debug)]
pub struct StepReader {
    file: File,
    step_bytes: usize,
}

impl StepReader {
    pub fn read(&self, k: usize) -> std::io::Result<Vec<f64>> {
        read_step(&self.file, self.step_bytes, k)
    }

    /// The file's data on the disk.
    pub fn sync(&self) -> std::io::Result<()> {
        self.file.sync_data()
    }
}

fn read_step(file: &File, step_bytes: usize, k: usize) -> std::io::Result<Vec<f64>> {
    let mut bytes = vec![0u8; step_bytes];
    file.read_exact_at(&mut bytes, (HEADER + k * step_bytes) as u64)?;
    Ok(bytes
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
        .collect())
}

/// numpy's format 1.0 header for a C-order float64 `(steps, rows, cols)`, padded with spaces
/// to [`HEADER`] bytes and ended by a newline.
fn header(steps: usize, rows: usize, cols: usize) -> Vec<u8> {
    let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({steps}, {rows}, {cols}), }}");
    let text_len = HEADER - 10;
    let mut h = Vec::with_capacity(HEADER);
    h.extend_from_slice(b"\x93NUMPY\x01\x00");
    h.extend_from_slice(&(text_len as u16).to_le_bytes());
    h.extend_from_slice(dict.as_bytes());
    h.resize(HEADER - 1, b' ');
    h.push(b'\n');
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_grow_are_cut_back_and_read_as_npy_at_every_moment() {
        let dir = std::env::temp_dir().join(format!("hetfleet-steps-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("s.npy");
        let step = |k: usize| (0..6).map(move |i| (10 * k + i) as f64 + 0.5);
        let mut f = StepFile::create(&p, 2, 3).unwrap();
        assert_eq!(
            fleet_math::npy::read(&p).unwrap().shape,
            vec![0, 2, 3],
            "valid when empty"
        );
        for k in 0..3 {
            f.append(step(k)).unwrap();
        }
        let a = fleet_math::npy::read(&p).unwrap();
        assert_eq!(a.shape, vec![3, 2, 3]);
        assert_eq!(a.data, (0..3).flat_map(step).collect::<Vec<_>>());
        // A re-fit from step 1: cut back, then the redone steps.
        f.truncate(1).unwrap();
        f.append(step(7).map(|v| -v)).unwrap();
        let a = fleet_math::npy::read(&p).unwrap();
        assert_eq!(a.shape, vec![2, 2, 3]);
        assert_eq!(f.read(1).unwrap(), step(7).map(|v| -v).collect::<Vec<_>>());
        assert_eq!(a.data[..6], step(0).collect::<Vec<_>>()[..]);
        assert!(f.read(2).is_err() && f.append(step(0).take(5)).is_err());
        // Three sizes of 20 digits still fit.
        assert_eq!(header(usize::MAX, usize::MAX, usize::MAX).len(), HEADER);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
