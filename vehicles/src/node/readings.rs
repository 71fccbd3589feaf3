//! The vehicle node's instrument: lines from its source placed on the grid by the mission's
//! clock and site, kept by step and cell until the epoch's batch takes them, and every refusal
//! counted (in telemetry) and said in the log at most once in a while per kind.

use fleet_mission::config::MissionConfig;
use fleet_mission::grid::Grid;
use fleet_mission::instrument::{parse_line, Collected, Placer, Refusal, Tally};
use fleet_mission::protocol::{ReadingCounts, Sample, VehicleKind};
use std::ops::Range;
use tracing::warn;
use vehicles::sensor::Line;

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

    /// One line from the source, at `now` (UTC seconds).
    pub fn on_line(&mut self, line: Line, now: f64) {
        let placed = match line {
            Line::Text(bytes) => parse_line(&bytes).and_then(|r| self.placer.place(&r, now, self.oldest)),
            Line::Oversized(n) => Err((Refusal::Oversized, format!("a line of {n} bytes"))),
        };
        match placed {
            Ok(p) => {
                self.collected.add(&p, self.sigma);
                self.tally.accept();
            }
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
