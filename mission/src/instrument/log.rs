//! The readings log: what a vehicle's instrument gave it, one NDJSON line an input, as the
//! vehicle accepted it. It is the field's record (a run directory's `readings.ndjson`, which
//! `fleet assimilate` turns into the same model again), and the vehicle's own: after a crash the
//! node takes back the readings of the epochs still open from it.
//!
//! A line is the reading interface's object with the vehicle's id added, so any log of the
//! interface with `vehicle` added is one:
//!
//! ```text
//! {"vehicle":"boat-1","t":1795597230.25,"lat":55.67612,"lon":12.56841,"value":0.42,"sigma":0.01}
//! {"vehicle":"av-1","frame":"frame_20261125T090031Z.tif","t":1795597231.0}
//! {"vehicle":"av-1","step":31,"fix":[120.5,40.25]}
//! ```
//!
//! A frame line names a frame the aerial took from its directory (the frame stays there); a fix
//! line is where an aerial with a camera was at a sampling step (grid metres, what the noise of
//! its frame's cells is grown by).

use super::reading::Reading;
use serde::{Deserialize, Serialize};

/// One line of the log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Logged {
    pub vehicle: String,
    #[serde(flatten)]
    pub entry: Entry,
}

/// What a line records.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Entry {
    /// A point reading, as the instrument said it (a MAVLink value with the position and time
    /// it was given).
    Reading(Reading),
    /// A frame taken from the aerial's directory, and its time.
    Frame { frame: String, t: f64 },
    /// Where an aerial was at a sampling step (grid metres, x east and y north).
    Fix { step: u64, fix: [f64; 2] },
}

impl Logged {
    /// The line (without its newline).
    pub fn line(&self) -> String {
        serde_json::to_string(self).expect("a logged entry is plain data")
    }

    /// A line of a log, or why it is not one.
    pub fn parse(line: &str) -> Result<Self, String> {
        serde_json::from_str(line).map_err(|e| e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_entry_reads_back_to_the_same_bits() {
        let entries = [
            Entry::Reading(Reading {
                t: 1_795_597_230.25,
                lat: 55.676_123_456_789_01,
                lon: 0.1 + 0.2,
                value: -1.0 / 3.0,
                sigma: Some(0.01),
            }),
            Entry::Reading(Reading {
                t: 1.0,
                lat: 0.0,
                lon: 0.0,
                value: 2.0,
                sigma: None,
            }),
            Entry::Frame {
                frame: "frame_20261125T090031Z.tif".into(),
                t: 1_795_597_231.0,
            },
            Entry::Fix {
                step: 31,
                fix: [120.5, 1.0 / 7.0],
            },
        ];
        for entry in entries {
            let logged = Logged {
                vehicle: "av-1".into(),
                entry,
            };
            assert_eq!(Logged::parse(&logged.line()).unwrap(), logged);
        }
        // Any finite number, not only the friendly ones: serde_json reads back the same bits only
        // with its `float_roundtrip` feature (without it, about one number in ten is a bit off).
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..10_000 {
            let x = f64::from_bits(rng.random::<u64>());
            if !x.is_finite() {
                continue;
            }
            let logged = Logged {
                vehicle: "av-1".into(),
                entry: Entry::Fix { step: 1, fix: [x, -x] },
            };
            assert_eq!(Logged::parse(&logged.line()).unwrap(), logged, "{x:e}");
        }
        let r = Logged::parse(r#"{"vehicle":"boat-1","t":1,"lat":2,"lon":3,"value":4}"#).unwrap();
        assert!(matches!(r.entry, Entry::Reading(Reading { sigma: None, .. })));
        assert!(Logged::parse(r#"{"vehicle":"boat-1","t":1}"#).is_err());
        assert!(
            Logged::parse("{\"t\":1,\"lat\":2,\"lon\":3,\"value\":4}").is_err(),
            "a line names its vehicle"
        );
    }
}
