//! Readings that arrive as MAVLink NAMED_VALUE_FLOAT on the vehicle's autopilot link (what an
//! ArduPilot Lua script's `gcs:send_named_float` or a companion computer sends): a value and
//! the autopilot's boot time, nothing else. Where it was taken is the autopilot's position at
//! that time (GLOBAL_POSITION_INT, interpolated between the two fixes around it), and when in
//! UTC is the autopilot's clock through SYSTEM_TIME (`time_unix_usec` against `time_boot_ms`).
//!
//! A value usually arrives before the fix that follows it, so it waits (bounded) until a fix at
//! or after its time has come; a value that cannot be placed is refused: no fix within
//! [`MAX_GAP_MS`] of it (`no_fix`), no UTC from the autopilot yet (`no_time`: SYSTEM_TIME says 0
//! until its GPS has time), stamped well after the autopilot's clock (`from_future`), not finite
//! (`not_finite`). Pure: the bridge hands it the three
//! messages as numbers, in the order they came.

use super::reading::{Reading, Refusal};
use std::collections::VecDeque;

/// The widest gap between two fixes a value may be interpolated across, and how long (by the
/// autopilot's clock) a value waits for a fix after it or for UTC.
pub const MAX_GAP_MS: u32 = 2_000;
/// Fixes kept (the last 10 s at ArduPilot's fastest stream rate of 50 Hz).
const FIXES: usize = 512;
/// Values waiting for their fix or for UTC, at most: beyond it the oldest is refused.
const WAITING: usize = 1024;

/// What a value became: a reading to place, or why it was refused.
pub type Outcome = Result<Reading, (Refusal, String)>;

/// One autopilot's fixes and clock, and the values waiting for them.
#[derive(Debug, Clone, Default)]
pub struct NamedValues {
    /// `(time_boot_ms, lat, lon)`, oldest first.
    fixes: VecDeque<(u32, f64, f64)>,
    /// UTC seconds at boot (SYSTEM_TIME's `time_unix_usec` less its `time_boot_ms`).
    boot_utc: Option<f64>,
    /// `(time_boot_ms, value)`, as they came.
    waiting: VecDeque<(u32, f64)>,
    /// The newest boot time the autopilot said (its fixes and SYSTEM_TIME).
    latest_ms: u32,
}

impl NamedValues {
    /// A value of the instrument's name, taken at the autopilot's `time_boot_ms`.
    pub fn on_value(&mut self, time_boot_ms: u32, value: f32) -> Vec<Outcome> {
        if !value.is_finite() {
            return vec![Err((Refusal::NotFinite, format!("NAMED_VALUE_FLOAT {value}")))];
        }
        let mut out = vec![];
        if self.latest_ms > 0 && time_boot_ms > self.latest_ms.saturating_add(MAX_GAP_MS) {
            let ahead = time_boot_ms - self.latest_ms;
            return vec![Err((
                Refusal::FromFuture,
                format!("stamped {ahead} ms after the autopilot's clock"),
            ))];
        }
        if self.waiting.len() == WAITING {
            let (b, _) = self.waiting.pop_front().expect("a full queue");
            out.push(Err((
                Refusal::NoFix,
                format!("a value at boot time {b} ms waited too long for a fix (more than {WAITING} waiting)"),
            )));
        }
        self.waiting.push_back((time_boot_ms, value as f64));
        out.extend(self.release());
        out
    }

    /// The autopilot's GLOBAL_POSITION_INT (degrees times 1e7; 0, 0 is "no position", as
    /// ArduPilot sends before it has one).
    pub fn on_fix(&mut self, time_boot_ms: u32, lat_e7: i32, lon_e7: i32) -> Vec<Outcome> {
        let mut out = vec![];
        self.seen(time_boot_ms, &mut out);
        if (lat_e7, lon_e7) != (0, 0) && self.fixes.back().is_none_or(|f| f.0 < time_boot_ms) {
            if self.fixes.len() == FIXES {
                self.fixes.pop_front();
            }
            self.fixes
                .push_back((time_boot_ms, lat_e7 as f64 / 1e7, lon_e7 as f64 / 1e7));
        }
        out.extend(self.release());
        out
    }

    /// The autopilot's SYSTEM_TIME (`time_unix_usec` 0: it has no UTC yet).
    pub fn on_time(&mut self, time_unix_usec: u64, time_boot_ms: u32) -> Vec<Outcome> {
        let mut out = vec![];
        self.seen(time_boot_ms, &mut out);
        if time_unix_usec > 0 {
            self.boot_utc = Some(time_unix_usec as f64 / 1e6 - time_boot_ms as f64 / 1e3);
        }
        out.extend(self.release());
        out
    }

    /// Values waiting, now.
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }

    /// The autopilot's clock said `ms`: a clock that went back is an autopilot that restarted,
    /// and what was known of the old boot is forgotten (its waiting values refused). (A value's
    /// stamp is not the autopilot's word: it never moves the clock.)
    fn seen(&mut self, ms: u32, out: &mut Vec<Outcome>) {
        if ms.saturating_add(MAX_GAP_MS) < self.latest_ms {
            let why = "the autopilot restarted (its boot time went back) before this value could be placed";
            out.extend(self.waiting.drain(..).map(|_| Err((Refusal::NoFix, why.to_string()))));
            self.fixes.clear();
            self.boot_utc = None;
            self.latest_ms = ms;
        }
        self.latest_ms = self.latest_ms.max(ms);
    }

    /// The waiting values that can be placed now, or refused now, in order; the rest wait.
    fn release(&mut self) -> Vec<Outcome> {
        let mut out = vec![];
        while let Some(&(b, value)) = self.waiting.front() {
            let overdue = self.latest_ms.saturating_sub(b) > MAX_GAP_MS;
            let outcome = match (self.boot_utc, self.position_at(b)) {
                (Some(utc), Some(Ok((lat, lon)))) => Ok(Reading {
                    t: utc + b as f64 / 1e3,
                    lat,
                    lon,
                    value,
                    sigma: None,
                }),
                (_, Some(Err(why))) => Err((Refusal::NoFix, why)),
                (None, _) if overdue => Err((
                    Refusal::NoTime,
                    "no UTC from the autopilot (SYSTEM_TIME's time_unix_usec is 0 until its GPS has time)".into(),
                )),
                (_, None) if overdue => Err((
                    Refusal::NoFix,
                    format!("no position fix within {MAX_GAP_MS} ms after it"),
                )),
                _ => break,
            };
            self.waiting.pop_front();
            out.push(outcome);
        }
        out
    }

    /// The position at boot time `b`: interpolated between the fixes around it, an error when
    /// they are too far apart or `b` is before them, `None` while no fix at or after `b` has come.
    fn position_at(&self, b: u32) -> Option<Result<(f64, f64), String>> {
        let after = self.fixes.iter().position(|f| f.0 >= b)?;
        let (t1, lat1, lon1) = self.fixes[after];
        if t1 == b {
            return Some(Ok((lat1, lon1)));
        }
        let Some(&(t0, lat0, lon0)) = after.checked_sub(1).map(|i| &self.fixes[i]) else {
            return Some(Err(format!("no position fix before boot time {b} ms")));
        };
        if t1 - t0 > MAX_GAP_MS {
            return Some(Err(format!(
                "the fixes around it are {} ms apart (at most {MAX_GAP_MS})",
                t1 - t0
            )));
        }
        let w = (b - t0) as f64 / (t1 - t0) as f64;
        Some(Ok((lat0 + w * (lat1 - lat0), lon0 + w * (lon1 - lon0))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOOT_UTC_US: u64 = 1_795_597_200_000_000;

    fn placed(o: &[Outcome]) -> Vec<Reading> {
        o.iter().map(|r| *r.as_ref().expect("placed")).collect()
    }

    fn kinds(o: &[Outcome]) -> Vec<Refusal> {
        o.iter().map(|r| r.as_ref().expect_err("refused").0).collect()
    }

    #[test]
    fn a_value_is_placed_between_the_fixes_around_it_and_timed_by_system_time() {
        let mut n = NamedValues::default();
        assert!(n.on_time(BOOT_UTC_US + 1_000_000, 1_000).is_empty());
        assert!(n.on_fix(1_000, 550_000_000, 120_000_000).is_empty());
        // A value at 1250 ms waits for the fix after it.
        assert!(n.on_value(1_250, 0.5).is_empty());
        assert_eq!(n.waiting(), 1);
        let r = placed(&n.on_fix(1_500, 550_001_000, 120_002_000));
        // Half way from the first fix to the second: (1250 - 1000) / (1500 - 1000).
        assert_eq!(r.len(), 1);
        assert!((r[0].lat - 55.00005).abs() < 1e-12 && (r[0].lon - 12.0001).abs() < 1e-12);
        assert!((r[0].t - (1_795_597_200.0 + 1.25)).abs() < 1e-6);
        assert_eq!((r[0].value, r[0].sigma), (0.5, None));
        // A value at a fix's own time is placed at once.
        let r = placed(&n.on_value(1_500, 2.0));
        assert!((r[0].lat - 55.0001).abs() < 1e-12);
    }

    #[test]
    fn values_that_cannot_be_placed_are_refused_with_their_reason() {
        let mut n = NamedValues::default();
        n.on_fix(1_000, 550_000_000, 120_000_000);
        // No UTC: the value waits, then is refused once the autopilot's clock is well past it.
        assert!(n.on_value(1_000, 1.0).is_empty());
        assert_eq!(kinds(&n.on_time(0, 3_100)), vec![Refusal::NoTime]);
        n.on_time(BOOT_UTC_US + 3_100_000, 3_100);
        // Before every fix kept.
        assert_eq!(kinds(&n.on_value(900, 1.0)), vec![Refusal::NoFix]);
        // Fixes 5 s apart: a GPS outage between them.
        n.on_fix(6_000, 550_000_000, 120_000_000);
        assert_eq!(kinds(&n.on_value(3_000, 1.0)), vec![Refusal::NoFix]);
        // No fix after it for more than the gap.
        assert!(n.on_value(6_200, 1.0).is_empty());
        assert_eq!(kinds(&n.on_time(BOOT_UTC_US + 8_300_000, 8_300)), vec![Refusal::NoFix]);
        assert_eq!(kinds(&n.on_value(8_300, f32::NAN)), vec![Refusal::NotFinite]);
        assert_eq!(kinds(&n.on_value(8_300 + 3_600_000, 1.0)), vec![Refusal::FromFuture]);
        // A value stamped long ago is no restart of the autopilot: the fixes stay.
        assert_eq!(kinds(&n.on_value(1, 1.0)), vec![Refusal::NoFix]);
        // "No position" (0, 0) is not a fix.
        n.on_value(8_400, 1.0);
        assert!(n.on_fix(8_500, 0, 0).is_empty());
        assert_eq!(n.waiting(), 1);
    }

    #[test]
    fn a_restarted_autopilot_forgets_its_old_boot_and_the_queue_is_bounded() {
        let mut n = NamedValues::default();
        n.on_time(BOOT_UTC_US, 100_000);
        n.on_fix(100_000, 550_000_000, 120_000_000);
        n.on_value(100_050, 1.0);
        assert_eq!(kinds(&n.on_fix(500, 550_000_000, 120_000_000)), vec![Refusal::NoFix]);
        // The old boot's UTC is gone: a new value waits for a SYSTEM_TIME of the new boot.
        assert!(n.on_value(500, 1.0).is_empty());
        assert_eq!(placed(&n.on_time(BOOT_UTC_US, 600)).len(), 1);
        let mut m = NamedValues::default();
        let refused: usize = (0..WAITING as u32 + 10).map(|i| m.on_value(i / 100, 1.0).len()).sum();
        assert_eq!((refused, m.waiting()), (10, WAITING));
    }
}
