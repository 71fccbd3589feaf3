//! The vehicle's readings log on disk (`<state-dir>/<id>.readings.ndjson`,
//! `fleet_mission::instrument::log`): every input the instrument gave and the vehicle took,
//! appended as it is taken, one write a line (a killed process loses none of them), synced to
//! the disk at every tick (a power cut loses at most the last quarter second). A restarted node
//! takes back from it the readings of the epochs still open; `fleet up` gathers the logs into
//! the run's `readings.ndjson` for `fleet assimilate`.

use fleet_mission::instrument::{Entry, Logged, Reading};
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use tracing::warn;

pub struct ReadingsLog {
    file: std::fs::File,
    path: PathBuf,
    vehicle: String,
    /// Lines written since the last sync.
    dirty: bool,
    /// A write failed (said once; the readings still go into the batches).
    failed: bool,
}

impl ReadingsLog {
    /// The log of `vehicle` at `path`, opened for appending (created if new).
    pub fn open(path: &Path, vehicle: &str) -> std::io::Result<Self> {
        let file = std::fs::OpenOptions::new().create(true).append(true).open(path)?;
        Ok(Self {
            file,
            path: path.into(),
            vehicle: vehicle.into(),
            dirty: false,
            failed: false,
        })
    }

    pub fn write(&mut self, entry: Entry) {
        let mut line = Logged {
            vehicle: self.vehicle.clone(),
            entry,
        }
        .line();
        line.push('\n');
        match self.file.write_all(line.as_bytes()) {
            Ok(()) => self.dirty = true,
            Err(e) if !std::mem::replace(&mut self.failed, true) => {
                warn!(
                    "the readings log {}: {e} (readings still go into the batches; the log misses them)",
                    self.path.display()
                );
            }
            Err(_) => {}
        }
    }

    /// To the disk, if anything was written since the last time.
    pub fn sync(&mut self) {
        if std::mem::take(&mut self.dirty) {
            if let Err(e) = self.file.sync_data() {
                warn!("syncing the readings log {}: {e}", self.path.display());
            }
        }
    }

    /// This vehicle's point readings in the log (a torn last line, as a crash may leave, and
    /// other vehicles' lines are passed over).
    pub fn readings(&self) -> Vec<Reading> {
        let Ok(file) = std::fs::File::open(&self.path) else {
            return vec![];
        };
        std::io::BufReader::new(file)
            .lines()
            .map_while(Result::ok)
            .filter_map(|l| Logged::parse(&l).ok())
            .filter(|l| l.vehicle == self.vehicle)
            .filter_map(|l| match l.entry {
                Entry::Reading(r) => Some(r),
                _ => None,
            })
            .collect()
    }
}
