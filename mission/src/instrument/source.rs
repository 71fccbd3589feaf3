//! Which instrument feeds a vehicle (`[sensors]` in the mission, `vehicle --sensor`): its
//! name as written, parsed once.

use crate::protocol::VehicleKind;
use crate::roster::Roster;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::str::FromStr;

/// Where a vehicle's readings come from.
#[derive(Debug, Clone, PartialEq)]
pub enum SensorSource {
    /// Mixed reality: the mission's truth sampled at the vehicle's fix (the simulator).
    Sim,
    /// Newline-delimited JSON readings in UDP datagrams to this address (one or more lines
    /// per datagram).
    Udp(SocketAddr),
    /// Newline-delimited JSON readings on the node's standard input.
    Stdin,
    /// MAVLink NAMED_VALUE_FLOAT messages of this name on the vehicle's autopilot link.
    Mavlink(String),
    /// GeoTIFF frames appearing in this directory (aerials).
    Geotiff(PathBuf),
}

/// The names a source may take, for error messages.
pub const FORMS: &str = "sim, stdin, udp:ADDR:PORT, mavlink:NAME or geotiff:DIR";

impl SensorSource {
    /// Whether the source gives point readings (a boat's instrument) rather than frames.
    pub fn is_point(&self) -> bool {
        matches!(self, Self::Udp(_) | Self::Stdin | Self::Mavlink(_))
    }
}

impl FromStr for SensorSource {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, rest) = s.split_once(':').unwrap_or((s, ""));
        match (kind, rest) {
            ("sim", "") => Ok(Self::Sim),
            ("stdin", "") => Ok(Self::Stdin),
            ("udp", a) => a
                .parse()
                .map(Self::Udp)
                .map_err(|_| format!("{s:?}: udp wants ADDR:PORT (udp:0.0.0.0:15602)")),
            // NAMED_VALUE_FLOAT's name is a char[10].
            ("mavlink", n) if !n.is_empty() && n.len() <= 10 && n.is_ascii() => Ok(Self::Mavlink(n.into())),
            ("mavlink", _) => Err(format!(
                "{s:?}: mavlink wants a NAMED_VALUE_FLOAT name of 1 to 10 ASCII characters"
            )),
            ("geotiff", d) if !d.is_empty() => Ok(Self::Geotiff(d.into())),
            _ => Err(format!("{s:?} is not a sensor source ({FORMS})")),
        }
    }
}

impl fmt::Display for SensorSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Sim => write!(f, "sim"),
            Self::Stdin => write!(f, "stdin"),
            Self::Udp(a) => write!(f, "udp:{a}"),
            Self::Mavlink(n) => write!(f, "mavlink:{n}"),
            Self::Geotiff(d) => write!(f, "geotiff:{}", d.display()),
        }
    }
}

/// The mission's `[sensors]` table: `default` for every vehicle, and one entry per vehicle id
/// that differs (`boat-2 = "udp:0.0.0.0:15602"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Sensors {
    /// Every vehicle's source unless it has its own entry: `sim` (the truth sampled at the
    /// vehicle's fix), `stdin`, `udp:ADDR:PORT` (NDJSON readings), `mavlink:NAME`
    /// (NAMED_VALUE_FLOAT on the autopilot's link) or `geotiff:DIR` (an aerial's frames).
    #[serde(default = "sim")]
    pub default: String,
    /// One entry per vehicle id whose source differs from `default` (`boat-2 = "udp:0.0.0.0:15602"`).
    #[serde(flatten)]
    pub vehicles: BTreeMap<String, String>,
}

fn sim() -> String {
    "sim".into()
}

impl Default for Sensors {
    fn default() -> Self {
        Self {
            default: sim(),
            vehicles: BTreeMap::new(),
        }
    }
}

impl Sensors {
    /// A vehicle's source as written (its own entry, else the default).
    pub fn of(&self, id: &str) -> &str {
        self.vehicles.get(id).map_or(&self.default, String::as_str)
    }

    /// Check the table against the mission's vehicles, whether it has a clock (`[time]`), a
    /// truth and autopilots: every entry a known vehicle, every source one its kind can use, any
    /// source other than `sim` only with mission time, `mavlink` only with an autopilot and `sim`
    /// only with a truth. The error is the key and the rule.
    pub fn check(&self, roster: &Roster, m: Mission) -> Result<(), (String, String)> {
        if let Some(id) = self.vehicles.keys().find(|id| roster.get(id).is_none()) {
            return Err((
                id.clone(),
                format!("not a vehicle of this mission ({})", roster.ids().join(", ")),
            ));
        }
        for v in roster.all() {
            let key = if self.vehicles.contains_key(v.id.as_str()) {
                v.id.to_string()
            } else {
                "default".into()
            };
            let source: SensorSource = self.of(&v.id).parse().map_err(|e| (key.clone(), e))?;
            check_source(&source, v.kind, m).map_err(|e| (key.clone(), format!("{source} for {}: {e}", v.id)))?;
            if source == SensorSource::Sim && !m.truth {
                let rule = format!(
                    "sim for {}: the simulated sensor samples the truth, and there is no [truth]",
                    v.id
                );
                return Err((key, rule));
            }
        }
        Ok(())
    }
}

/// What of the mission decides which sources a vehicle may read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mission {
    /// Mission time (`[time]`).
    pub timed: bool,
    /// A truth (`[truth]` or `--truth`).
    pub truth: bool,
    /// An autopilot link (`[mavlink] autopilot` or `--autopilot` other than `none`).
    pub autopilot: bool,
}

/// Whether a vehicle of `kind` can read `source` in mission `m`.
pub fn check_source(source: &SensorSource, kind: VehicleKind, m: Mission) -> Result<(), String> {
    if matches!(source, SensorSource::Mavlink(_)) && !m.autopilot {
        return Err(
            "NAMED_VALUE_FLOAT comes on the autopilot's link, and the vehicle has none (autopilot = \"none\")".into(),
        );
    }
    if kind == VehicleKind::Aerial && source.is_point() {
        return Err("an aerial's readings are frames (sim or geotiff), not points".into());
    }
    if kind == VehicleKind::Boat && matches!(source, SensorSource::Geotiff(_)) {
        return Err("a boat's readings are points (stdin, udp or mavlink), not frames".into());
    }
    if *source != SensorSource::Sim && !m.timed {
        return Err("readings from an instrument need mission time ([time] start and step_s)".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_form_parses_and_prints_back() {
        for s in [
            "sim",
            "stdin",
            "udp:0.0.0.0:15602",
            "udp:[::1]:9",
            "mavlink:SONDE",
            "geotiff:/data/frames",
        ] {
            assert_eq!(s.parse::<SensorSource>().unwrap().to_string(), s);
        }
        for bad in [
            "",
            "sims",
            "udp:",
            "udp:host",
            "udp:1.2.3.4:99999",
            "mavlink:",
            "mavlink:ELEVENCHARSX",
            "file:x",
        ] {
            assert!(bad.parse::<SensorSource>().is_err(), "{bad}");
        }
    }
}
