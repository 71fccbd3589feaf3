//! The ground-station gateway: one MAVLink endpoint (by default `udpout:127.0.0.1:14550`,
//! where QGroundControl and MAVProxy listen) that carries every vehicle's autopilot stream, each
//! under its own system id, and routes what the ground station sends back to the vehicle whose
//! autopilot it addresses. Vehicles reach it over Zenoh (`vehicle/<id>/mavlink` out,
//! `gcs/<id>/mavlink` in), so a ground station at the base sees the fleet through the same
//! intermittent links as the model server, and one that only answers its last sender (as
//! pymavlink's and MAVProxy's `udpin:` do) still reaches every vehicle.

use crate::bridge::parse_frame;
use mavlink::dialects::common::MavMessage;
use mavlink::{MavHeader, Message};
use std::collections::{BTreeMap, BTreeSet};

/// Which vehicle speaks for which MAVLink system, learned from their streams.
#[derive(Debug, Default)]
pub struct Router {
    by_sysid: BTreeMap<u8, String>,
    vehicles: BTreeSet<String>,
    pub refused: u64,
}

impl Router {
    /// A frame from a vehicle's stream: checked, and its system id learned for that vehicle.
    pub fn from_vehicle(&mut self, vehicle: &str, frame: &[u8]) -> Result<(MavHeader, MavMessage), String> {
        let (h, m) = parse_frame(frame).inspect_err(|_| self.refused += 1)?;
        let Ok(sysid) = u8::try_from(h.system_id) else {
            self.refused += 1;
            return Err(format!("{vehicle} sent as system {}: MAVLink system ids are 1-255", h.system_id));
        };
        self.vehicles.insert(vehicle.to_string());
        if let Some(other) = self.by_sysid.get(&sysid).filter(|v| *v != vehicle) {
            self.refused += 1;
            return Err(format!("{vehicle} sent as system {} which is {other}'s", h.system_id));
        }
        self.by_sysid.insert(sysid, vehicle.to_string());
        Ok((h, m))
    }

    /// The vehicles a frame from the ground station goes to: the one whose autopilot it
    /// addresses, or all for a broadcast (a ground station's HEARTBEAT).
    pub fn from_gcs(&mut self, frame: &[u8]) -> Result<Vec<String>, String> {
        let (_, m) = parse_frame(frame).inspect_err(|_| self.refused += 1)?;
        match m.target_system_id() {
            None | Some(0) => Ok(self.vehicles.iter().cloned().collect()),
            Some(t) => match self.by_sysid.get(&t) {
                Some(v) => Ok(vec![v.clone()]),
                None => {
                    self.refused += 1;
                    Err(format!("{} for system {t}, which no vehicle has", m.message_name()))
                }
            },
        }
    }

    pub fn systems(&self) -> &BTreeMap<u8, String> {
        &self.by_sysid
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bridge::frame_bytes;
    use mavlink::dialects::common::*;

    fn from(sysid: u8, m: &MavMessage) -> Vec<u8> {
        frame_bytes(MavHeader { system_id: sysid as u32, component_id: 1, sequence: 0 }, m)
    }

    #[test]
    #[allow(deprecated)]
    fn routes_by_target_system_and_refuses_impostors_and_garbage() {
        let mut r = Router::default();
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        r.from_vehicle("boat-1", &from(3, &hb)).unwrap();
        r.from_vehicle("boat-2", &from(4, &hb)).unwrap();
        assert!(r.from_vehicle("boat-2", &from(3, &hb)).is_err(), "boat-2 may not speak as system 3");
        let mode = |t| from(255, &MavMessage::SET_MODE(SET_MODE_DATA { target_system: t, custom_mode: 4, ..Default::default() }));
        assert_eq!(r.from_gcs(&mode(4)).unwrap(), ["boat-2"]);
        assert_eq!(r.from_gcs(&from(255, &hb)).unwrap(), ["boat-1", "boat-2"]);
        assert!(r.from_gcs(&mode(9)).is_err());
        let mut bad = mode(3);
        let n = bad.len();
        bad[n - 1] ^= 0xff;
        assert!(r.from_gcs(&bad).is_err(), "bad CRC");
        assert!(r.from_gcs(b"\xfd\x09garbage").is_err());
        assert_eq!(r.refused, 4);
    }
}
