//! Readiness as ArduPilot has it: no GPS fix for `gps_delay_s` after boot, so no position, no
//! EKF origin and no arming ("Need Position Estimate"); at the fix the EKF's origin is set where
//! the vehicle is (`libraries/AP_AHRS`: the origin is the first good GPS position, not the
//! site's corner) and announced with GPS_GLOBAL_ORIGIN. Arming is refused outside an enforced
//! fence ("Vehicle breaching Polygon fence"), not within its `FENCE_MARGIN`: ArduPilot 4.7's
//! `AC_Fence::pre_arm_check` refuses a breach, and only records a margin breach
//! (`libraries/AC_Fence/AC_Fence.cpp`, `libraries/AP_Arming/AP_Arming.cpp`). A refusal is a
//! STATUSTEXT "Arm: ..." and a COMMAND_ACK of MAV_RESULT_FAILED; SYS_STATUS carries the pre-arm
//! bit; arming is said ("Throttle armed" by a rover, "Arming motors" by a copter). A copter armed on the
//! ground and not told to take off disarms itself after `DISARM_DELAY`
//! (`ArduCopter/motors.cpp`, `auto_disarm_check`).

use super::*;

/// ArduPilot's "force" value for MAV_CMD_COMPONENT_ARM_DISARM's param2: arm without checks.
const FORCE_ARM: f32 = 2989.0;
/// A failing pre-arm check is said again this often while disarmed (simulated s;
/// `AP_Arming::update`, `PREARM_DISPLAY_PERIOD`).
const PREARM_PERIOD_S: f64 = 30.0;

impl SimAutopilot {
    /// Whether the GPS has its fix and the EKF its origin.
    pub fn has_fix(&self) -> bool {
        self.ekf_origin.is_some()
    }

    /// The fix, once `gps_delay_s` simulated seconds have passed: the EKF origin set where the
    /// vehicle is, and said.
    pub(super) fn update_fix(&mut self) {
        if self.ekf_origin.is_some() || self.sim_s < self.spec.gps_delay_s {
            return;
        }
        self.ekf_origin = Some(self.pos);
        self.say(MavSeverity::MAV_SEVERITY_INFO, "EKF3 IMU0 origin set");
        self.announce_origin();
    }

    /// GPS_GLOBAL_ORIGIN unasked, as a copter sends it when its origin is set and on arming; a
    /// rover sends it only when asked (MAV_CMD_REQUEST_MESSAGE).
    fn announce_origin(&mut self) {
        if self.spec.frame == Frame::Multirotor {
            let origin = self.gps_global_origin();
            self.out.extend(origin);
        }
    }

    /// While disarmed with a check failing: "PreArm: <why>" at once, then every 30 s, as a
    /// ground station hears it from ArduPilot.
    pub(super) fn report_prearm(&mut self) {
        let why = self.arming_refusal().filter(|_| !self.armed);
        let Some(why) = why else {
            self.prearm_said_s = None;
            return;
        };
        if self.prearm_said_s.is_some_and(|t| self.sim_s - t < PREARM_PERIOD_S) {
            return;
        }
        self.prearm_said_s = Some(self.sim_s);
        self.say(MavSeverity::MAV_SEVERITY_CRITICAL, &format!("PreArm: {why}"));
    }

    /// Why arming would be refused now (ArduPilot's words), or `None`.
    pub fn arming_refusal(&self) -> Option<String> {
        if !self.has_fix() {
            return Some("Need Position Estimate".into());
        }
        if self.spec.safety.fence_enable {
            if let Some((room, kind)) = self.fence.clearance(&self.pos) {
                if room < 0.0 {
                    return Some(format!("Vehicle breaching {kind} fence"));
                }
            }
        }
        None
    }

    /// MAV_CMD_COMPONENT_ARM_DISARM: arming after the checks (unless forced), disarming
    /// always; whether it was done.
    pub(super) fn arm_disarm(&mut self, arm: bool, force: f32) -> bool {
        if !arm {
            self.armed = false;
            return true;
        }
        if self.armed {
            return true;
        }
        if force != FORCE_ARM {
            if let Some(why) = self.arming_refusal() {
                self.say(MavSeverity::MAV_SEVERITY_CRITICAL, &format!("Arm: {why}"));
                return false;
            }
        }
        self.armed = true;
        self.armed_on_ground_s = 0.0;
        let said = match self.spec.frame {
            Frame::Boat => "Throttle armed",
            Frame::Multirotor => "Arming motors",
        };
        self.say(MavSeverity::MAV_SEVERITY_INFO, said);
        self.announce_origin();
        true
    }

    /// MAV_CMD_NAV_TAKEOFF (a multirotor, armed, in GUIDED, on the ground): climb to `alt`
    /// metres above home where it is. Refused otherwise, as ArduCopter's guided takeoff is.
    pub(super) fn takeoff(&mut self, alt: f32) -> bool {
        let ok = self.spec.frame == Frame::Multirotor
            && self.armed
            && self.landed
            && self.role() == Some(Control::Guided)
            && alt.is_finite()
            && alt > 0.0;
        if ok {
            self.landed = false;
            self.goal = Some(Vector3::new(self.pos.x, self.pos.y, self.home.z - alt as f64));
        }
        ok
    }

    /// A copter armed on the ground for `disarm_delay_s` without a takeoff disarms itself.
    pub(super) fn check_auto_disarm(&mut self, dt_sim: f64) {
        if !(self.armed && self.landed) {
            self.armed_on_ground_s = 0.0;
            return;
        }
        self.armed_on_ground_s += dt_sim;
        if self.armed_on_ground_s >= self.spec.disarm_delay_s {
            self.armed = false;
            self.say(MavSeverity::MAV_SEVERITY_INFO, "Disarming motors");
        }
    }

    /// GPS_GLOBAL_ORIGIN, once there is an origin.
    pub fn gps_global_origin(&self) -> Option<MavMessage> {
        let (lat, lon, alt) = self.spec.site.global_of(&self.ekf_origin?);
        Some(MavMessage::GPS_GLOBAL_ORIGIN(GPS_GLOBAL_ORIGIN_DATA {
            latitude: (lat * 1e7).round() as i32,
            longitude: (lon * 1e7).round() as i32,
            altitude: (alt * 1e3).round() as i32,
            time_usec: ((self.boot_unix_s + self.wall_s) * 1e6) as u64,
        }))
    }

    /// GPS_RAW_INT and EKF_STATUS_REPORT (1 Hz): no fix and a constant-position EKF before
    /// the fix; a 3D fix and absolute horizontal position after.
    pub fn readiness_reports(&self) -> Vec<MavMessage> {
        let fix = self.has_fix();
        let (lat, lon, alt) = self.spec.site.global_of(&self.pos);
        let gps = MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
            time_usec: ((self.boot_unix_s + self.wall_s) * 1e6) as u64,
            fix_type: if fix {
                GpsFixType::GPS_FIX_TYPE_3D_FIX
            } else {
                GpsFixType::GPS_FIX_TYPE_NO_FIX
            },
            lat: if fix { (lat * 1e7).round() as i32 } else { 0 },
            lon: if fix { (lon * 1e7).round() as i32 } else { 0 },
            alt: if fix { (alt * 1e3).round() as i32 } else { 0 },
            eph: if fix { 80 } else { u16::MAX },
            epv: if fix { 120 } else { u16::MAX },
            vel: (self.vel.xy().norm() * 100.0) as u16,
            cog: u16::MAX,
            satellites_visible: if fix { 12 } else { 0 },
            ..Default::default()
        });
        let flags = if fix {
            EkfStatusFlags::EKF_ATTITUDE
                | EkfStatusFlags::EKF_VELOCITY_HORIZ
                | EkfStatusFlags::EKF_VELOCITY_VERT
                | EkfStatusFlags::EKF_POS_HORIZ_REL
                | EkfStatusFlags::EKF_POS_HORIZ_ABS
                | EkfStatusFlags::EKF_POS_VERT_ABS
                | EkfStatusFlags::EKF_PRED_POS_HORIZ_REL
                | EkfStatusFlags::EKF_PRED_POS_HORIZ_ABS
        } else {
            EkfStatusFlags::EKF_ATTITUDE | EkfStatusFlags::EKF_CONST_POS_MODE
        };
        let ekf = MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA {
            flags,
            velocity_variance: 0.1,
            pos_horiz_variance: if fix { 0.1 } else { 1.0 },
            pos_vert_variance: 0.1,
            compass_variance: 0.05,
            ..Default::default()
        });
        vec![gps, ekf]
    }
}
