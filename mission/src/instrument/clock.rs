//! Mission time (`[time]` in the mission file): a step is `step_s` seconds of UTC from
//! `start`, so a reading's time says which step it belongs to, and an epoch closes by the
//! clock. Without `[time]`, steps are the simulator's counter (`[pace] step_ms`) and only the
//! `sim` sensor source can be used.

use serde::{Deserialize, Serialize};

/// The mission's `[time]` table as written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TimeConfig {
    /// The start of step 0, RFC 3339 in UTC (`"2026-11-25T09:00:00Z"`).
    pub start: String,
    /// Seconds per step.
    pub step_s: f64,
}

/// Step `k` covers UTC seconds `[start + k step_s, start + (k + 1) step_s)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MissionClock {
    /// Seconds since 1970 (UTC) of the start of step 0.
    pub start: f64,
    pub step_s: f64,
}

impl MissionClock {
    /// The clock of a `[time]` table; the error names the key and says what is wrong.
    pub fn of(t: &TimeConfig) -> Result<Self, (&'static str, String)> {
        let start: jiff::Timestamp = t
            .start
            .parse()
            .map_err(|e| ("start", format!("{:?} is not an RFC 3339 UTC time ({e})", t.start)))?;
        if !(t.step_s.is_finite() && t.step_s > 0.0) {
            return Err(("step_s", format!("{} must be a number of seconds > 0", t.step_s)));
        }
        Ok(Self {
            start: start.as_millisecond() as f64 / 1e3,
            step_s: t.step_s,
        })
    }

    /// The step UTC time `t` falls in (`None` before the start or not a number).
    pub fn step_of(&self, t: f64) -> Option<u64> {
        let k = ((t - self.start) / self.step_s).floor();
        (k.is_finite() && k >= 0.0 && k < u64::MAX as f64).then_some(k as u64)
    }

    /// When step `k` starts (UTC seconds).
    pub fn time_of(&self, k: u64) -> f64 {
        self.start + k as f64 * self.step_s
    }

    /// The clock as RFC 3339 (for files and logs).
    pub fn rfc3339(t: f64) -> String {
        jiff::Timestamp::from_millisecond((t * 1e3).round() as i64)
            .map(|ts| ts.to_string())
            .unwrap_or_else(|_| format!("{t} s"))
    }

    /// Seconds since 1970 now, by this machine's clock.
    pub fn now() -> f64 {
        jiff::Timestamp::now().as_millisecond() as f64 / 1e3
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn clock() -> MissionClock {
        MissionClock::of(&TimeConfig {
            start: "2026-11-25T09:00:00Z".into(),
            step_s: 2.0,
        })
        .unwrap()
    }

    #[test]
    fn steps_are_half_open_intervals_of_utc() {
        let c = clock();
        // 2026-11-25T09:00:00Z is 1795597200 s after 1970 (date -u -d ... +%s).
        assert_eq!(c.start, 1_795_597_200.0);
        assert_eq!(c.step_of(c.start), Some(0));
        assert_eq!(c.step_of(c.start + 1.999), Some(0));
        assert_eq!(c.step_of(c.start + 2.0), Some(1));
        assert_eq!(c.step_of(c.start - 0.001), None);
        assert_eq!(c.step_of(f64::NAN), None);
        assert_eq!(c.time_of(3), c.start + 6.0);
        assert_eq!(MissionClock::rfc3339(c.time_of(3)), "2026-11-25T09:00:06Z");
    }

    #[test]
    fn a_bad_table_names_its_key() {
        let bad = |start: &str, step_s: f64| {
            MissionClock::of(&TimeConfig {
                start: start.into(),
                step_s,
            })
            .unwrap_err()
            .0
        };
        assert_eq!(bad("yesterday", 1.0), "start");
        assert_eq!(bad("2026-11-25T09:00:00Z", 0.0), "step_s");
        assert_eq!(bad("2026-11-25T09:00:00Z", f64::INFINITY), "step_s");
    }
}
