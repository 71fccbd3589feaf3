//! The vehicle node's instrument: lines from its source placed on the grid by the mission's
//! clock and site, kept by step and cell until the epoch's batch takes them, and every refusal
//! counted (in telemetry) and said in the log at most once in a while per kind.

use fleet_mission::config::MissionConfig;
use fleet_mission::grid::Grid;
use fleet_mission::instrument::{parse_line, Collected, Placer, Refusal, Tally};
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
}

impl Instrument {
    /// The instrument of a `kind` vehicle whose first sensed step is `first`, or `None` in a
    /// mission without a clock (checked when the source was chosen).
    pub fn new(mission: &MissionConfig, grid: Grid, frames: usize, kind: VehicleKind, first: u64) -> Option<Self> {
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
        })
    }

    /// One line or frame from the source, at `now` (UTC seconds).
    pub fn on_input(&mut self, input: Input, now: f64) {
        let kept = match input {
            Input::Line(Line::Text(bytes)) => parse_line(&bytes)
                .and_then(|r| self.placer.place(&r, now, self.oldest))
                .map(|p| self.collected.add(&p, self.sigma)),
            Input::Line(Line::Oversized(n)) => Err((Refusal::Oversized, format!("a line of {n} bytes"))),
            Input::Frame(frame) => self.frame(frame, now),
            Input::Reading(r) => r
                .and_then(|r| self.placer.place(&r, now, self.oldest))
                .map(|p| self.collected.add(&p, self.sigma)),
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

    /// A frame on the grid: each cell with a value is a reading of its step at the cell's centre.
    fn frame(&mut self, frame: Frame, now: f64) -> Result<(), (Refusal, String)> {
        let (name, t, values) = frame.map_err(|(name, why)| (Refusal::Malformed, format!("frame {name}: {why}")))?;
        let step = self
            .placer
            .step_at(t, now, self.oldest)
            .map_err(|(kind, why)| (kind, format!("frame {name}: {why}")))?;
        let grid = self.placer.grid;
        for (cell, v) in values.iter().enumerate().filter_map(|(c, v)| Some((c, (*v)?))) {
            let position = grid.centre_m(grid.cell(cell));
            let p = fleet_mission::instrument::Placed {
                step,
                cell,
                position,
                value: v,
                sigma: None,
            };
            self.collected.add(&p, self.sigma);
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
        }
    }
}
