//! What the bridge reads of its autopilot before it lets the planner drive it: readiness by
//! state, not by a timer (the GPS fix from GPS_RAW_INT, the EKF's absolute position from
//! EKF_STATUS_REPORT, the pre-arm bit of SYS_STATUS, and what the autopilot says when it
//! refuses to arm), and the autopilot's own settings that the bridge keeps to (`FENCE_MARGIN`,
//! `WP_RADIUS` or a copter's `WPNAV_RADIUS`, a rover's `TURN_RADIUS`, and the system id under
//! either of its names: `MAV_SYSID` from ArduPilot 4.7, `SYSID_THISMAV` before).

use crate::autopilot::modes::Frame;
use mavlink::dialects::ardupilotmega::*;
use mavlink::MessageData;

/// What the autopilot has said of its readiness (`None`: not said yet, so not waited for).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Readiness {
    /// A 3D fix or better (GPS_RAW_INT).
    pub gps_fix: Option<bool>,
    /// The EKF has an absolute horizontal position and is not in constant-position mode.
    pub ekf: Option<bool>,
    /// The pre-arm checks pass (SYS_STATUS, when the autopilot reports the bit).
    pub prearm: Option<bool>,
    /// The autopilot's last word on why it will not arm ("PreArm: ...", "Arm: ..."), until armed.
    pub refusal: Option<String>,
}

impl Readiness {
    /// Take what a message says of readiness.
    pub fn on_message(&mut self, m: &MavMessage) {
        match m {
            MavMessage::GPS_RAW_INT(g) => {
                self.gps_fix = Some(g.fix_type as u8 >= GpsFixType::GPS_FIX_TYPE_3D_FIX as u8)
            }
            MavMessage::EKF_STATUS_REPORT(e) => {
                self.ekf = Some(
                    e.flags.contains(EkfStatusFlags::EKF_POS_HORIZ_ABS)
                        && !e.flags.contains(EkfStatusFlags::EKF_CONST_POS_MODE),
                )
            }
            MavMessage::SYS_STATUS(s)
                if s.onboard_control_sensors_present
                    .contains(MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK) =>
            {
                self.prearm = Some(
                    s.onboard_control_sensors_health
                        .contains(MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK),
                )
            }
            _ => {}
        }
    }

    /// What it still waits for, first things first (`None`: ready, as far as it has said).
    pub fn waiting_for(&self, has_position: bool) -> Option<String> {
        if self.gps_fix == Some(false) {
            return Some("GPS fix".into());
        }
        if self.ekf == Some(false) {
            return Some("EKF position estimate".into());
        }
        if !has_position {
            return Some("position".into());
        }
        if self.prearm == Some(false) {
            return Some(match &self.refusal {
                Some(r) => format!("pre-arm checks ({r})"),
                None => "pre-arm checks".into(),
            });
        }
        None
    }
}

/// Whether a STATUSTEXT is the autopilot refusing to arm (ArduPilot prefixes its pre-arm
/// reports "PreArm: " and an arming attempt's failure "Arm: ").
pub fn is_arming_refusal(text: &str) -> bool {
    text.starts_with("PreArm:") || text.starts_with("Arm:")
}

/// The autopilot's own settings the bridge keeps to, as read from it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Limits {
    /// `FENCE_MARGIN` (m).
    pub fence_margin: Option<f64>,
    /// `WP_RADIUS` (m), or a copter's `WPNAV_RADIUS` (read in cm, kept in m).
    pub wp_radius: Option<f64>,
    /// A rover's `TURN_RADIUS` (m); 0 for a copter.
    pub turn_radius: Option<f64>,
    /// The system id and the name it answered under (`MAV_SYSID`, or `SYSID_THISMAV` before 4.7).
    pub sysid: Option<(String, f64)>,
}

/// The parameters the bridge reads, by frame.
pub fn wanted(frame: Frame) -> &'static [&'static str] {
    match frame {
        Frame::Boat => &["FENCE_MARGIN", "WP_RADIUS", "TURN_RADIUS", "MAV_SYSID", "SYSID_THISMAV"],
        Frame::Multirotor => &["FENCE_MARGIN", "WPNAV_RADIUS", "MAV_SYSID", "SYSID_THISMAV"],
    }
}

impl Limits {
    /// Take a PARAM_VALUE the bridge asked for; whether it was one.
    pub fn on_param(&mut self, name: &str, value: f32) -> bool {
        let v = value as f64;
        if !v.is_finite() {
            return false;
        }
        match name {
            "FENCE_MARGIN" => self.fence_margin = Some(v),
            "WP_RADIUS" => self.wp_radius = Some(v),
            "WPNAV_RADIUS" => self.wp_radius = Some(v / 100.0),
            "TURN_RADIUS" => self.turn_radius = Some(v),
            "MAV_SYSID" | "SYSID_THISMAV" => self.sysid = Some((name.to_string(), v)),
            _ => return false,
        }
        true
    }

    /// Whether the settings the bridge keeps to have all been read.
    pub fn complete(&self, frame: Frame) -> bool {
        self.fence_margin.is_some() && self.wp_radius.is_some() && (frame != Frame::Boat || self.turn_radius.is_some())
    }

    /// How far inside the fence the vehicle must stay clear: the margin plus the turn.
    pub fn clearance(&self) -> f64 {
        self.fence_margin.unwrap_or(0.0) + self.turn_radius.unwrap_or(0.0)
    }
}

/// The messages the bridge reads and the interval it asks for each (microseconds): positions
/// at 10 Hz, readiness and the fence's state at 1 Hz. ArduPilot streams what a link's `SRn_`
/// rates say, which may be nothing: MAV_CMD_SET_MESSAGE_INTERVAL asks for each by id.
pub fn intervals() -> [(u32, f32); 5] {
    [
        (GLOBAL_POSITION_INT_DATA::ID, 100_000.0),
        (GPS_RAW_INT_DATA::ID, 1_000_000.0),
        (EKF_STATUS_REPORT_DATA::ID, 1_000_000.0),
        (SYS_STATUS_DATA::ID, 1_000_000.0),
        (FENCE_STATUS_DATA::ID, 1_000_000.0),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readiness_waits_for_the_fix_then_the_ekf_then_the_pre_arm_checks() {
        let mut r = Readiness::default();
        assert_eq!(
            r.waiting_for(true),
            None,
            "an autopilot that says nothing is not waited for"
        );
        assert_eq!(r.waiting_for(false).as_deref(), Some("position"));
        r.on_message(&MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
            fix_type: GpsFixType::GPS_FIX_TYPE_NO_FIX,
            ..Default::default()
        }));
        r.on_message(&MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA {
            flags: EkfStatusFlags::EKF_ATTITUDE | EkfStatusFlags::EKF_CONST_POS_MODE,
            ..Default::default()
        }));
        assert_eq!(r.waiting_for(true).as_deref(), Some("GPS fix"));
        r.gps_fix = Some(true);
        assert_eq!(r.waiting_for(true).as_deref(), Some("EKF position estimate"));
        r.ekf = Some(true);
        let prearm = MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK;
        r.on_message(&MavMessage::SYS_STATUS(SYS_STATUS_DATA {
            onboard_control_sensors_present: prearm,
            ..Default::default()
        }));
        r.refusal = Some("PreArm: Fence requires position".into());
        assert_eq!(
            r.waiting_for(true).as_deref(),
            Some("pre-arm checks (PreArm: Fence requires position)")
        );
        assert!(is_arming_refusal("Arm: Vehicle breaching Polygon fence") && !is_arming_refusal("Fence breach: RTL"));
        let mut l = Limits::default();
        assert!(l.on_param("WPNAV_RADIUS", 300.0) && l.on_param("FENCE_MARGIN", 2.0));
        assert_eq!(l.wp_radius, Some(3.0), "a copter's radius is in cm");
        assert!(l.complete(Frame::Multirotor) && !l.complete(Frame::Boat));
    }
}
