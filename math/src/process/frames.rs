//! A truth a node reads a frame at a time. A mixed-reality node needs the truth's frame at each
//! step it senses or scores, never all of them at once, and at 384 x 768 the 100 frames of the
//! bundled mission are 236 MB: held in memory, they were a fifth of the model server's peak
//! and as much again in every vehicle (docs/decisions/085, the twenty-first pass). So a truth given as a
//! `.npy` file stays in its file and each frame is read from it when asked (one positioned
//! read); a truth made here (the simulator) stays in memory. Either way a frame is the same
//! values, NaN where the truth has none, and the whole file is checked once when it is opened,
//! as [`super::dataset::load_truth`] checks it.

use super::error::DatasetError;
use super::FieldSeries;
use crate::npy::{NpyError, MAX_VALUES};
use std::io::Seek;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// A field series read a frame at a time: its shape, time step and land, and its frames.
#[derive(Debug)]
pub struct Frames {
    rows: usize,
    cols: usize,
    dt: f64,
    frames: usize,
    /// Cells with no value in any frame, in order (see [`FieldSeries::land`]).
    land: Vec<u32>,
    store: Store,
}

#[derive(Debug)]
enum Store {
    Memory(FieldSeries),
    /// A C-order `(frames, rows, cols)` array of `width`-byte little-endian floats from byte
    /// `offset` of the file on.
    File {
        path: PathBuf,
        file: std::fs::File,
        offset: u64,
        width: usize,
    },
}

impl Frames {
    /// A series held in memory.
    pub fn in_memory(series: FieldSeries) -> Self {
        Self {
            rows: series.rows,
            cols: series.cols,
            dt: series.dt,
            frames: series.frames(),
            land: series.land(),
            store: Store::Memory(series),
        }
    }

    /// A truth `.npy` read a frame at a time (float64 or float32, C order), checked whole as
    /// [`super::dataset::load_truth`] checks it: an infinity, a frame without any value or
    /// a file shorter than its header says are refused. A Fortran-order file is loaded whole
    /// (its frames are not contiguous).
    pub fn open_npy(path: &Path, dt: f64) -> Result<Self, DatasetError> {
        let p = path.display().to_string();
        let io = |source| {
            DatasetError::Npy(NpyError::Io {
                path: p.clone(),
                source,
            })
        };
        let mut file = std::fs::File::open(path).map_err(io)?;
        let npy = npyz::NpyFile::new(&mut file).map_err(io)?;
        let width = match npy.dtype() {
            npyz::DType::Plain(ts) if ts.to_string() == "<f8" => 8,
            npyz::DType::Plain(ts) if ts.to_string() == "<f4" => 4,
            _ => return super::dataset::load_truth(path, dt).map(Self::in_memory),
        };
        if npy.order() == npyz::Order::Fortran {
            return super::dataset::load_truth(path, dt).map(Self::in_memory);
        }
        let shape: Vec<usize> = npy.shape().iter().map(|&s| s as usize).collect();
        let &[frames, rows, cols] = shape.as_slice() else {
            return Err(DatasetError::Shape { path: p, shape });
        };
        if frames < 1 || rows == 0 || cols == 0 {
            return Err(DatasetError::TooSmall { path: p, shape, min: 1 });
        }
        let offset = file.stream_position().map_err(io)?;
        let total = frames.checked_mul(rows * cols).filter(|&t| t <= MAX_VALUES);
        let len = file.metadata().map_err(io)?.len();
        if total.is_none_or(|t| offset + (t * width) as u64 > len) {
            let why = format!("the header's shape {shape:?} does not fit the file's {len} bytes");
            return Err(DatasetError::Npy(NpyError::Header { path: p, why }));
        }
        let mut me = Self {
            rows,
            cols,
            dt,
            frames,
            land: vec![],
            store: Store::File {
                path: path.to_path_buf(),
                file,
                offset,
                width,
            },
        };
        me.land = me.check_all()?;
        Ok(me)
    }

    /// Every frame read once: no infinity, no frame without a value; the land (NaN in every
    /// frame) found on the way.
    fn check_all(&self) -> Result<Vec<u32>, DatasetError> {
        let n = self.dim();
        let mut everywhere = vec![true; n];
        let mut all_missing = true;
        let mut spread = super::units::Spread::default();
        for k in 0..self.frames {
            let x = self.frame(k)?;
            x.iter().for_each(|&v| spread.add(v));
            if let Some(i) = x.iter().position(|v| v.is_infinite()) {
                let path = self.path_name();
                return Err(NpyError::NonFinite {
                    path,
                    index: k * n + i,
                    value: x[i],
                }
                .into());
            }
            let missing = x.iter().filter(|v| v.is_nan()).count();
            all_missing &= missing == n;
            everywhere.iter_mut().zip(&x).for_each(|(e, v)| *e &= v.is_nan());
        }
        // The message of `netcdf::check_holes`, which the whole-file load gives. A frame with no
        // value at all is a frame in which nothing was seen, not a broken file.
        if all_missing {
            return Err(DatasetError::Holes {
                path: self.path_name(),
                why: "every value is missing (fill value, missing_value or outside the valid range)".into(),
            });
        }
        spread.check().map_err(|why| DatasetError::Units {
            path: self.path_name(),
            why,
        })?;
        Ok((0..n).filter(|&i| everywhere[i]).map(|i| i as u32).collect())
    }

    fn path_name(&self) -> String {
        match &self.store {
            Store::Memory(_) => "the truth".into(),
            Store::File { path, .. } => path.display().to_string(),
        }
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    /// `(rows, cols, frames)`, as [`FieldSeries::shape`].
    pub fn shape(&self) -> (usize, usize, usize) {
        (self.rows, self.cols, self.frames)
    }

    /// Cells a frame has.
    pub fn dim(&self) -> usize {
        self.rows * self.cols
    }

    /// How many frames there are.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Seconds between consecutive frames.
    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// The cells with no value in any frame (land), in order.
    pub fn land(&self) -> &[u32] {
        &self.land
    }

    /// Frame `k` (cells in row-major order, NaN where the truth has no value). An error only
    /// for a file the disk will not give back (it was checked whole when it was opened).
    pub fn frame(&self, k: usize) -> Result<Vec<f64>, DatasetError> {
        assert!(k < self.frames, "frame {k} of a truth of {} frames", self.frames);
        let n = self.dim();
        match &self.store {
            Store::Memory(s) => Ok(s.snapshots.col(k).iter().copied().collect()),
            Store::File {
                path,
                file,
                offset,
                width,
            } => {
                let mut bytes = vec![0u8; n * width];
                let at = offset + (k * n * width) as u64;
                file.read_exact_at(&mut bytes, at).map_err(|source| DatasetError::Io {
                    path: format!("reading frame {k} of {}", path.display()),
                    source,
                })?;
                Ok(match width {
                    8 => bytes
                        .chunks_exact(8)
                        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
                        .collect(),
                    _ => bytes
                        .chunks_exact(4)
                        .map(|b| f64::from(f32::from_le_bytes(b.try_into().unwrap())))
                        .collect(),
                })
            }
        }
    }

    /// Whether the frames are read from a file as they are asked for.
    pub fn is_file_backed(&self) -> bool {
        matches!(self.store, Store::File { .. })
    }

    /// The whole series in memory (for what needs every frame at once: a report, a test).
    pub fn to_series(&self) -> Result<FieldSeries, DatasetError> {
        if let Store::Memory(s) = &self.store {
            return Ok(s.clone());
        }
        let n = self.dim();
        let mut snapshots = faer::Mat::zeros(n, self.frames);
        for k in 0..self.frames {
            let x = self.frame(k)?;
            snapshots.col_mut(k).iter_mut().zip(x).for_each(|(s, v)| *s = v);
        }
        Ok(FieldSeries {
            rows: self.rows,
            cols: self.cols,
            dt: self.dt,
            snapshots,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(frames: usize, rows: usize, cols: usize) -> FieldSeries {
        FieldSeries {
            rows,
            cols,
            dt: 0.5,
            snapshots: faer::Mat::from_fn(rows * cols, frames, |i, k| (i as f64) * 0.25 - k as f64),
        }
    }

    fn write(dir: &Path, name: &str, s: &FieldSeries) -> PathBuf {
        let p = dir.join(name);
        let n = s.dim();
        let data: Vec<f64> = (0..s.frames() * n).map(|j| s.snapshots[(j % n, j / n)]).collect();
        crate::npy::write(&p, &[s.frames(), s.rows, s.cols], &data).unwrap();
        p
    }

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("fleet-frames-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A frame read from the file is the frame the whole-file load gives, to the bit, NaN
    /// (land and cloud) included; shape, time step and land are the same.
    #[test]
    fn frames_from_the_file_are_the_loaded_truths() {
        let dir = scratch("same");
        let mut s = series(6, 3, 4);
        for k in 0..6 {
            s.snapshots[(5, k)] = f64::NAN; // land
        }
        s.snapshots[(2, 3)] = f64::NAN; // cloud in one frame
        let p = write(&dir, "t.npy", &s);
        let whole = super::super::dataset::load_truth(&p, 0.5).unwrap();
        let f = Frames::open_npy(&p, 0.5).unwrap();
        assert!(f.is_file_backed());
        assert_eq!((f.rows(), f.cols(), f.frames(), f.dt()), (3, 4, 6, 0.5));
        assert_eq!(f.land(), whole.land().as_slice());
        assert_eq!(f.land(), &[5]);
        for k in 0..6 {
            let a: Vec<u64> = f.frame(k).unwrap().iter().map(|v| v.to_bits()).collect();
            let b: Vec<u64> = whole.snapshots.col(k).iter().map(|v| v.to_bits()).collect();
            assert_eq!(a, b, "frame {k}");
        }
        let back = f.to_series().unwrap();
        assert_eq!(back.snapshots.col(3).iter().filter(|v| v.is_nan()).count(), 2);
        let mem = Frames::in_memory(whole);
        assert!(!mem.is_file_backed());
        let bits = |x: Vec<f64>| x.iter().map(|v| v.to_bits()).collect::<Vec<u64>>();
        assert_eq!(bits(mem.frame(2).unwrap()), bits(f.frame(2).unwrap()));
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// Positioned reads take `&File`: one `Frames` serves every thread of a node by an `Arc`.
    #[test]
    fn frames_are_shared_between_threads() {
        fn shared<T: Send + Sync>() {}
        shared::<Frames>();
    }

    /// What the whole-file load refuses, opening refuses: an infinity (naming its index), a
    /// file with no value, a file cut short of its header's shape. A frame without a value
    /// opens: nothing was seen then.
    #[test]
    fn a_bad_truth_file_is_refused_when_it_is_opened() {
        let dir = scratch("bad");
        let mut s = series(4, 2, 3);
        s.snapshots[(1, 2)] = f64::INFINITY;
        let p = write(&dir, "inf.npy", &s);
        let e = Frames::open_npy(&p, 1.0).unwrap_err().to_string();
        assert!(e.contains("value 13 is not finite"), "{e}");
        let mut s = series(4, 2, 3);
        for i in 0..6 {
            s.snapshots[(i, 1)] = f64::NAN;
        }
        let p = write(&dir, "empty.npy", &s);
        let f = Frames::open_npy(&p, 1.0).unwrap();
        assert!(f.frame(1).unwrap().iter().all(|v| v.is_nan()) && f.land().is_empty());
        let mut none = series(4, 2, 3);
        none.snapshots.fill(f64::NAN);
        let p = write(&dir, "none.npy", &none);
        let e = Frames::open_npy(&p, 1.0).unwrap_err().to_string();
        assert!(e.contains("every value is missing"), "{e}");
        let p = write(&dir, "short.npy", &series(4, 2, 3));
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() - 8]).unwrap();
        let e = Frames::open_npy(&p, 1.0).unwrap_err().to_string();
        assert!(e.contains("does not fit the file's"), "{e}");
        std::fs::remove_dir_all(dir).unwrap();
    }
}
