//! The fused estimate and its reported variance at every step assimilated, kept where the user
//! of the core needs them:
//!
//! - in memory (the default): the experiments score every step against the truth and clone
//!   the core for a probe, so they read the steps back as they were made;
//! - in the run directory, written as the steps are made ([`History::in_files`]): the model
//!   server. Memory then does not grow with the mission (a step of the two is 4.7 MB at
//!   384 x 768) and nothing is copied whole at the end. A thread writes them from a bounded
//!   queue ([`crate::step_writer`]), off the epoch's path. The files are `estimate.npy.part` and
//!   `variance.npy.part` until the run's outputs are written ([`History::publish`]), when they
//!   take their names: a finished run's files appear when it finishes, as its other outputs do
//!   (and `fleet up`, which clears the previous run's outputs as it starts, never removes
//!   them), and a server that dies leaves every step it made readable in the `.part` files.
//!
//! Land (no data in the truth) is NaN in the files, numpy's mark of a value that is not there;
//! the core itself keeps land at 0 (dry), and the newest step, which the published model
//! carries, is kept in memory as the core made it.

use crate::step_file::{StepFile, StepReader};
use crate::step_writer::{Step, StepWriter};
use std::borrow::Cow;
use std::io;
use std::path::Path;
use std::sync::Arc;

/// The run's files of the fused map, and the suffix they have until the run's outputs are
/// written.
pub const FILES: [&str; 2] = ["estimate.npy", "variance.npy"];
const PART: &str = ".part";

/// Every step's fused estimate and variance.
#[derive(Debug)]
pub struct History(Store);

#[derive(Debug)]
enum Store {
    /// Steps `first..` in memory (`first` is 0 unless cloned from a file-backed history).
    Memory {
        first: usize,
        estimates: Vec<Vec<f64>>,
        variances: Vec<Vec<f64>>,
    },
    Files {
        writer: StepWriter,
        /// The estimate's and the variance's files, read back after the writer has caught up.
        readers: [StepReader; 2],
        steps: usize,
        /// Cells with no data (NaN in the files).
        land: Vec<bool>,
        /// The newest step as the core made it.
        last: Option<Step>,
    },
}

impl Default for History {
    fn default() -> Self {
        Self(Store::Memory {
            first: 0,
            estimates: vec![],
            variances: vec![],
        })
    }
}

/// A clone is the core's probe (an experiment tries an epoch on a copy): a file-backed history
/// clones into memory from its newest step on, so the copy never writes the run's files.
impl Clone for History {
    fn clone(&self) -> Self {
        match &self.0 {
            Store::Memory {
                first,
                estimates,
                variances,
            } => Self(Store::Memory {
                first: *first,
                estimates: estimates.clone(),
                variances: variances.clone(),
            }),
            Store::Files { steps, last, .. } => {
                let (estimates, variances) = last.iter().map(|s| (s.0.clone(), s.1.clone())).unzip();
                Self(Store::Memory {
                    first: steps - usize::from(last.is_some()),
                    estimates,
                    variances,
                })
            }
        }
    }
}

impl History {
    /// In `dir`'s `estimate.npy.part` and `variance.npy.part` (created, or replaced), `land`
    /// NaN there.
    pub fn in_files(dir: &Path, rows: usize, cols: usize, land: &[usize]) -> io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let mut on_land = vec![false; rows * cols];
        land.iter().for_each(|&c| on_land[c] = true);
        let files = [
            StepFile::create(dir.join(format!("{}{PART}", FILES[0])), rows, cols)?,
            StepFile::create(dir.join(format!("{}{PART}", FILES[1])), rows, cols)?,
        ];
        let (writer, readers) = StepWriter::start(files, on_land.clone())?;
        Ok(Self(Store::Files {
            writer,
            readers,
            steps: 0,
            land: on_land,
            last: None,
        }))
    }

    /// The directory whose `.npy` files the steps go to (`None`: in memory).
    pub fn files_dir(&self) -> Option<&Path> {
        match &self.0 {
            Store::Files { writer, .. } => writer.dir(),
            Store::Memory { .. } => None,
        }
    }

    /// Steps made so far.
    pub fn len(&self) -> usize {
        match &self.0 {
            Store::Memory { first, estimates, .. } => first + estimates.len(),
            Store::Files { steps, .. } => *steps,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The next step.
    pub fn push(&mut self, estimate: Vec<f64>, variance: Vec<f64>) -> io::Result<()> {
        match &mut self.0 {
            Store::Memory {
                estimates, variances, ..
            } => {
                estimates.push(estimate);
                variances.push(variance);
            }
            Store::Files {
                writer, steps, last, ..
            } => {
                let step = Arc::new((estimate, variance));
                writer.append(step.clone())?;
                *steps += 1;
                *last = Some(step);
            }
        }
        Ok(())
    }

    /// Keep the first `steps` steps (a re-fit from a checkpoint redoes the rest).
    pub fn truncate(&mut self, steps: usize) -> io::Result<()> {
        match &mut self.0 {
            Store::Memory {
                first,
                estimates,
                variances,
            } => {
                if steps < *first {
                    return Err(not_kept(steps, *first));
                }
                estimates.truncate(steps - *first);
                variances.truncate(steps - *first);
            }
            Store::Files {
                writer,
                readers,
                steps: made,
                land,
                last,
            } => {
                if steps >= *made {
                    return Ok(());
                }
                writer.truncate(steps)?;
                *made = steps;
                // The newest step again, land dry (0) as the core keeps it.
                let dry = |v: Vec<f64>| -> Vec<f64> {
                    v.into_iter()
                        .zip(land.iter())
                        .map(|(v, &l)| if l { 0.0 } else { v })
                        .collect()
                };
                *last = match steps {
                    0 => None,
                    s => {
                        writer.wait()?;
                        Some(Arc::new((dry(readers[0].read(s - 1)?), dry(readers[1].read(s - 1)?))))
                    }
                };
            }
        }
        Ok(())
    }

    /// Step `k`'s estimate (land NaN when read back from the files).
    pub fn estimate(&self, k: usize) -> io::Result<Cow<'_, [f64]>> {
        self.step(k, true)
    }

    /// Step `k`'s reported variance (land NaN when read back from the files).
    pub fn variance(&self, k: usize) -> io::Result<Cow<'_, [f64]>> {
        self.step(k, false)
    }

    fn step(&self, k: usize, estimate: bool) -> io::Result<Cow<'_, [f64]>> {
        match &self.0 {
            Store::Memory {
                first,
                estimates,
                variances,
            } => {
                let steps = if estimate { estimates } else { variances };
                k.checked_sub(*first)
                    .and_then(|i| steps.get(i))
                    .map(|s| Cow::Borrowed(s.as_slice()))
                    .ok_or_else(|| not_kept(k, *first))
            }
            Store::Files {
                writer, readers, steps, ..
            } => {
                if k >= *steps {
                    return Err(io::Error::new(io::ErrorKind::NotFound, format!("step {k} of {steps}")));
                }
                writer.wait()?;
                Ok(Cow::Owned(readers[usize::from(!estimate)].read(k)?))
            }
        }
    }

    /// Every step's estimate, read back (for tests and small runs: a copy of the whole history).
    pub fn estimates(&self) -> io::Result<Vec<Vec<f64>>> {
        (0..self.len()).map(|k| self.estimate(k).map(Cow::into_owned)).collect()
    }

    /// Every step's reported variance, read back.
    pub fn variances(&self) -> io::Result<Vec<Vec<f64>>> {
        (0..self.len()).map(|k| self.variance(k).map(Cow::into_owned)).collect()
    }

    /// The newest step's estimate and variance, as the core made them.
    pub fn last(&self) -> Option<(&[f64], &[f64])> {
        match &self.0 {
            Store::Memory {
                estimates, variances, ..
            } => estimates
                .last()
                .zip(variances.last())
                .map(|(e, v)| (e.as_slice(), v.as_slice())),
            Store::Files { last, .. } => last.as_deref().map(|(e, v)| (e.as_slice(), v.as_slice())),
        }
    }

    /// The files on the disk under their own names (`estimate.npy`, `variance.npy`), when in
    /// files. Steps made after it (a late batch's re-fit) still go to them: the open files
    /// are the same.
    pub fn publish(&self) -> io::Result<()> {
        if let Store::Files { writer, readers, .. } = &self.0 {
            writer.wait()?;
            for ((part, reader), name) in writer.paths().iter().zip(readers).zip(FILES) {
                reader.sync()?;
                if part.exists() {
                    std::fs::rename(part, part.with_file_name(name))?;
                }
            }
        }
        Ok(())
    }
}

fn not_kept(k: usize, first: usize) -> io::Error {
    io::Error::new(
        io::ErrorKind::NotFound,
        format!("step {k} is not kept here (from step {first}: a copy of a history in files)"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(k: usize) -> (Vec<f64>, Vec<f64>) {
        let e = (0..6).map(|i| (k * 10 + i) as f64).collect();
        let v = (0..6).map(|i| 1.0 + (k * 10 + i) as f64 / 100.0).collect();
        (e, v)
    }

    /// The same steps, in memory and in files: the same values read back (land NaN in the
    /// files), the same newest step, the same after a cut back; a clone of the file-backed one
    /// keeps its newest step and writes no file.
    #[test]
    fn memory_and_files_hold_the_same_steps() {
        let dir = std::env::temp_dir().join(format!("hetfleet-history-{}", std::process::id()));
        let land = [4usize];
        let mut mem = History::default();
        let mut files = History::in_files(&dir, 2, 3, &land).unwrap();
        for k in 0..4 {
            let (e, v) = step(k);
            let dry = |mut x: Vec<f64>| {
                x[4] = 0.0;
                x
            };
            mem.push(dry(e.clone()), dry(v.clone())).unwrap();
            files.push(dry(e), dry(v)).unwrap();
        }
        let same = |mem: &History, files: &History| {
            assert_eq!(mem.len(), files.len());
            assert_eq!(mem.last(), files.last());
            for k in 0..mem.len() {
                let (a, b) = (mem.estimate(k).unwrap(), files.estimate(k).unwrap());
                assert!(b[4].is_nan() && a[4] == 0.0);
                assert_eq!((a[..4].to_vec(), a[5]), (b[..4].to_vec(), b[5]));
                assert_eq!(mem.variance(k).unwrap()[0], files.variance(k).unwrap()[0]);
            }
        };
        same(&mem, &files);
        let a = fleet_math::npy::read(dir.join("estimate.npy.part")).unwrap();
        assert_eq!(a.shape, vec![4, 2, 3]);
        mem.truncate(2).unwrap();
        files.truncate(2).unwrap();
        same(&mem, &files);
        let probe = files.clone();
        assert!(
            probe.files_dir().is_none()
                && files.files_dir() == Some(dir.as_path())
                && probe.len() == 2
                && probe.last() == files.last()
        );
        assert!(probe.estimate(0).is_err(), "not kept in the copy");
        // Published: under their names, and still written (twice is no harm).
        files.publish().unwrap();
        files.publish().unwrap();
        files.push(step(9).0, step(9).1).unwrap();
        assert_eq!(files.variance(2).unwrap()[0], step(9).1[0], "read back once written");
        assert_eq!(
            fleet_math::npy::read(dir.join("variance.npy")).unwrap().shape,
            vec![3, 2, 3]
        );
        assert!(!dir.join("estimate.npy.part").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
