//! The writer of the run's fused map: a thread that owns `estimate.npy.part` and
//! `variance.npy.part` ([`StepFile`]s) and takes steps from a bounded queue, so the epoch hands
//! a step over and goes on (at 384 x 768 a step of the two is 4.7 MB: writing it in the epoch
//! cost 55 ms an epoch). The queue holds [`QUEUE_STEPS`] steps; a full queue waits for the disk
//! rather than holding more in memory. A write that fails is reported at the next call (and
//! every call after: the files are then incomplete, and the run must say so).

use crate::step_file::{StepFile, StepReader};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;

/// Steps queued at most (two boat epochs of the default mission's 5 steps, and some).
pub const QUEUE_STEPS: usize = 12;

/// A step's estimate and variance, shared with the core's newest step.
pub type Step = Arc<(Vec<f64>, Vec<f64>)>;

enum Op {
    Append(Step),
    Truncate(usize),
    /// Everything before it is written: answered when reached.
    Barrier(mpsc::Sender<()>),
}

/// The writer thread's handle.
#[derive(Debug)]
pub struct StepWriter {
    queue: Option<SyncSender<Op>>,
    thread: Option<JoinHandle<()>>,
    failed: Arc<Mutex<Option<String>>>,
    paths: [PathBuf; 2],
}

impl std::fmt::Debug for Op {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Op::Append(_) => "Append",
            Op::Truncate(_) => "Truncate",
            Op::Barrier(_) => "Barrier",
        })
    }
}

impl StepWriter {
    /// Start writing `files` (land NaN in them); readers of the same files for reading back.
    pub fn start(files: [StepFile; 2], land: Vec<bool>) -> io::Result<(Self, [StepReader; 2])> {
        let readers = [files[0].reader()?, files[1].reader()?];
        let paths = [files[0].path().to_path_buf(), files[1].path().to_path_buf()];
        let (queue, rx) = mpsc::sync_channel(QUEUE_STEPS);
        let failed = Arc::new(Mutex::new(None));
        let thread = std::thread::Builder::new().name("history-writer".into()).spawn({
            let failed = failed.clone();
            move || write_steps(files, &land, rx, &failed)
        })?;
        let writer = Self {
            queue: Some(queue),
            thread: Some(thread),
            failed,
            paths,
        };
        Ok((writer, readers))
    }

    pub fn paths(&self) -> &[PathBuf; 2] {
        &self.paths
    }

    pub fn dir(&self) -> Option<&Path> {
        self.paths[0].parent()
    }

    /// The next step (waits only when [`QUEUE_STEPS`] are queued).
    pub fn append(&self, step: Step) -> io::Result<()> {
        self.send(Op::Append(step))
    }

    /// Keep the first `steps` steps.
    pub fn truncate(&self, steps: usize) -> io::Result<()> {
        self.send(Op::Truncate(steps))
    }

    /// Wait until everything queued is written; the first failure, if any.
    pub fn wait(&self) -> io::Result<()> {
        let (tx, rx) = mpsc::channel();
        self.send(Op::Barrier(tx))?;
        rx.recv().map_err(|_| stopped())?;
        self.check()
    }

    fn send(&self, op: Op) -> io::Result<()> {
        self.check()?;
        let queue = self.queue.as_ref().ok_or_else(stopped)?;
        queue.send(op).map_err(|_| stopped())
    }

    fn check(&self) -> io::Result<()> {
        match self.failed.lock().unwrap_or_else(PoisonError::into_inner).as_ref() {
            Some(why) => Err(io::Error::other(why.clone())),
            None => Ok(()),
        }
    }
}

/// Everything queued is written before the handle goes.
impl Drop for StepWriter {
    fn drop(&mut self) {
        drop(self.queue.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn stopped() -> io::Error {
    io::Error::other("the history's writer thread has stopped")
}

/// The thread: each op in order; after a failure only barriers are answered.
fn write_steps(mut files: [StepFile; 2], land: &[bool], rx: Receiver<Op>, failed: &Mutex<Option<String>>) {
    for op in rx {
        let done = match op {
            Op::Barrier(reply) => {
                let _ = reply.send(());
                continue;
            }
            _ if failed.lock().unwrap_or_else(PoisonError::into_inner).is_some() => continue,
            Op::Append(step) => append(&mut files, land, &step),
            Op::Truncate(steps) => files.iter_mut().try_for_each(|f| f.truncate(steps)),
        };
        if let Err(e) = done {
            let path = files[0].path().display().to_string();
            *failed.lock().unwrap_or_else(PoisonError::into_inner) = Some(format!("{path}: {e}"));
        }
    }
}

fn append(files: &mut [StepFile; 2], land: &[bool], step: &Step) -> io::Result<()> {
    let wet = |values: &[f64]| -> Vec<f64> {
        values
            .iter()
            .zip(land)
            .map(|(&v, &l)| if l { f64::NAN } else { v })
            .collect()
    };
    files[0].append(wet(&step.0).into_iter())?;
    files[1].append(wet(&step.1).into_iter())
}
