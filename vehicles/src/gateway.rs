//! The ground-station gateway: one MAVLink endpoint (by default `udpout:127.0.0.1:14550`,
//! where QGroundControl and MAVProxy listen) that carries every vehicle's autopilot stream, each
//! under its own system id, and routes what the ground station sends back to the vehicle whose
//! autopilot it addresses. Vehicles reach it over Zenoh (`vehicle/<id>/mavlink` out,
//! `gcs/<id>/mavlink` in), so a ground station at the base sees the fleet through the same
//! intermittent links as the model server, and one that only answers its last sender (as
//! pymavlink's and MAVProxy's `udpin:` do) still reaches every vehicle.

use crate::link::parse_frame;
use crate::signing::Refused;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MavHeader, Message};
use std::collections::BTreeMap;

/// Which vehicle speaks for which MAVLink system: fixed by the mission file (each vehicle's
/// place in it, from 1), never learned from what arrives, so no stream can claim another
/// vehicle's system id, whichever comes up first.
#[derive(Debug, Default)]
pub struct Router {
    by_sysid: BTreeMap<u8, String>,
    sysid_of: BTreeMap<String, u8>,
    /// Refusals by reason (`impostor`, `unknown_vehicle`, `unreadable`, `no_such_system`, and
    /// with signing `unsigned`, `bad_signature`, `replay`).
    pub refused: BTreeMap<&'static str, u64>,
}

impl Router {
    /// A router for the mission's vehicles and their system ids.
    pub fn new(systems: impl IntoIterator<Item = (String, u8)>) -> Self {
        let sysid_of: BTreeMap<String, u8> = systems.into_iter().collect();
        Self {
            by_sysid: sysid_of.iter().map(|(v, s)| (*s, v.clone())).collect(),
            sysid_of,
            refused: BTreeMap::new(),
        }
    }

    fn refuse<T>(&mut self, reason: &'static str, why: String) -> Result<T, Refusal> {
        *self.refused.entry(reason).or_default() += 1;
        Err(Refusal { reason, why })
    }

    /// A ground-station frame the signing check refused, counted.
    pub fn refused_by_signing(&mut self, r: Refused) -> Refusal {
        let why = match r {
            Refused::Unsigned => "an unsigned frame from the ground station (signing is on: give it the mission's key)",
            Refused::BadSignature => "a frame from the ground station signed with another key (or altered)",
            Refused::Replay => {
                "a signed frame from the ground station sent again (its timestamp is not newer than the last)"
            }
        };
        self.refuse::<()>(r.reason(), why.into()).unwrap_err()
    }

    /// Refusals in all.
    pub fn refused_total(&self) -> u64 {
        self.refused.values().sum()
    }

    /// Bytes from a vehicle's stream that are no frame (a bundle's bad tail), counted.
    pub fn unreadable(&mut self, why: String) -> Refusal {
        self.refuse::<()>("unreadable", why).unwrap_err()
    }

    /// A frame from a vehicle's stream: it must be readable and sent as that vehicle's own
    /// system id.
    pub fn from_vehicle(&mut self, vehicle: &str, frame: &[u8]) -> Result<(MavHeader, MavMessage), Refusal> {
        let (h, m) = match parse_frame(frame) {
            Ok(f) => f,
            Err(e) => return self.refuse("unreadable", format!("{vehicle}: {e}")),
        };
        let Some(&own) = self.sysid_of.get(vehicle) else {
            return self.refuse("unknown_vehicle", format!("{vehicle} is not a vehicle of the mission"));
        };
        if h.system_id != own as u32 {
            let whose = u8::try_from(h.system_id)
                .ok()
                .and_then(|s| self.by_sysid.get(&s))
                .map_or_else(|| "no vehicle's".to_string(), |v| format!("{v}'s"));
            return self.refuse(
                "impostor",
                format!(
                    "{vehicle} sent as system {}, which is {whose} (the mission gives {vehicle} system {own})",
                    h.system_id
                ),
            );
        }
        Ok((h, m))
    }

    /// The vehicles a frame from the ground station goes to: the one whose autopilot it
    /// addresses, or all for a broadcast (a ground station's HEARTBEAT).
    pub fn from_gcs(&mut self, frame: &[u8]) -> Result<Vec<String>, Refusal> {
        let (_, m) = match parse_frame(frame) {
            Ok(f) => f,
            Err(e) => return self.refuse("unreadable", format!("from the ground station: {e}")),
        };
        match m.target_system_id() {
            None | Some(0) => Ok(self.sysid_of.keys().cloned().collect()),
            Some(t) => match self.by_sysid.get(&t) {
                Some(v) => Ok(vec![v.clone()]),
                None => self.refuse(
                    "no_such_system",
                    format!("{} for system {t}, which no vehicle has", m.message_name()),
                ),
            },
        }
    }

    pub fn systems(&self) -> &BTreeMap<u8, String> {
        &self.by_sysid
    }
}

/// A frame the gateway did not pass on, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Refusal {
    pub reason: &'static str,
    pub why: String,
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.why)
    }
}

/// Logs refusals without flooding: the first of each reason at once, then a count at most
/// every `every`.
pub struct RefusalLog {
    every: std::time::Duration,
    last: BTreeMap<&'static str, (std::time::Instant, u64)>,
}

impl RefusalLog {
    pub fn new(every: std::time::Duration) -> Self {
        Self {
            every,
            last: BTreeMap::new(),
        }
    }

    /// What to log for this refusal now (`None`: only counted).
    pub fn note(&mut self, r: &Refusal) -> Option<String> {
        self.note_at(r, std::time::Instant::now())
    }

    /// [`Self::note`] at a given time.
    pub fn note_at(&mut self, r: &Refusal, now: std::time::Instant) -> Option<String> {
        match self.last.get_mut(r.reason) {
            None => {
                self.last.insert(r.reason, (now, 0));
                Some(format!(
                    "refused ({}): {} (further refusals of this kind are counted, and logged at most every {} s)",
                    r.reason,
                    r.why,
                    self.every.as_secs()
                ))
            }
            Some((at, skipped)) if now.duration_since(*at) >= self.every => {
                let n = std::mem::take(skipped);
                *at = now;
                Some(format!(
                    "refused ({}): {} ({n} more since the last report)",
                    r.reason, r.why
                ))
            }
            Some((_, skipped)) => {
                *skipped += 1;
                None
            }
        }
    }
}

/// The component a sensor-health notice comes from: the vehicle's companion computer
/// (`MAV_COMP_ID_ONBOARD_COMPUTER`), not its autopilot, whose message sequence it must not
/// disturb.
pub const HEALTH_COMPONENT: u8 = 191;

/// What the ground station is told of the vehicles' sensors: a STATUSTEXT under the vehicle's
/// system id when the model server's verdict on its sensor changes (an error when excluded, a
/// warning when suspect, a notice when it is back), as an autopilot says its own failures.
#[derive(Debug, Default)]
pub struct HealthNotices {
    said: BTreeMap<String, fleet_mission::protocol::Health>,
    sequence: u8,
}

impl HealthNotices {
    /// The notices a server status calls for, each once per change of verdict.
    pub fn of(
        &mut self,
        status: &fleet_mission::protocol::ServerStatus,
        router: &Router,
    ) -> Vec<(MavHeader, MavMessage)> {
        use fleet_mission::protocol::Health;
        use mavlink::dialects::ardupilotmega::{MavSeverity, STATUSTEXT_DATA};
        let mut out = vec![];
        for (vehicle, h) in &status.health {
            let (id, was) = (
                vehicle.to_string(),
                self.said.get(vehicle.as_str()).copied().unwrap_or_default(),
            );
            let Some(&sysid) = router.sysid_of.get(&id).filter(|_| h.state != was) else {
                continue;
            };
            self.said.insert(id, h.state);
            let severity = match h.state {
                Health::Excluded => MavSeverity::MAV_SEVERITY_ERROR,
                Health::Suspect => MavSeverity::MAV_SEVERITY_WARNING,
                Health::Ok => MavSeverity::MAV_SEVERITY_NOTICE,
            };
            let text = shortened(&format!("Sensor {}: {}", h.state, h.reason), 50);
            let header = MavHeader {
                system_id: sysid as u32,
                component_id: HEALTH_COMPONENT,
                sequence: self.sequence,
            };
            self.sequence = self.sequence.wrapping_add(1);
            out.push((
                header,
                MavMessage::STATUSTEXT(STATUSTEXT_DATA {
                    severity,
                    text: text.as_str().into(),
                    ..Default::default()
                }),
            ));
        }
        out
    }
}

/// At most `n` bytes of `s`, cut at a character's boundary (STATUSTEXT carries 50).
fn shortened(s: &str, n: usize) -> String {
    let mut end = s.len().min(n);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    s[..end].trim_end().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::frame_bytes;
    use mavlink::dialects::ardupilotmega::*;

    fn from(sysid: u8, m: &MavMessage) -> Vec<u8> {
        frame_bytes(
            MavHeader {
                system_id: sysid as u32,
                component_id: 1,
                sequence: 0,
            },
            m,
        )
    }

    fn mission_router() -> Router {
        Router::new([
            ("av-1".to_string(), 1),
            ("boat-1".to_string(), 3),
            ("boat-2".to_string(), 4),
        ])
    }

    #[test]
    #[allow(deprecated)]
    fn routes_by_target_system_and_refuses_impostors_and_garbage() {
        let mut r = mission_router();
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        r.from_vehicle("boat-1", &from(3, &hb)).unwrap();
        r.from_vehicle("boat-2", &from(4, &hb)).unwrap();
        assert!(
            r.from_vehicle("boat-2", &from(3, &hb)).is_err(),
            "boat-2 may not speak as system 3"
        );
        assert!(r.from_vehicle("boat-9", &from(9, &hb)).is_err(), "not in the mission");
        let mode = |t| {
            from(
                255,
                &MavMessage::SET_MODE(SET_MODE_DATA {
                    target_system: t,
                    custom_mode: 4,
                    ..Default::default()
                }),
            )
        };
        assert_eq!(r.from_gcs(&mode(4)).unwrap(), ["boat-2"]);
        assert_eq!(r.from_gcs(&from(255, &hb)).unwrap(), ["av-1", "boat-1", "boat-2"]);
        assert!(r.from_gcs(&mode(9)).is_err());
        let mut bad = mode(3);
        let n = bad.len();
        bad[n - 1] ^= 0xff;
        assert!(r.from_gcs(&bad).is_err(), "bad CRC");
        assert!(r.from_gcs(b"\xfd\x09garbage").is_err());
        assert_eq!(r.refused_total(), 5);
        assert_eq!(
            (
                r.refused["impostor"],
                r.refused["unknown_vehicle"],
                r.refused["unreadable"],
                r.refused["no_such_system"]
            ),
            (1, 1, 2, 1)
        );
    }

    #[test]
    #[allow(deprecated)]
    fn a_claim_made_before_the_real_vehicle_comes_up_takes_nothing_over() {
        // boat-1 (its own credentials, its own key) claims boat-2's system id first.
        let mut r = mission_router();
        let hb = |mode| {
            MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: mode,
                ..Default::default()
            })
        };
        for _ in 0..10 {
            assert_eq!(
                r.from_vehicle("boat-1", &from(4, &hb(99))).unwrap_err().reason,
                "impostor"
            );
        }
        // The real boat-2 is still itself, and an operator's HOLD for system 4 goes to it.
        assert!(r.from_vehicle("boat-2", &from(4, &hb(15))).is_ok());
        let hold = from(
            255,
            &MavMessage::SET_MODE(SET_MODE_DATA {
                target_system: 4,
                custom_mode: 4,
                ..Default::default()
            }),
        );
        assert_eq!(r.from_gcs(&hold).unwrap(), ["boat-2"]);
        // Even before boat-2 has said anything.
        let mut r = mission_router();
        r.from_vehicle("boat-1", &from(4, &hb(99))).unwrap_err();
        assert_eq!(r.from_gcs(&hold).unwrap(), ["boat-2"]);
    }

    #[test]
    fn refusals_are_logged_once_then_counted_then_summarised() {
        let every = std::time::Duration::from_secs(10);
        let mut log = RefusalLog::new(every);
        let t0 = std::time::Instant::now();
        let r = Refusal {
            reason: "impostor",
            why: "x".into(),
        };
        assert!(log.note_at(&r, t0).is_some());
        assert!((0..100).all(|_| log.note_at(&r, t0 + every / 2).is_none()));
        assert!(log.note_at(&r, t0 + every).unwrap().contains("100 more"));
        assert!(
            log.note_at(
                &Refusal {
                    reason: "unreadable",
                    why: "y".into()
                },
                t0 + every
            )
            .is_some(),
            "another reason is logged at once"
        );
    }

    /// A verdict becomes one STATUSTEXT under the vehicle's system id, from its companion
    /// computer, at the severity an autopilot would give it, at most 50 bytes; the same verdict
    /// again says nothing; a vehicle the mission does not have gets nothing.
    #[test]
    fn a_sensor_verdict_is_told_to_the_ground_station_once() {
        use fleet_mission::protocol::{Health, SensorHealth, ServerStatus};
        let router = mission_router();
        let mut status: ServerStatus = serde_json::from_str(
            r#"{"version":1,"next_epoch":1,"finished":false,"batches":0,"duplicates":0,"rejected":{},"alive":[],
            "waiting_for":[],"pending_epochs":0,"latency_p50_ms":0,"latency_p99_ms":0}"#,
        )
        .unwrap();
        let mut say = HealthNotices::default();
        assert!(say.of(&status, &router).is_empty());
        let reason = "stuck: its values repeat".to_string();
        for (id, state) in [
            ("boat-1", Health::Excluded),
            ("av-1", Health::Ok),
            ("boat-9", Health::Excluded),
        ] {
            let reason = reason.clone();
            status
                .health
                .insert(id.parse().unwrap(), SensorHealth { state, reason });
        }
        let said = say.of(&status, &router);
        assert_eq!(said.len(), 1, "{said:?}");
        let (h, m) = &said[0];
        assert_eq!((h.system_id, h.component_id), (3, HEALTH_COMPONENT));
        let MavMessage::STATUSTEXT(t) = m else { panic!("{m:?}") };
        assert_eq!(t.severity, MavSeverity::MAV_SEVERITY_ERROR);
        let text = t.text.to_str().unwrap();
        assert!(text.starts_with("Sensor excluded: stuck") && text.len() <= 50, "{text}");
        assert!(say.of(&status, &router).is_empty(), "said twice");
        status.health.get_mut("boat-1").unwrap().state = Health::Ok;
        let back = say.of(&status, &router);
        assert!(matches!(&back[0].1, MavMessage::STATUSTEXT(t) if t.severity == MavSeverity::MAV_SEVERITY_NOTICE));
    }
}
