//! Where a reading lands: the step of its time (by the mission's clock) and the cell of its
//! position (by the site's placement on the Earth), or why it cannot be used.

use super::clock::MissionClock;
use super::reading::{Reading, Refusal};
use crate::fence::{inside, SiteFence};
use crate::site::Site;
use fleet_math::grid::Grid;

/// How far ahead of this machine's clock a reading may be timed (an instrument's clock a
/// little fast, or a reading taken as the step turns).
pub const FUTURE_SLACK_S: f64 = 2.0;

/// A reading on the model grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placed {
    pub step: u64,
    pub cell: usize,
    /// Grid metres `(x east, y north)` of the grid's (0, 0) corner.
    pub position: (f64, f64),
    pub value: f64,
    pub sigma: Option<f64>,
}

/// What placing a reading needs to know of the mission.
#[derive(Debug, Clone)]
pub struct Placer {
    pub site: Site,
    pub grid: Grid,
    pub fence: Option<SiteFence>,
    pub clock: MissionClock,
    /// Steps in the mission: a reading timed after the last is refused.
    pub frames: u64,
}

impl Placer {
    /// The step of time `t` at `now` with the oldest open step `oldest`, or why it is refused.
    pub fn step_at(&self, t: f64, now: f64, oldest: u64) -> Result<u64, (Refusal, String)> {
        if t > now + FUTURE_SLACK_S {
            let ahead = t - now;
            return Err((
                Refusal::FromFuture,
                format!("timed {ahead:.1} s after this machine's clock"),
            ));
        }
        let Some(step) = self.clock.step_of(t) else {
            return Err((Refusal::TooOld, "timed before the mission's start".into()));
        };
        if step >= self.frames {
            return Err((Refusal::FromFuture, format!("step {step} is after the mission's last")));
        }
        if step < oldest {
            return Err((Refusal::TooOld, format!("step {step}: steps before {oldest} are sent")));
        }
        Ok(step)
    }

    /// The reading's step and cell at `now` (UTC seconds) with the oldest step still open
    /// `oldest` (readings before it are too old: their batch has gone).
    /// Where comes before when: a reading off the site is `outside_site` whenever it was taken.
    pub fn place(&self, r: &Reading, now: f64, oldest: u64) -> Result<Placed, (Refusal, String)> {
        let ned = self.site.ned_of_global(r.lat, r.lon, self.site.origin[2]);
        let (x, y) = self.site.grid_of(&ned);
        let Some(cell) = self.grid.cell_at(x, y) else {
            return Err((Refusal::OutsideSite, format!("({}, {}) is off the site", r.lat, r.lon)));
        };
        if let Some(f) = &self.fence {
            if !inside(&f.polygon_m, [ned.y, ned.x]) {
                return Err((
                    Refusal::OutsideFence,
                    format!("({}, {}) is outside the fence", r.lat, r.lon),
                ));
            }
        }
        let step = self.step_at(r.t, now, oldest)?;
        Ok(Placed {
            step,
            cell: self.grid.index(cell),
            position: (x, y),
            value: r.value,
            sigma: r.sigma,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn placer(fence: Option<SiteFence>) -> Placer {
        let grid = Grid::new(10, 20, 1.0).unwrap();
        Placer {
            site: Site::new([55.0, 12.0, 0.0], Some([200.0, 100.0]), &grid),
            grid,
            fence,
            clock: MissionClock {
                start: 1000.0,
                step_s: 10.0,
            },
            frames: 50,
        }
    }

    /// The reading at grid metres `(x, y)` and time `t`.
    fn at(p: &Placer, x: f64, y: f64, t: f64) -> Reading {
        let (lat, lon, _) = p.site.global_of(&p.site.ned_of((x, y), 0.0));
        Reading {
            t,
            lat,
            lon,
            value: 1.5,
            sigma: None,
        }
    }

    #[test]
    fn a_reading_lands_in_the_step_of_its_time_and_the_cell_of_its_position() {
        let p = placer(None);
        // Grid metres (3.5, 7.5) is row 7, column 3 on a 10 x 20 grid of 1 m cells.
        let placed = p.place(&at(&p, 3.5, 7.5, 1025.0), 1030.0, 0).unwrap();
        assert_eq!((placed.step, placed.cell), (2, 7 * 20 + 3));
        assert!((placed.position.0 - 3.5).abs() < 1e-6 && (placed.position.1 - 7.5).abs() < 1e-6);
    }

    #[test]
    fn readings_out_of_time_or_place_are_refused() {
        let fence = SiteFence {
            polygon_m: vec![[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0]],
            size_m: Some([200.0, 100.0]),
        };
        let p = placer(Some(fence));
        let kind = |r: Reading, now: f64, oldest: u64| p.place(&r, now, oldest).unwrap_err().0;
        assert_eq!(kind(at(&p, 3.5, 7.5, 1040.0), 1030.0, 0), Refusal::FromFuture);
        assert_eq!(kind(at(&p, 3.5, 7.5, 999.0), 1030.0, 0), Refusal::TooOld);
        assert_eq!(kind(at(&p, 3.5, 7.5, 1005.0), 1030.0, 1), Refusal::TooOld);
        assert_eq!(kind(at(&p, 3.5, 7.5, 1600.0), 2000.0, 0), Refusal::FromFuture);
        assert_eq!(kind(at(&p, -0.5, 7.5, 1005.0), 1030.0, 0), Refusal::OutsideSite);
        assert_eq!(kind(at(&p, 3.5, 10.5, 1005.0), 1030.0, 0), Refusal::OutsideSite);
        // East of 100 physical metres is grid x > 10: on the grid, outside the fence.
        assert_eq!(kind(at(&p, 12.5, 5.5, 1005.0), 1030.0, 0), Refusal::OutsideFence);
        assert!(
            p.place(&at(&p, 9.5, 5.5, 1031.0), 1030.0, 0).is_ok(),
            "within the clock's slack"
        );
    }
}
