//! The key space of DESIGN.md, all under `fleet/<mission>/`, in one place.

use super::ProtocolError;

/// Root of every key.
pub const ROOT: &str = "fleet";
/// Longest mission or vehicle id we accept.
pub const MAX_ID_LEN: usize = 32;

/// An id is 1-32 characters of `[A-Za-z0-9_-]`: nothing a Zenoh key expression would read as
/// a separator or wildcard (`/`, `*`, `$`, `?`, `#`).
pub fn check_id(what: &str, id: &str) -> Result<(), ProtocolError> {
    let ok = !id.is_empty()
        && id.len() <= MAX_ID_LEN
        && id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if ok {
        Ok(())
    } else {
        Err(ProtocolError::Invalid(format!(
            "{what} id {id:?} must be 1-{MAX_ID_LEN} characters of A-Z a-z 0-9 _ -"
        )))
    }
}

/// A key as the protocol's reference lists it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyUse {
    pub key: String,
    /// What travels on it: a message's `type`, or what else.
    pub payload: &'static str,
    pub put_by: &'static str,
    pub read_by: &'static str,
}

/// Keys of one mission.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    mission: String,
}

impl Keys {
    pub fn new(mission: &str) -> Result<Self, ProtocolError> {
        check_id("mission", mission)?;
        Ok(Self {
            mission: mission.into(),
        })
    }

    fn vehicle(&self, id: &str, leaf: &str) -> String {
        format!("{ROOT}/{}/vehicle/{id}/{leaf}", self.mission)
    }

    /// A vehicle's measurement batches.
    pub fn measurements(&self, id: &str) -> String {
        self.vehicle(id, "measurements")
    }

    /// Every vehicle's measurement batches (the server's subscription).
    pub fn all_measurements(&self) -> String {
        self.vehicle("*", "measurements")
    }

    pub fn telemetry(&self, id: &str) -> String {
        self.vehicle(id, "telemetry")
    }

    /// A vehicle's autopilot stream, MAVLink 2 frames as they come (for ground stations).
    pub fn mavlink(&self, id: &str) -> String {
        self.vehicle(id, "mavlink")
    }

    pub fn all_mavlink(&self) -> String {
        self.vehicle("*", "mavlink")
    }

    /// Frames from ground stations for one vehicle's autopilot (only the gateway puts here).
    pub fn gcs(&self, id: &str) -> String {
        format!("{ROOT}/{}/gcs/{id}/mavlink", self.mission)
    }

    pub fn ack(&self, id: &str) -> String {
        self.vehicle(id, "ack")
    }

    pub fn model_latest(&self) -> String {
        format!("{ROOT}/{}/model/latest", self.mission)
    }

    pub fn plan(&self, id: &str) -> String {
        format!("{ROOT}/{}/plan/{id}", self.mission)
    }

    pub fn alive(&self, id: &str) -> String {
        format!("{ROOT}/{}/alive/{id}", self.mission)
    }

    /// Every node's liveliness token.
    pub fn all_alive(&self) -> String {
        self.alive("*")
    }

    /// Every ground-station stream (what the gateway puts).
    pub fn all_gcs(&self) -> String {
        self.gcs("*")
    }

    /// Everything of this mission.
    pub fn everything(&self) -> String {
        format!("{ROOT}/{}/**", self.mission)
    }

    /// Every vehicle's plan (the server's queryable).
    pub fn all_plans(&self) -> String {
        self.plan("*")
    }

    /// The server's own status (counters, link view).
    pub fn server_status(&self) -> String {
        format!("{ROOT}/{}/server/status", self.mission)
    }

    /// The operator's verdict on a vehicle's sensor (only the ground station's seat, the
    /// gateway's user, puts here).
    pub fn sensor_override(&self, id: &str) -> String {
        format!("{ROOT}/{}/server/sensor/{id}", self.mission)
    }

    pub fn all_sensor_overrides(&self) -> String {
        self.sensor_override("*")
    }

    /// Every key a node puts or reads, with what travels on it and who puts and reads it (the
    /// protocol's reference page lists them from here), for the vehicle `id`.
    pub fn catalogue(&self, id: &str) -> [KeyUse; 10] {
        let use_ = |key: String, payload, put_by, read_by| KeyUse {
            key,
            payload,
            put_by,
            read_by,
        };
        [
            use_(self.measurements(id), "`batch`", "the vehicle", "the model server"),
            use_(
                self.telemetry(id),
                "`telemetry`",
                "the vehicle",
                "the model server, `fleet-watch`",
            ),
            use_(self.ack(id), "`ack`", "the model server", "the vehicle"),
            use_(
                self.mavlink(id),
                "MAVLink 2 frames from its autopilot, as they come",
                "the vehicle",
                "`gcs-gateway`",
            ),
            use_(
                self.gcs(id),
                "MAVLink 2 frames from ground stations to its autopilot",
                "`gcs-gateway`",
                "the vehicle",
            ),
            use_(
                self.model_latest(),
                "`model`, without the modes; a get answers it whole",
                "the model server (every epoch)",
                "`fleet-watch`, any observer",
            ),
            use_(
                self.plan(id),
                "`plan`; a get answers the newest",
                "the model server",
                "the vehicle, `fleet-watch`",
            ),
            use_(
                self.alive(id),
                "a liveliness token (no payload)",
                "every node",
                "the model server, `fleet-watch`, `gcs-gateway`",
            ),
            use_(
                self.server_status(),
                "`status`",
                "the model server",
                "`fleet-watch`, `gcs-gateway`, `fleet-operator`",
            ),
            use_(
                self.sensor_override(id),
                "`override`",
                "`fleet-operator` (the ground station's seat)",
                "the model server",
            ),
        ]
    }

    /// The vehicle id in a concrete key of this mission's vehicle space, if it is one.
    pub fn vehicle_of(&self, key: &str) -> Option<super::VehicleId> {
        self.id_after(key, "vehicle")?.parse().ok()
    }

    /// The id in a concrete `plan/<id>` or `alive/<id>` key (`space` is `plan` or `alive`).
    pub fn id_after(&self, key: &str, space: &str) -> Option<String> {
        let rest = key.strip_prefix(&format!("{ROOT}/{}/{space}/", self.mission))?;
        let id = rest.split('/').next()?;
        check_id(space, id).ok().map(|_| id.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_and_ids() {
        let k = Keys::new("tank-1").unwrap();
        assert_eq!(k.measurements("boat-3"), "fleet/tank-1/vehicle/boat-3/measurements");
        assert_eq!(k.all_measurements(), "fleet/tank-1/vehicle/*/measurements");
        assert_eq!(k.model_latest(), "fleet/tank-1/model/latest");
        assert_eq!(k.plan("av-1"), "fleet/tank-1/plan/av-1");
        assert_eq!(k.mavlink("boat-3"), "fleet/tank-1/vehicle/boat-3/mavlink");
        assert_eq!(k.gcs("boat-3"), "fleet/tank-1/gcs/boat-3/mavlink");
        assert_eq!(
            k.vehicle_of("fleet/tank-1/vehicle/boat-3/measurements").as_deref(),
            Some("boat-3")
        );
        assert_eq!(k.vehicle_of("fleet/other/vehicle/boat-3/measurements"), None);
        assert_eq!(k.id_after("fleet/tank-1/plan/av-2", "plan").as_deref(), Some("av-2"));
        assert_eq!(
            k.id_after("fleet/tank-1/alive/boat-1", "alive").as_deref(),
            Some("boat-1")
        );
        assert_eq!(k.id_after("fleet/tank-1/plan/*", "plan"), None);
        for bad in ["", "a/b", "*", "a$", "x".repeat(33).as_str(), "ü"] {
            assert!(check_id("vehicle", bad).is_err(), "{bad:?}");
            assert!(Keys::new(bad).is_err());
        }
    }
}
