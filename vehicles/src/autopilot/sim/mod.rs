//! A simulated autopilot that speaks MAVLink as ArduPilot does: a kinematic boat (speed and
//! turn-rate limits, on the surface) or multirotor (speed limit, at cruise altitude), with
//! modes, arming, guided targets (SET_POSITION_TARGET_LOCAL_NED, MAV_CMD_DO_REPOSITION), the
//! mission protocol for missions, fences and rally points (upload, download, clear; a mission
//! runs with MISSION_CURRENT and MISSION_ITEM_REACHED), and the geofence enforced once
//! `FENCE_ENABLE` is set (targets outside refused, a breach triggers `FENCE_ACTION`; RTL goes
//! to the nearest rally point). Pure: messages in, messages out, time passed in; `serve` puts
//! it on a socket. One module per part of what it does: [`commands`] (modes, arming, commands,
//! parameters), [`mission_items`] (the mission protocol and running a mission), [`motion`]
//! (the physics, the battery and the fence) and [`telemetry`] (what it reports).
//!
//! Missions follow ArduPilot's convention: item 0 is home (taken as sent, never flown, read
//! back as home), AUTO runs from item 1; items are MAV_CMD_NAV_WAYPOINT in a global frame, or
//! MAV_CMD_DO_CHANGE_SPEED (done when reached in the sequence), as MAVSDK and QGroundControl
//! send them.

// Ground stations still send SET_MODE, MISSION_REQUEST and the *_INT frame names: we take them.
#![allow(deprecated)]

mod commands;
mod mission_items;
mod motion;
mod readiness;
mod telemetry;

use super::geofence::{Geofence, MAX_FENCE_ITEMS};
use super::modes::{Control, Frame};
use super::params;
use super::safety::{Action, ARMED_DRAW_A, IDLE_DRAW_A, MAX_DRAW_A};
pub use super::spec::{SimSpec, PIVOT_ANGLE_DEG};

use mavlink::dialects::ardupilotmega::*;
use mavlink::{MavHeader, Message, MessageData};
use nalgebra::Vector3;
use std::f64::consts::PI;

/// Longest mission we take.
pub const MAX_MISSION_ITEMS: u16 = 500;
/// Physics step (simulated seconds).
const SUBSTEP_S: f64 = 0.05;
/// An upload waits this long (wall seconds) for an item before asking again, as ArduPilot's
/// `MissionItemProtocol::update` does (1 s plus the link's slowdown).
const UPLOAD_RETRY_S: f64 = 1.0;
/// An upload with no item for this long (wall seconds) is cancelled (ArduPilot's
/// `upload_timeout_ms`).
const UPLOAD_TIMEOUT_S: f64 = 8.0;

/// How far the mission has run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Run {
    NotStarted,
    Started,
    Complete,
}

struct Upload {
    kind: MavMissionType,
    count: u16,
    items: Vec<MISSION_ITEM_INT_DATA>,
    from: (u8, u8),
    asked_at: f64,
    /// When the last item came (or the count).
    received_at: f64,
}

pub struct SimAutopilot {
    pub spec: SimSpec,
    /// Local NED (m).
    pub pos: Vector3<f64>,
    pub vel: Vector3<f64>,
    /// Radians from north, clockwise.
    pub heading: f64,
    pub armed: bool,
    pub mode: u32,
    mode_before_pause: Option<u32>,
    goal: Option<Vector3<f64>>,
    home: Vector3<f64>,
    pub mission: Vec<MISSION_ITEM_INT_DATA>,
    pub current: u16,
    mission_run: Run,
    /// The fence as uploaded, and as enforced.
    pub fence_items: Vec<MISSION_ITEM_INT_DATA>,
    pub fence: Geofence,
    pub rally: Vec<MISSION_ITEM_INT_DATA>,
    /// Outside the enforced fence now; breaches so far.
    pub breached: bool,
    pub breach_count: u16,
    upload: Option<Upload>,
    /// Wall seconds since boot, and UTC seconds (since 1970) at boot: its clock, as its GPS
    /// would give it (SYSTEM_TIME).
    pub wall_s: f64,
    pub boot_unix_s: f64,
    /// Simulated seconds since boot.
    pub sim_s: f64,
    /// The EKF's origin (the site's NED): where it was when the GPS got its fix, as ArduPilot
    /// sets it (`libraries/AP_AHRS`); `None` before the fix. LOCAL_POSITION_NED and local
    /// targets are relative to it, not to the site's corner.
    pub ekf_origin: Option<Vector3<f64>>,
    /// A multirotor on the ground (until told to take off), and for how long it has been armed
    /// there (simulated seconds).
    pub landed: bool,
    armed_on_ground_s: f64,
    /// When "PreArm: ..." was last said (simulated s), while a check fails and it is disarmed.
    prearm_said_s: Option<f64>,
    /// Charge used (mAh), and the draw now (A).
    pub consumed_mah: f64,
    draw_a: f64,
    /// Why a failsafe took the vehicle from its mode (latched until the mode is set again).
    pub failsafe: Option<&'static str>,
    out: Vec<MavMessage>,
}

fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

impl SimAutopilot {
    /// Boots disarmed, in the frame's boot mode, at `home` (local NED).
    pub fn new(spec: SimSpec, home: Vector3<f64>) -> Self {
        let mode = spec.frame.boot_mode();
        let landed = spec.frame == Frame::Multirotor;
        let ekf_origin = (spec.gps_delay_s <= 0.0).then_some(home);
        let consumed_mah = spec
            .safety
            .battery_start_mah
            .map_or(0.0, |c| (spec.safety.battery_mah - c).max(0.0));
        Self {
            spec,
            pos: home,
            vel: Vector3::zeros(),
            heading: 0.0,
            armed: false,
            mode,
            mode_before_pause: None,
            goal: None,
            home,
            mission: vec![],
            current: 0,
            mission_run: Run::NotStarted,
            fence_items: vec![],
            fence: Geofence::default(),
            rally: vec![],
            breached: false,
            breach_count: 0,
            upload: None,
            wall_s: 0.0,
            sim_s: 0.0,
            // With no GPS delay, the fix is there at boot.
            ekf_origin,
            landed,
            armed_on_ground_s: 0.0,
            prearm_said_s: None,
            boot_unix_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64()),
            consumed_mah,
            draw_a: IDLE_DRAW_A,
            failsafe: None,
            out: vec![],
        }
    }

    pub fn role(&self) -> Option<Control> {
        self.spec.frame.role(self.mode)
    }

    /// Messages to send (replies and events), oldest first.
    pub fn take(&mut self) -> Vec<MavMessage> {
        std::mem::take(&mut self.out)
    }

    pub(super) fn for_me(&self, msg: &MavMessage) -> bool {
        msg.target_system_id().is_none_or(|t| t == 0 || t == self.spec.sysid)
    }

    /// The surface (boats) or cruise altitude (multirotors) under a point.
    pub(super) fn at_altitude(&self, mut p: Vector3<f64>) -> Vector3<f64> {
        p.z = match self.spec.frame {
            Frame::Boat => 0.0,
            Frame::Multirotor => p.z.min(0.0),
        };
        p
    }

    /// Whether the enforced fence keeps the vehicle from a place.
    pub(super) fn fenced_out(&self, ned: &Vector3<f64>) -> bool {
        self.spec.safety.fence_enable && !self.fence.contains(ned)
    }

    /// A guided target (the site's NED). Outside the enforced fence a copter ignores it without
    /// a word and keeps its old goal (`ArduCopter/mode_guided.cpp`: the destination is refused,
    /// and a position target has no ack to carry that); a rover takes it (ArduRover's guided
    /// mode does not check it) and the breach triggers `FENCE_ACTION`.
    fn guided_target(&mut self, p: Vector3<f64>) {
        if !p.iter().all(|v| v.is_finite()) {
            return;
        }
        let p = self.at_altitude(p);
        if !(self.fenced_out(&p) && self.spec.frame == Frame::Multirotor) {
            self.goal = Some(p);
        }
    }

    /// A SET_POSITION_TARGET_GLOBAL_INT's place (the site's NED): its altitude above home
    /// (GLOBAL_RELATIVE_ALT) or above mean sea level (GLOBAL); other frames are not taken.
    fn global_target(&self, t: &SET_POSITION_TARGET_GLOBAL_INT_DATA) -> Option<Vector3<f64>> {
        let (lat, lon) = (t.lat_int as f64 * 1e-7, t.lon_int as f64 * 1e-7);
        if !(lat.abs() <= 90.0 && lon.abs() <= 180.0) {
            return None;
        }
        let home_alt = self.spec.site.global_of(&self.home).2;
        let alt = match t.coordinate_frame {
            MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT => {
                home_alt + t.alt as f64
            }
            MavFrame::MAV_FRAME_GLOBAL_INT | MavFrame::MAV_FRAME_GLOBAL => t.alt as f64,
            _ => return None,
        };
        Some(self.spec.site.ned_of_global(lat, lon, alt))
    }

    pub(super) fn say(&mut self, severity: MavSeverity, text: &str) {
        self.out.push(MavMessage::STATUSTEXT(STATUSTEXT_DATA {
            severity,
            text: text.into(),
            ..Default::default()
        }));
    }

    /// Take one message from a ground station or companion computer.
    pub fn handle(&mut self, from: &MavHeader, msg: &MavMessage) {
        if !self.for_me(msg) {
            return;
        }
        let Ok(sysid) = u8::try_from(from.system_id) else {
            return;
        };
        let sender = (sysid, from.component_id);
        match msg {
            MavMessage::COMMAND_LONG(c) => self.command(
                c.command,
                [c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7],
                None,
            ),
            MavMessage::COMMAND_INT(c) => {
                let global = Some((c.x as f64 * 1e-7, c.y as f64 * 1e-7, c.z as f64));
                self.command(
                    c.command,
                    [c.param1, c.param2, c.param3, c.param4, 0.0, 0.0, c.z],
                    global,
                )
            }
            MavMessage::SET_MODE(m) => {
                self.set_mode(m.custom_mode);
            }
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(t)
                if self.role() == Some(Control::Guided) && t.coordinate_frame == MavFrame::MAV_FRAME_LOCAL_NED =>
            {
                // Relative to the EKF origin (none before the fix: nothing to be relative to).
                if let Some(o) = self.ekf_origin {
                    self.guided_target(o + Vector3::new(t.x as f64, t.y as f64, t.z as f64));
                }
            }
            MavMessage::SET_POSITION_TARGET_GLOBAL_INT(t) if self.role() == Some(Control::Guided) => {
                if let Some(p) = self.global_target(t) {
                    self.guided_target(p);
                }
            }
            MavMessage::PARAM_REQUEST_LIST(_) | MavMessage::PARAM_REQUEST_READ(_) | MavMessage::PARAM_SET(_) => {
                self.param_message(msg)
            }
            _ => self.mission_message(sender, msg),
        }
    }
}

#[cfg(test)]
mod tests;
