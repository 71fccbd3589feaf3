//! One reading on the wire (newline-delimited JSON, the module's interface) and every reason
//! one is refused. A reading is refused, counted and never assimilated; nothing an instrument
//! sends can panic the node.

use serde::{Deserialize, Serialize};

/// The longest line taken (bytes, without the newline): a reading is under 200 bytes; a
/// source reads at most this much of a line and refuses the rest as `oversized` without
/// holding it.
pub const MAX_LINE: usize = 4096;

/// A reading as the instrument said it (and as a readings log keeps it: serde_json writes each
/// number so that it reads back to the same bits).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Reading {
    /// UTC seconds since 1970.
    pub t: f64,
    /// WGS 84 degrees; NaN when the line had no position (missing or null).
    #[serde(default = "no_fix", deserialize_with = "fix")]
    pub lat: f64,
    #[serde(default = "no_fix", deserialize_with = "fix")]
    pub lon: f64,
    pub value: f64,
    /// Noise standard deviation (`None`: the mission's for the vehicle's kind).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<f64>,
}

fn no_fix() -> f64 {
    f64::NAN
}

/// A coordinate, or NaN for `null` (JSON has no NaN of its own, so NaN means "no fix").
fn fix<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Why a reading is refused: each kind is counted apart (in telemetry and the server's
/// status) and logged at most once in a while.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, strum::Display, strum::EnumIter, strum::IntoStaticStr,
)]
#[strum(serialize_all = "snake_case")]
pub enum Refusal {
    /// Not JSON, or not one object on one line.
    Malformed,
    /// JSON, but a field is missing or of the wrong type (`"value": "high"`).
    WrongType,
    /// A time, position or value that is not a finite number.
    NotFinite,
    /// `sigma` not a finite number of at least [`fleet_math::process::units::SMALLEST_NOISE`] (below,
    /// the estimator's variance floor is not negligible beside it: a reading so sure of itself
    /// would be taken as exact).
    BadSigma,
    /// A line longer than [`MAX_LINE`].
    Oversized,
    /// No position (`lat`/`lon` missing or null; a MAVLink value without a position fix).
    NoFix,
    /// Outside the site's extent (the model grid).
    OutsideSite,
    /// Inside the grid but outside the site's fence.
    OutsideFence,
    /// Timed after now (beyond the clock's tolerance).
    FromFuture,
    /// Timed before the oldest epoch still open (its batch has gone), or before the mission.
    TooOld,
    /// A MAVLink value while the autopilot has no UTC (SYSTEM_TIME's `time_unix_usec` is 0).
    NoTime,
    /// Readings came faster than the node takes them and its queue was full (a flood).
    Overflow,
}

/// Parse one line (without its newline). Fields beyond the five are ignored (drivers may add
/// their own), so a driver can carry more than hetfleet reads.
pub fn parse_line(line: &[u8]) -> Result<Reading, (Refusal, String)> {
    if line.len() > MAX_LINE {
        return Err((Refusal::Oversized, format!("{} bytes (at most {MAX_LINE})", line.len())));
    }
    let r: Reading = serde_json::from_slice(line).map_err(|e| {
        use serde_json::error::Category;
        match e.classify() {
            Category::Data => (Refusal::WrongType, e.to_string()),
            _ => (Refusal::Malformed, e.to_string()),
        }
    })?;
    let (lat, lon) = (r.lat, r.lon);
    if lat.is_nan() || lon.is_nan() {
        return Err((Refusal::NoFix, "no lat/lon".into()));
    }
    if ![r.t, lat, lon, r.value].iter().all(|x| x.is_finite()) {
        return Err((Refusal::NotFinite, "t, lat, lon and value must be finite".into()));
    }
    if !(-90.0..=90.0).contains(&lat) || !(-180.0..=180.0).contains(&lon) {
        return Err((Refusal::OutsideSite, format!("({lat}, {lon}) is not a WGS 84 position")));
    }
    if let Some(s) = r.sigma {
        if !(s.is_finite() && s >= fleet_math::process::units::SMALLEST_NOISE) {
            let least = fleet_math::process::units::SMALLEST_NOISE;
            return Err((Refusal::BadSigma, format!("sigma {s} must be at least {least:e}")));
        }
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kind(line: &str) -> Refusal {
        parse_line(line.as_bytes()).unwrap_err().0
    }

    #[test]
    fn the_documented_line_parses() {
        let r = parse_line(br#"{"t": 1795000000.25, "lat": -33.8601, "lon": 151.2101, "value": 0.42, "sigma": 0.01}"#)
            .unwrap();
        assert_eq!(
            r,
            Reading {
                t: 1795000000.25,
                lat: -33.8601,
                lon: 151.2101,
                value: 0.42,
                sigma: Some(0.01)
            }
        );
        let r = parse_line(br#"{"t":1,"lat":0,"lon":0,"value":-3,"depth_m":0.5}"#).unwrap();
        assert_eq!((r.sigma, r.value), (None, -3.0));
    }

    #[test]
    fn every_bad_line_is_refused_with_its_kind() {
        assert_eq!(kind("not json"), Refusal::Malformed);
        assert_eq!(
            kind(r#"{"t":1,"lat":0,"lon":0,"value":1} trailing"#),
            Refusal::Malformed
        );
        assert_eq!(kind("\u{0}\u{1}\u{ff}"), Refusal::Malformed);
        assert_eq!(kind(""), Refusal::Malformed);
        assert_eq!(kind(r#"{"t":1,"lat":0,"lon":0,"value":"high"}"#), Refusal::WrongType);
        assert_eq!(kind(r#"{"t":1,"lat":0,"lon":0}"#), Refusal::WrongType);
        assert_eq!(kind("[1, 2, 3]"), Refusal::WrongType);
        assert_eq!(kind("42"), Refusal::WrongType);
        assert_eq!(kind(r#"{"t":1,"lon":0,"value":1}"#), Refusal::NoFix);
        assert_eq!(kind(r#"{"t":1,"lat":null,"lon":0,"value":1}"#), Refusal::NoFix);
        assert_eq!(kind(r#"{"t":1,"lat":91,"lon":0,"value":1}"#), Refusal::OutsideSite);
        assert_eq!(
            kind(r#"{"t":1,"lat":0,"lon":0,"value":1,"sigma":0}"#),
            Refusal::BadSigma
        );
        assert_eq!(
            kind(r#"{"t":1,"lat":0,"lon":0,"value":1,"sigma":-1}"#),
            Refusal::BadSigma
        );
        // A sigma the variance floor cannot hold beside it would make the reading exact.
        assert_eq!(
            kind(r#"{"t":1,"lat":0,"lon":0,"value":1,"sigma":1e-9}"#),
            Refusal::BadSigma
        );
        assert!(parse_line(br#"{"t":1,"lat":0,"lon":0,"value":1,"sigma":1e-5}"#).is_ok());
        let long = format!(
            r#"{{"t":1,"lat":0,"lon":0,"value":1,"pad":"{}"}}"#,
            "x".repeat(MAX_LINE)
        );
        assert_eq!(kind(&long), Refusal::Oversized);
    }
}
