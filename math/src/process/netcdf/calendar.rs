//! A CF time coordinate's numbers as dates, in the calendar the file names (CF 1.11, 4.4.2):
//! `standard`/`gregorian` (Julian before 1582-10-15, Gregorian from it), `proleptic_gregorian`,
//! `julian`, `noleap`/`365_day`, `all_leap`/`366_day` and `360_day`, as cftime (xarray's
//! decoder for every calendar) gives them. A climate model's year of 360 days has a 30th of
//! February, and its dates are not the standard calendar's.
//!
//! A day is 86,400 s in every calendar (CF has no leap seconds), so a step's length is the same
//! in all of them; only the date a number names differs.

/// A time axis as its file gives it: `units` (`"<unit> since <date>"`), `calendar` ("" is
/// CF's default, `standard`) and the coordinate's numbers, one per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TimeAxis {
    pub units: String,
    pub calendar: String,
    pub values: Vec<f64>,
}

impl TimeAxis {
    /// The date of `value` (`YYYY-MM-DD hh:mm:ss`, CF's own form) in the axis's calendar;
    /// `None` where the units or the calendar name no date (`none`, units without `since`, a
    /// reference date with a time-zone offset, which would move every date in silence).
    pub fn date_of(&self, value: f64) -> Option<String> {
        let (unit_s, epoch) = parse_units(&self.units)?;
        let cal = Calendar::named(&self.calendar)?;
        let seconds = cal.seconds_of(epoch) + value * unit_s;
        seconds.is_finite().then(|| cal.format(seconds))
    }

    /// The calendar's name as CF writes it (`standard` where the file gives none).
    pub fn calendar_name(&self) -> String {
        match self.calendar.trim() {
            "" => "standard".into(),
            c => c.to_ascii_lowercase(),
        }
    }
}

/// A calendar: how many days each month of each year has.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Calendar {
    /// Julian before 1582-10-15, Gregorian from it (the default).
    Standard,
    ProlepticGregorian,
    Julian,
    /// Every year of the length, February 28 or 29 days.
    Fixed(u32),
    /// Twelve months of 30 days.
    Day360,
}

/// `(year, month, day, seconds into the day)`.
type Date = (i64, u32, u32, f64);

/// Julian day number of the first Gregorian day, 1582-10-15.
const GREGORIAN_START: i64 = 2_299_161;

impl Calendar {
    fn named(name: &str) -> Option<Self> {
        Some(match name.trim().to_ascii_lowercase().as_str() {
            "" | "standard" | "gregorian" => Self::Standard,
            "proleptic_gregorian" => Self::ProlepticGregorian,
            "julian" => Self::Julian,
            "noleap" | "365_day" => Self::Fixed(365),
            "all_leap" | "366_day" => Self::Fixed(366),
            "360_day" => Self::Day360,
            _ => return None,
        })
    }

    /// Seconds from the calendar's own day 0 to `date`.
    fn seconds_of(self, (y, m, d, s): Date) -> f64 {
        self.day_number(y, m, d) as f64 * 86_400.0 + s
    }

    fn day_number(self, y: i64, m: u32, d: u32) -> i64 {
        match self {
            Self::Day360 => y * 360 + i64::from((m - 1) * 30 + d - 1),
            Self::Fixed(len) => y * i64::from(len) + i64::from(month_start(m, len == 366) + d - 1),
            Self::Julian => jdn_julian(y, m, d),
            Self::ProlepticGregorian => jdn_gregorian(y, m, d),
            Self::Standard => match jdn_gregorian(y, m, d) {
                n if n >= GREGORIAN_START => n,
                _ => jdn_julian(y, m, d),
            },
        }
    }

    /// The date `seconds` from day 0, formatted.
    fn format(self, seconds: f64) -> String {
        let day = (seconds / 86_400.0).floor();
        let in_day = ((seconds - day * 86_400.0) * 1e6).round() / 1e6;
        let (y, m, d) = self.date_of_day(day as i64);
        let s = in_day.round() as i64;
        format!("{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
    }

    fn date_of_day(self, n: i64) -> (i64, u32, u32) {
        match self {
            Self::Day360 => {
                let (y, r) = (n.div_euclid(360), n.rem_euclid(360) as u32);
                (y, r / 30 + 1, r % 30 + 1)
            }
            Self::Fixed(len) => {
                let (y, r) = (n.div_euclid(i64::from(len)), n.rem_euclid(i64::from(len)) as u32);
                let m = (1..=12).rev().find(|&m| month_start(m, len == 366) <= r).unwrap_or(1);
                (y, m, r - month_start(m, len == 366) + 1)
            }
            Self::Julian => from_jdn(n, false),
            Self::ProlepticGregorian => from_jdn(n, true),
            Self::Standard => from_jdn(n, n >= GREGORIAN_START),
        }
    }
}

/// Days of the year before month `m` (1-12) in a year of 365 days, or 366 when `leap`.
fn month_start(m: u32, leap: bool) -> u32 {
    const START: [u32; 12] = [0, 31, 59, 90, 120, 151, 181, 212, 243, 273, 304, 334];
    START[(m.clamp(1, 12) - 1) as usize] + u32::from(leap && m > 2)
}

/// Julian day number of a Gregorian date (Fliegel and Van Flandern, 1968, in whole days).
fn jdn_gregorian(y: i64, m: u32, d: u32) -> i64 {
    let (y, m) = march_based(y, m);
    i64::from(d) + (153 * m + 2) / 5 + 365 * y + y.div_euclid(4) - y.div_euclid(100) + y.div_euclid(400) - 32_045
}

/// Julian day number of a Julian-calendar date.
fn jdn_julian(y: i64, m: u32, d: u32) -> i64 {
    let (y, m) = march_based(y, m);
    i64::from(d) + (153 * m + 2) / 5 + 365 * y + y.div_euclid(4) - 32_083
}

/// The year counted from March of 4801 BC and the month from March (0-11: February is last,
/// so a leap day falls at a year's end).
fn march_based(y: i64, m: u32) -> (i64, i64) {
    let a = (14 - i64::from(m)) / 12;
    (y + 4800 - a, i64::from(m) + 12 * a - 3)
}

/// The date of Julian day number `n`, Gregorian or Julian (Richards' algorithm).
fn from_jdn(n: i64, gregorian: bool) -> (i64, u32, u32) {
    let f = match gregorian {
        true => n + 1401 + (((4 * n + 274_277).div_euclid(146_097)) * 3).div_euclid(4) - 38,
        false => n + 1401,
    };
    let e = 4 * f + 3;
    let h = 5 * (e.rem_euclid(1461) / 4) + 2;
    let d = h.rem_euclid(153) / 5 + 1;
    let m = (h.div_euclid(153) + 2).rem_euclid(12) + 1;
    let y = e.div_euclid(1461) - 4716 + (14 - m) / 12;
    (y, m as u32, d as u32)
}

/// `"<unit> since <date>"`: seconds per unit and the reference date; `None` for anything else.
fn parse_units(units: &str) -> Option<(f64, Date)> {
    let (unit, date) = units.split_once(" since ")?;
    let unit_s = match unit.trim().to_ascii_lowercase().as_str() {
        "days" | "day" | "d" => 86_400.0,
        "hours" | "hour" | "hr" | "h" => 3_600.0,
        "minutes" | "minute" | "min" => 60.0,
        "seconds" | "second" | "sec" | "s" => 1.0,
        "milliseconds" | "millisecond" | "ms" => 1e-3,
        _ => return None,
    };
    Some((unit_s, parse_date(date.trim())?))
}

/// `Y-M-D`, then optionally `[T ]h:m[:s[.f]]` and `Z` or `UTC`; an offset from UTC is `None`.
fn parse_date(text: &str) -> Option<Date> {
    let text = text.trim_end_matches('Z').trim_end_matches("UTC").trim();
    let (day, time) = match text.split_once(['T', ' ']) {
        Some((d, t)) => (d, t.trim()),
        None => (text, ""),
    };
    let (sign, day) = match day.strip_prefix('-') {
        Some(rest) => (-1, rest),
        None => (1, day),
    };
    let mut ymd = day.split('-');
    let y: i64 = ymd.next()?.parse().ok()?;
    let m: u32 = ymd.next().unwrap_or("1").parse().ok()?;
    let d: u32 = ymd.next().unwrap_or("1").parse().ok()?;
    if ymd.next().is_some() || !(1..=12).contains(&m) || !(1..=31).contains(&d) {
        return None;
    }
    let mut seconds = 0.0;
    if !time.is_empty() {
        let mut hms = time.split(':');
        for scale in [3600.0, 60.0, 1.0] {
            if let Some(part) = hms.next() {
                seconds += part.parse::<f64>().ok()? * scale;
            }
        }
        if hms.next().is_some() {
            return None;
        }
    }
    Some((sign * y, m, d, seconds))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn date(units: &str, calendar: &str, value: f64) -> Option<String> {
        let axis = TimeAxis {
            units: units.into(),
            calendar: calendar.into(),
            values: vec![],
        };
        axis.date_of(value)
    }

    /// Dates with known answers in each calendar (as cftime gives them).
    #[test]
    fn each_calendar_counts_its_own_days() {
        let d = |cal, v| date("days since 2000-01-01", cal, v).unwrap();
        // 59 days after 1 January: 29 February in a leap year, 1 March without one.
        assert_eq!(d("standard", 59.0), "2000-02-29 00:00:00");
        assert_eq!(d("noleap", 59.0), "2000-03-01 00:00:00");
        assert_eq!(d("all_leap", 59.0), "2000-02-29 00:00:00");
        // 360_day: a month is 30 days, February too; a year is 360.
        assert_eq!(d("360_day", 59.0), "2000-02-30 00:00:00");
        assert_eq!(d("360_day", 360.0), "2001-01-01 00:00:00");
        // 1900 is a leap year only in the Julian calendar.
        let h = |cal| date("days since 1900-02-28", cal, 1.0).unwrap();
        assert_eq!(h("julian"), "1900-02-29 00:00:00");
        assert_eq!(h("proleptic_gregorian"), "1900-03-01 00:00:00");
        assert_eq!(h("gregorian"), "1900-03-01 00:00:00");
        // The standard calendar skips from 4 to 15 October 1582; the proleptic one does not.
        let g = |cal| date("days since 1582-10-04", cal, 1.0).unwrap();
        assert_eq!(g("standard"), "1582-10-15 00:00:00");
        assert_eq!(g("proleptic_gregorian"), "1582-10-05 00:00:00");
        // Hours, a reference time of day, and CF's short date forms.
        assert_eq!(
            date("hours since 1-1-1 00:00:0.0", "noleap", 36.0).unwrap(),
            "0001-01-02 12:00:00"
        );
        assert_eq!(
            date("seconds since 1970-01-01T00:00:00Z", "", 86_399.0).unwrap(),
            "1970-01-01 23:59:59"
        );
        // 2024-01-01 is 19,723 days after 1970-01-01 (the Unix epoch).
        assert_eq!(
            date("days since 1970-01-01", "standard", 19_723.0).unwrap(),
            "2024-01-01 00:00:00"
        );
        // Days before the reference date.
        assert_eq!(
            date("days since 2000-01-01", "360_day", -1.0).unwrap(),
            "1999-12-30 00:00:00"
        );
    }

    #[test]
    fn what_names_no_date_gives_none() {
        assert_eq!(date("s", "standard", 1.0), None);
        assert_eq!(date("days since 2000-01-01", "none", 1.0), None);
        assert_eq!(date("days since 2000-01-01 00:00 +06:00", "standard", 1.0), None);
        assert_eq!(date("fortnights since 2000-01-01", "standard", 1.0), None);
    }

    /// Every day of four centuries in every calendar goes to its date and back to its number.
    #[test]
    fn day_numbers_and_dates_are_inverse() {
        for cal in [
            "standard",
            "proleptic_gregorian",
            "julian",
            "noleap",
            "all_leap",
            "360_day",
        ] {
            let c = Calendar::named(cal).unwrap();
            let start = c.day_number(1800, 1, 1);
            for n in start..start + 146_097 {
                let (y, m, d) = c.date_of_day(n);
                assert_eq!(c.day_number(y, m, d), n, "{cal}: {y}-{m}-{d}");
            }
        }
    }
}
