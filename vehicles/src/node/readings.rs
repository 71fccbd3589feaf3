//! The vehicle node's instrument: lines from its source placed on the grid by the mission's
//! clock and site, kept by step and cell until the epoch's batch takes them (and written to the
//! readings log as they are taken), and every refusal counted (in telemetry) and said in the
//! log at most once in a while per kind.

use super::readings_log::ReadingsLog;
use fleet_math::grid::Grid;
use fleet_mission::config::MissionConfig;
use fleet_mission::instrument::{parse_line, Collected, Entry, Placer, Reading, Refusal, Tally};
use fleet_mission::protocol::{ReadingCounts, Sample, VehicleKind};
use std::ops::Range;
use tracing::warn;
use vehicles::sensor::{Frame, Input, Line};

/// How long after an epoch's last step ends its batch waits for readings still on their way
/// (an instrument's latency; a reading timed in the epoch and later than this is refused as
/// too old, and counted).
pub const CLOSE_AFTER_S: f64 = 2.0;

pub struct Instrument {
    placer: Placer,
    collected: Collected,
    tally: Tally,
    /// The mission's noise for this vehicle's kind (a reading without `sigma`).
    sigma: f64,
    /// The oldest step still open: readings before it are too old.
    oldest: u64,
    /// Where what is taken is written (none: not kept beyond the batches).
    log: Option<ReadingsLog>,
}

impl Instrument {
    /// The instrument of a `kind` vehicle whose first sensed step is `first`, or `None` in a
    /// mission without a clock (checked when the source was chosen); what it takes is written
    /// to `log`.
    pub fn new(
        mission: &MissionConfig,
        (grid, frames): (Grid, usize),
        kind: VehicleKind,
        first: u64,
        log: Option<ReadingsLog>,
    ) -> Option<Self> {
        Some(Self {
            placer: Placer {
                site: mission.mavlink.site(&grid),
                grid,
                fence: mission.team.fence.clone(),
                clock: mission.clock()?,
                frames: frames as u64,
            },
            collected: Collected::default(),
            tally: Tally::default(),
            sigma: mission.noise(kind).sigma0,
            oldest: first,
            log,
        })
    }

    /// One line or frame from the source, at `now` (UTC seconds).
    pub fn on_input(&mut self, input: Input, now: f64) {
        let kept = match input {
            Input::Line(Line::Text(bytes)) => parse_line(&bytes).and_then(|r| self.point(r, now)),
            Input::Line(Line::Oversized(n)) => Err((Refusal::Oversized, format!("a line of {n} bytes"))),
            Input::Frame(frame) => self.frame(frame, now),
            Input::Reading(r) => r.and_then(|r| self.point(r, now)),
            Input::Lost(n) => {
                for _ in 1..n {
                    self.tally.refuse(Refusal::Overflow, now);
                }
                Err((Refusal::Overflow, format!("{n} readings found the queue full")))
            }
        };
        match kept {
            Ok(()) => self.tally.accept(),
            Err((kind, why)) => {
                if self.tally.refuse(kind, now) {
                    warn!(
                        kind = %kind,
                        refused = self.tally.refused(kind),
                        "reading refused: {why} (said once every 10 s per kind; all are counted)"
                    );
                }
            }
        }
    }

    /// A point reading: placed, kept and logged.
    fn point(&mut self, r: Reading, now: f64) -> Result<(), (Refusal, String)> {
        let p = self.placer.place(&r, now, self.oldest)?;
        self.collected.add(&p, self.sigma);
        if let Some(log) = &mut self.log {
            log.write(Entry::Reading(r));
        }
        Ok(())
    }

    /// After a restart, the epochs from step `open` on are open again: the readings the log
    /// holds of them are taken back (frames come again from their directory).
    pub fn reopen(&mut self, open: u64, now: f64) {
        self.oldest = open;
        let readings = self.log.as_ref().map(ReadingsLog::readings).unwrap_or_default();
        let mut back = 0;
        for r in readings {
            if let Ok(p) = self.placer.place(&r, now, open) {
                self.collected.add(&p, self.sigma);
                back += 1;
            }
        }
        if back > 0 {
            tracing::info!(
                readings = back,
                from_step = open,
                "readings of the open epochs taken back from the log"
            );
        }
    }

    /// Where an aerial was at its sampling steps (grid metres), for the log.
    pub fn log_fixes(&mut self, fixes: impl Iterator<Item = (u64, (f64, f64))>) {
        if let Some(log) = &mut self.log {
            for (step, (x, y)) in fixes {
                log.write(Entry::Fix { step, fix: [x, y] });
            }
        }
    }

    /// The log to the disk (at every tick).
    pub fn sync(&mut self) {
        if let Some(log) = &mut self.log {
            log.sync();
        }
    }

    /// A frame on the grid: each cell with a value is a reading of its step at the cell's centre.
    fn frame(&mut self, frame: Frame, now: f64) -> Result<(), (Refusal, String)> {
        let (name, t, values) = frame.map_err(|(name, why)| (Refusal::Malformed, format!("frame {name}: {why}")))?;
        let step = self
            .placer
            .step_at(t, now, self.oldest)
            .map_err(|(kind, why)| (kind, format!("frame {name}: {why}")))?;
        if values.iter().all(Option::is_none) {
            // A camera that saw nothing (cloud throughout, or a frame off the site): no
            // observation at its step, counted so the report can say so.
            self.tally.empty_frames += 1;
            tracing::info!(frame = %name, step, "a frame with no value at any cell: nothing observed at its step");
        }
        self.collected.add_frame(step, &self.placer.grid, &values, self.sigma);
        if let Some(log) = &mut self.log {
            log.write(Entry::Frame { frame: name, t });
        }
        Ok(())
    }

    /// The samples of `steps` for the epoch's batch; later readings of those steps are too old.
    pub fn take(&mut self, steps: Range<u64>) -> Vec<Sample> {
        self.oldest = self.oldest.max(steps.end);
        self.collected.take(steps)
    }

    pub fn counts(&self) -> ReadingCounts {
        ReadingCounts {
            received: self.tally.received,
            accepted: self.tally.accepted,
            refused: self.tally.refusals(),
            empty_frames: self.tally.empty_frames,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_mission::config::DEFAULT_MISSION;

    /// A boat of the default mission on the clock, its log at `log`.
    fn boat(log: &std::path::Path) -> Instrument {
        let text = format!("{DEFAULT_MISSION}\n[time]\nstart = \"2026-11-25T09:00:00Z\"\nstep_s = 1.0\n");
        let mission = MissionConfig::from_toml(&text).unwrap();
        let grid = Grid::new(48, 96, 1.0).unwrap();
        let log = ReadingsLog::open(log, "boat-1").unwrap();
        Instrument::new(&mission, (grid, 100), VehicleKind::Boat, 20, Some(log)).unwrap()
    }

    /// A killed node's readings of the open epochs come back from its log when it restarts.
    #[test]
    fn a_restarted_node_takes_back_the_open_epochs_readings_from_its_log() {
        let dir = std::env::temp_dir().join(format!("hetfleet-readings-log-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("boat-1.readings.ndjson");
        let _ = std::fs::remove_file(&path);
        let start = 1_795_597_200.0;
        let line = |k: u64, x: f64| {
            let site = fleet_mission::site::Site::new([55.6761, 12.5683, 0.0], None, &Grid::new(48, 96, 1.0).unwrap());
            let (lat, lon, _) = site.global_of(&site.ned_of((x, 10.5), 0.0));
            let t = start + k as f64 + 0.5;
            Input::Line(Line::Text(
                format!(r#"{{"t":{t},"lat":{lat},"lon":{lon},"value":{x}}}"#).into_bytes(),
            ))
        };
        let mut before = boat(&path);
        for (k, x) in [(21, 1.5), (22, 2.5), (26, 3.5), (27, 4.5)] {
            before.on_input(line(k, x), start + 30.0);
        }
        before.sync();
        let sent = before.take(20..25);
        drop(before);
        // Restarted after the batch of steps 20..25 went: steps from 25 on are open again.
        let mut after = boat(&path);
        after.reopen(25, start + 30.0);
        let again = after.take(25..30);
        assert_eq!(sent.iter().map(|s| s.step).collect::<Vec<_>>(), vec![21, 22]);
        assert_eq!(
            again.iter().map(|s| (s.step, s.values.clone())).collect::<Vec<_>>(),
            vec![(26, vec![3.5]), (27, vec![4.5])]
        );
        assert_eq!(after.counts().accepted, 0, "taken back, not received again");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
