//! A simulated autopilot that speaks MAVLink as ArduPilot does: a kinematic boat (speed and
//! turn-rate limits, on the surface) or multirotor (speed limit, at cruise altitude), with
//! modes, arming, guided targets (SET_POSITION_TARGET_LOCAL_NED, MAV_CMD_DO_REPOSITION), the
//! mission protocol for missions, fences and rally points (upload, download, clear; a mission
//! runs with MISSION_CURRENT and MISSION_ITEM_REACHED), and the geofence enforced once
//! `FENCE_ENABLE` is set (targets outside refused, a breach triggers `FENCE_ACTION`; RTL goes
//! to the nearest rally point). Pure: messages in, messages out, time passed in; `serve` puts
//! it on a socket.
//!
//! Missions follow ArduPilot's convention: item 0 is home (taken as sent, never flown, read
//! back as home), AUTO runs from item 1; items are MAV_CMD_NAV_WAYPOINT in a global frame, or
//! MAV_CMD_DO_CHANGE_SPEED (done when reached in the sequence), as MAVSDK and QGroundControl
//! send them.

// Ground stations still send SET_MODE, MISSION_REQUEST and the *_INT frame names: we take them.
#![allow(deprecated)]

use super::geofence::{Geofence, MAX_FENCE_ITEMS};
use super::modes::{Frame, Role};
use super::params;
use super::safety::{Action, Safety, ARMED_DRAW_A, IDLE_DRAW_A, MAX_DRAW_A};
use fleet_mission::site::Site;
use mavlink::dialects::common::*;
use mavlink::{MavHeader, Message, MessageData};
use nalgebra::Vector3;
use std::f64::consts::PI;

/// Longest mission we take.
pub const MAX_MISSION_ITEMS: u16 = 500;
/// Physics step (simulated seconds).
const SUBSTEP_S: f64 = 0.05;
/// An upload waits this long (wall seconds) for an item before asking again, five times.
const UPLOAD_RETRY_S: f64 = 0.5;

#[derive(Debug, Clone)]
pub struct SimSpec {
    pub frame: Frame,
    pub sysid: u8,
    pub site: Site,
    /// m/s
    pub max_speed: f64,
    /// rad/s (boats only)
    pub turn_rate: f64,
    /// m above the origin (multirotors)
    pub cruise_alt: f64,
    /// Simulated seconds per wall second.
    pub speedup: f64,
    pub safety: Safety,
}

impl SimSpec {
    /// The simulated airframe the mission's `[mavlink]` section describes.
    pub fn from_config(frame: Frame, sysid: u8, site: Site, m: &fleet_mission::config::MavlinkConfig) -> Self {
        let max_speed = match frame {
            Frame::Boat => m.boat_speed_ms,
            Frame::Multirotor => m.multirotor_speed_ms,
        };
        let action = |name: &str| Action::from_name(name).unwrap_or(Action::Rtl);
        let safety = Safety {
            fence_action: action(&m.fence_action),
            battery_mah: m.battery_mah,
            battery_low_mah: m.battery_low_mah,
            low_battery_action: action(&m.low_battery_action),
            ..Safety::default()
        };
        Self {
            frame,
            sysid,
            site,
            max_speed,
            turn_rate: m.boat_turn_rate_dps.to_radians(),
            cruise_alt: m.cruise_alt_m,
            speedup: m.sim_speedup,
            safety,
        }
    }
}

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
    tries: u32,
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
    /// Wall seconds since boot.
    pub wall_s: f64,
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
            consumed_mah,
            draw_a: IDLE_DRAW_A,
            failsafe: None,
            out: vec![],
        }
    }

    pub fn role(&self) -> Option<Role> {
        self.spec.frame.role(self.mode)
    }

    /// Messages to send (replies and events), oldest first.
    pub fn take(&mut self) -> Vec<MavMessage> {
        std::mem::take(&mut self.out)
    }

    fn for_me(&self, msg: &MavMessage) -> bool {
        msg.target_system_id().is_none_or(|t| t == 0 || t == self.spec.sysid)
    }

    fn ack(&mut self, command: MavCmd, ok: bool) {
        let result = if ok {
            MavResult::MAV_RESULT_ACCEPTED
        } else {
            MavResult::MAV_RESULT_DENIED
        };
        self.out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command,
            result,
            ..Default::default()
        }));
    }

    fn set_mode(&mut self, mode: u32) -> bool {
        let Some(role) = self.spec.frame.role(mode) else {
            return false;
        };
        if role == Role::Auto && self.mode != mode {
            if self.mission_run == Run::Complete {
                // AUTO again after the end: from the start, as ArduPilot does.
                self.current = self.first_item();
            }
            self.current = self.current.clamp(
                self.first_item(),
                self.mission.len().saturating_sub(1).max(self.first_item() as usize) as u16,
            );
            self.mission_run = Run::Started;
        }
        if role != Role::Guided {
            self.goal = None;
        }
        self.mode = mode;
        true
    }

    /// The surface (boats) or cruise altitude (multirotors) under a point.
    fn at_altitude(&self, mut p: Vector3<f64>) -> Vector3<f64> {
        p.z = match self.spec.frame {
            Frame::Boat => 0.0,
            Frame::Multirotor => p.z.min(0.0),
        };
        p
    }

    fn command(&mut self, command: MavCmd, p: [f32; 7], global: Option<(f64, f64, f64)>) {
        use MavCmd::*;
        let ok = match command {
            MAV_CMD_COMPONENT_ARM_DISARM => {
                self.armed = p[0] >= 0.5;
                true
            }
            MAV_CMD_DO_SET_MODE => self.set_mode(p[1] as u32),
            MAV_CMD_NAV_RETURN_TO_LAUNCH => self.set_mode(self.spec.frame.mode(Role::Return)),
            MAV_CMD_MISSION_START => self.mission.len() > 1 && self.set_mode(self.spec.frame.mode(Role::Auto)),
            MAV_CMD_DO_PAUSE_CONTINUE if p[0] < 0.5 => {
                self.mode_before_pause = Some(self.mode);
                self.set_mode(self.spec.frame.hold_mode())
            }
            MAV_CMD_DO_PAUSE_CONTINUE => {
                let back = self
                    .mode_before_pause
                    .take()
                    .unwrap_or(self.spec.frame.mode(Role::Guided));
                self.set_mode(back)
            }
            MAV_CMD_DO_REPOSITION => {
                // COMMAND_INT carries degrees * 1e7 in x, y; COMMAND_LONG degrees in params 5, 6.
                let (lat, lon, alt) = global.unwrap_or((p[4] as f64, p[5] as f64, p[6] as f64));
                if lat.is_finite() && lon.is_finite() && lat.abs() <= 90.0 && lon.abs() <= 180.0 {
                    let up = if alt.is_finite() { alt } else { self.spec.cruise_alt };
                    let ned = self.at_altitude(self.spec.site.ned_of_global(lat, lon, self.spec.site.origin[2] + up));
                    if self.fenced_out(&ned) {
                        false
                    } else {
                        self.set_mode(self.spec.frame.mode(Role::Guided));
                        self.goal = Some(ned);
                        true
                    }
                } else {
                    false
                }
            }
            // Ground stations ask for home on connecting (MAVProxy, QGC); the message follows
            // the ack, as ArduPilot sends it.
            MAV_CMD_GET_HOME_POSITION => return self.send_home(command),
            MAV_CMD_REQUEST_MESSAGE if p[0] as u32 == HOME_POSITION_DATA::ID => return self.send_home(command),
            _ => {
                self.out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                    command,
                    result: MavResult::MAV_RESULT_UNSUPPORTED,
                    ..Default::default()
                }));
                return;
            }
        };
        self.ack(command, ok);
    }

    /// PARAM_VALUE of parameter `index` (nothing for an index it does not have).
    fn param_value(&mut self, index: usize) {
        if let Some((name, value)) = params::by_index(&self.spec, index) {
            self.out.push(MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
                param_value: value,
                param_count: params::count(self.spec.frame) as u16,
                param_index: index as u16,
                param_id: name.into(),
                param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
            }));
        }
    }

    /// Accept `command` and send HOME_POSITION after the ack.
    fn send_home(&mut self, command: MavCmd) {
        self.ack(command, true);
        let home = self.home_position();
        self.out.push(home);
    }

    /// HOME_POSITION: where it booted, which RTL returns to.
    fn home_position(&self) -> MavMessage {
        let (lat, lon, alt) = self.spec.site.global_of(&self.home);
        MavMessage::HOME_POSITION(HOME_POSITION_DATA {
            latitude: (lat * 1e7).round() as i32,
            longitude: (lon * 1e7).round() as i32,
            altitude: (alt * 1e3).round() as i32,
            x: self.home.x as f32,
            y: self.home.y as f32,
            z: self.home.z as f32,
            q: [1.0, 0.0, 0.0, 0.0],
            ..Default::default()
        })
    }

    fn mission_ack(&mut self, to: (u8, u8), result: MavMissionResult, mission_type: MavMissionType) {
        self.out.push(MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: to.0,
            target_component: to.1,
            mavtype: result,
            mission_type,
            ..Default::default()
        }));
    }

    fn request_item(&mut self, seq: u16) {
        if let Some(u) = &mut self.upload {
            u.asked_at = self.wall_s;
            let (target_system, target_component) = u.from;
            self.out.push(MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq,
                target_system,
                target_component,
                mission_type: u.kind,
            }));
        }
    }

    /// The stored items of a mission type (`None`: a type we do not keep).
    fn items(&self, kind: MavMissionType) -> Option<&Vec<MISSION_ITEM_INT_DATA>> {
        match kind {
            MavMissionType::MAV_MISSION_TYPE_MISSION => Some(&self.mission),
            MavMissionType::MAV_MISSION_TYPE_FENCE => Some(&self.fence_items),
            MavMissionType::MAV_MISSION_TYPE_RALLY => Some(&self.rally),
            _ => None,
        }
    }

    /// Whether an uploaded item may be in a list of its type.
    fn valid_item(kind: MavMissionType, item: &MISSION_ITEM_INT_DATA) -> Result<(), MavMissionResult> {
        use MavCmd::*;
        match kind {
            MavMissionType::MAV_MISSION_TYPE_FENCE => match item.command {
                MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
                | MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
                | MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
                | MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION
                | MAV_CMD_NAV_FENCE_RETURN_POINT => Ok(()),
                _ => Err(MavMissionResult::MAV_MISSION_UNSUPPORTED),
            },
            MavMissionType::MAV_MISSION_TYPE_RALLY if item.command != MAV_CMD_NAV_RALLY_POINT => {
                Err(MavMissionResult::MAV_MISSION_UNSUPPORTED)
            }
            MavMissionType::MAV_MISSION_TYPE_RALLY => Ok(()),
            _ => Self::flyable(item),
        }
    }

    /// Store a finished upload; a fence must describe a fence.
    fn store(&mut self, kind: MavMissionType, items: Vec<MISSION_ITEM_INT_DATA>) -> MavMissionResult {
        match kind {
            MavMissionType::MAV_MISSION_TYPE_FENCE => match Geofence::from_items(&items, &self.spec.site) {
                Ok(f) => {
                    (self.fence, self.fence_items, self.breached) = (f, items, false);
                }
                Err(why) => return why,
            },
            MavMissionType::MAV_MISSION_TYPE_RALLY => self.rally = items,
            _ => {
                self.mission = items;
                self.current = self.first_item();
                self.mission_run = Run::NotStarted;
            }
        }
        MavMissionResult::MAV_MISSION_ACCEPTED
    }

    /// Whether the enforced fence keeps the vehicle from a place.
    fn fenced_out(&self, ned: &Vector3<f64>) -> bool {
        self.spec.safety.fence_enable && !self.fence.contains(ned)
    }

    fn say(&mut self, severity: MavSeverity, text: &str) {
        self.out.push(MavMessage::STATUSTEXT(STATUSTEXT_DATA {
            severity,
            text: text.into(),
            ..Default::default()
        }));
    }

    /// The first item AUTO runs: 1 (item 0 is home), or 0 with no mission.
    fn first_item(&self) -> u16 {
        u16::from(self.mission.len() > 1)
    }

    /// Whether an uploaded mission item is one we can run (item 0, home, is not run).
    fn flyable(item: &MISSION_ITEM_INT_DATA) -> Result<(), MavMissionResult> {
        use MavFrame::*;
        match item.command {
            _ if item.seq == 0 => return Ok(()),
            MavCmd::MAV_CMD_DO_CHANGE_SPEED if item.param2.is_finite() => return Ok(()),
            MavCmd::MAV_CMD_DO_CHANGE_SPEED => return Err(MavMissionResult::MAV_MISSION_INVALID_PARAM2),
            MavCmd::MAV_CMD_NAV_WAYPOINT => {}
            _ => return Err(MavMissionResult::MAV_MISSION_UNSUPPORTED),
        }
        if !matches!(
            item.frame,
            MAV_FRAME_GLOBAL | MAV_FRAME_GLOBAL_INT | MAV_FRAME_GLOBAL_RELATIVE_ALT | MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        ) {
            return Err(MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME);
        }
        if item.x.unsigned_abs() > 900_000_000 || item.y.unsigned_abs() > 1_800_000_000 || !item.z.is_finite() {
            return Err(MavMissionResult::MAV_MISSION_INVALID);
        }
        Ok(())
    }

    fn item_position(&self, item: &MISSION_ITEM_INT_DATA) -> Vector3<f64> {
        let relative = matches!(
            item.frame,
            MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        );
        let alt = if relative {
            self.spec.site.origin[2] + item.z as f64
        } else {
            item.z as f64
        };
        self.at_altitude(
            self.spec
                .site
                .ned_of_global(item.x as f64 * 1e-7, item.y as f64 * 1e-7, alt),
        )
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
                if self.role() == Some(Role::Guided) && t.coordinate_frame == MavFrame::MAV_FRAME_LOCAL_NED =>
            {
                let p = Vector3::new(t.x as f64, t.y as f64, t.z as f64);
                if p.iter().all(|v| v.is_finite()) {
                    let p = self.at_altitude(p);
                    // No ack exists for this message: refused, said, and the old goal kept.
                    if self.fenced_out(&p) {
                        self.say(
                            MavSeverity::MAV_SEVERITY_WARNING,
                            "Fence: target outside the fence, refused",
                        );
                    } else {
                        self.goal = Some(p);
                    }
                }
            }
            MavMessage::MISSION_COUNT(c) => {
                let room = match c.mission_type {
                    MavMissionType::MAV_MISSION_TYPE_MISSION | MavMissionType::MAV_MISSION_TYPE_RALLY => {
                        Some(MAX_MISSION_ITEMS)
                    }
                    MavMissionType::MAV_MISSION_TYPE_FENCE => Some(MAX_FENCE_ITEMS),
                    _ => None,
                };
                match room {
                    None => self.mission_ack(sender, MavMissionResult::MAV_MISSION_UNSUPPORTED, c.mission_type),
                    Some(_) if c.count == 0 => {
                        let r = self.store(c.mission_type, vec![]);
                        self.mission_ack(sender, r, c.mission_type);
                    }
                    Some(n) if c.count > n => {
                        self.mission_ack(sender, MavMissionResult::MAV_MISSION_NO_SPACE, c.mission_type)
                    }
                    Some(_) => {
                        self.upload = Some(Upload {
                            kind: c.mission_type,
                            count: c.count,
                            items: vec![],
                            from: sender,
                            asked_at: self.wall_s,
                            tries: 0,
                        });
                        self.request_item(0);
                    }
                }
            }
            MavMessage::MISSION_ITEM_INT(item) => self.take_item(sender, item),
            MavMessage::MISSION_REQUEST_LIST(r) => {
                let mission_type = r.mission_type;
                match self.items(mission_type).map(|v| v.len() as u16) {
                    Some(count) => self.out.push(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                        count,
                        target_system: sender.0,
                        target_component: sender.1,
                        mission_type,
                        ..Default::default()
                    })),
                    None => self.mission_ack(sender, MavMissionResult::MAV_MISSION_UNSUPPORTED, mission_type),
                }
            }
            MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA { seq, mission_type, .. })
            | MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA { seq, mission_type, .. }) => {
                match self.items(*mission_type).and_then(|v| v.get(*seq as usize)) {
                    Some(item) => {
                        let mut item = item.clone();
                        if *mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION && *seq == 0 {
                            // Item 0 reads back as home, as ArduPilot keeps it.
                            let (lat, lon, alt) = self.spec.site.global_of(&self.home);
                            (item.command, item.frame, item.x, item.y, item.z) = (
                                MavCmd::MAV_CMD_NAV_WAYPOINT,
                                MavFrame::MAV_FRAME_GLOBAL,
                                (lat * 1e7).round() as i32,
                                (lon * 1e7).round() as i32,
                                alt as f32,
                            );
                        }
                        let current = *mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION && *seq == self.current;
                        (
                            item.target_system,
                            item.target_component,
                            item.current,
                            item.mission_type,
                        ) = (sender.0, sender.1, u8::from(current), *mission_type);
                        self.out.push(MavMessage::MISSION_ITEM_INT(item));
                    }
                    None => self.mission_ack(sender, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE, *mission_type),
                }
            }
            MavMessage::MISSION_CLEAR_ALL(c) => {
                let all = c.mission_type == MavMissionType::MAV_MISSION_TYPE_ALL;
                for kind in [
                    MavMissionType::MAV_MISSION_TYPE_MISSION,
                    MavMissionType::MAV_MISSION_TYPE_FENCE,
                    MavMissionType::MAV_MISSION_TYPE_RALLY,
                ] {
                    if all || kind == c.mission_type {
                        self.store(kind, vec![]);
                    }
                }
                self.mission_ack(sender, MavMissionResult::MAV_MISSION_ACCEPTED, c.mission_type);
            }
            MavMessage::MISSION_SET_CURRENT(s) if (s.seq as usize) < self.mission.len() => {
                self.current = s.seq;
                self.out.push(self.mission_current());
            }
            MavMessage::PARAM_REQUEST_LIST(_) => {
                for i in 0..params::count(self.spec.frame) {
                    self.param_value(i);
                }
            }
            MavMessage::PARAM_REQUEST_READ(r) => {
                // By index, or by name when the index is -1 (the protocol's rule).
                let index = if r.param_index >= 0 {
                    Some(r.param_index as usize)
                } else {
                    r.param_id
                        .to_str()
                        .ok()
                        .and_then(|n| params::index_of(self.spec.frame, n))
                };
                if let Some(i) = index {
                    self.param_value(i);
                }
            }
            MavMessage::PARAM_SET(p) => {
                // Unknown names get no answer (as ArduPilot); a refused value is answered with
                // the one in force, so the ground station sees it did not take.
                if let Some(i) = p
                    .param_id
                    .to_str()
                    .ok()
                    .and_then(|n| params::index_of(self.spec.frame, n))
                {
                    params::set(&mut self.spec, i, p.param_value);
                    self.param_value(i);
                }
            }
            _ => {}
        }
    }

    fn take_item(&mut self, sender: (u8, u8), item: &MISSION_ITEM_INT_DATA) {
        let Some(u) = &mut self.upload else { return };
        if u.from != sender || u.kind != item.mission_type {
            return;
        }
        let (next, kind) = (u.items.len() as u16, u.kind);
        if item.seq < next {
            // A repeat: the request for the next was lost; ask again.
            self.request_item(next);
            return;
        }
        if item.seq > next {
            self.mission_ack(sender, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE, kind);
            self.upload = None;
            return;
        }
        if let Err(why) = Self::valid_item(kind, item) {
            self.mission_ack(sender, why, kind);
            self.upload = None;
            return;
        }
        u.items.push(item.clone());
        u.tries = 0;
        if u.items.len() as u16 == u.count {
            let done = self.upload.take().expect("upload in progress");
            let result = self.store(kind, done.items);
            self.mission_ack(sender, result, kind);
        } else {
            self.request_item(next + 1);
        }
    }

    /// Where the mode sends the vehicle (`None`: stay).
    fn destination(&self) -> Option<Vector3<f64>> {
        match self.role()? {
            Role::Guided => self.goal,
            Role::Auto => self.mission.get(self.current as usize).map(|i| self.item_position(i)),
            Role::Return => Some(self.at_altitude(self.return_point())),
            Role::Hold => None,
        }
    }

    /// Advance `dt_wall` wall seconds (`dt_wall * speedup` of simulated flight).
    pub fn step(&mut self, dt_wall: f64) {
        self.wall_s += dt_wall;
        self.retry_upload();
        self.run_do_items();
        let mut left = dt_wall * self.spec.speedup;
        let mut moved = 0.0;
        while left > 1e-12 {
            let dt = left.min(SUBSTEP_S);
            left -= dt;
            let before = self.pos;
            let reached = match (self.armed, self.destination()) {
                (true, Some(goal)) => self.move_toward(goal, dt),
                _ => false,
            };
            self.vel = (self.pos - before) / dt;
            moved += (self.pos - before).norm();
            if reached && self.role() == Some(Role::Auto) {
                self.item_reached();
            }
            self.check_fence();
        }
        // Draw by how fast it went, as a share of its top speed.
        let sim_s = dt_wall * self.spec.speedup;
        self.draw_a = match self.armed {
            false => IDLE_DRAW_A,
            true if sim_s > 0.0 => {
                ARMED_DRAW_A + (MAX_DRAW_A - ARMED_DRAW_A) * (moved / sim_s / self.spec.max_speed).clamp(0.0, 1.0)
            }
            true => ARMED_DRAW_A,
        };
        self.consumed_mah += self.draw_a * sim_s / 3.6;
        self.check_battery();
    }

    /// The charge left (mAh).
    pub fn remaining_mah(&self) -> f64 {
        (self.spec.safety.battery_mah - self.consumed_mah).max(0.0)
    }

    /// Below the low mark, armed: the battery failsafe's action, once.
    fn check_battery(&mut self) {
        if self.failsafe.is_some() || !self.armed || self.remaining_mah() > self.spec.safety.battery_low_mah {
            return;
        }
        let action = self.spec.safety.low_battery_action;
        self.failsafe = Some("battery low");
        self.act_on(action);
        let text = format!(
            "Failsafe: battery low ({:.0} mAh left): {}",
            self.remaining_mah(),
            ["continue", "RTL", "HOLD"][action as usize]
        );
        self.say(MavSeverity::MAV_SEVERITY_CRITICAL, &text);
    }

    /// A failsafe's action: the mode it calls for (none for `Continue`).
    fn act_on(&mut self, action: Action) {
        match action {
            Action::Rtl => self.set_mode(self.spec.frame.mode(Role::Return)),
            Action::Hold => self.set_mode(self.spec.frame.hold_mode()),
            Action::Continue => true,
        };
    }

    /// Where RTL goes: the nearest rally point, or home (at cruise altitude).
    fn return_point(&self) -> Vector3<f64> {
        let home = Vector3::new(self.home.x, self.home.y, -self.spec.cruise_alt);
        self.rally
            .iter()
            .map(|r| {
                let mut p = self.item_position(r);
                p.z = -self.spec.cruise_alt;
                p
            })
            .min_by(|a, b| (a - self.pos).xy().norm().total_cmp(&(b - self.pos).xy().norm()))
            .unwrap_or(home)
    }

    /// A breach of the enforced fence triggers the fence action once; back inside, it is over.
    fn check_fence(&mut self) {
        let out = self.fenced_out(&self.pos);
        if out && !self.breached {
            self.breach_count = self.breach_count.saturating_add(1);
            let action = self.spec.safety.fence_action;
            self.act_on(action);
            self.say(
                MavSeverity::MAV_SEVERITY_CRITICAL,
                &format!("Fence breach: {}", ["report only", "RTL", "HOLD"][action as usize]),
            );
        }
        self.breached = out;
    }

    fn retry_upload(&mut self) {
        let Some(u) = &mut self.upload else { return };
        if self.wall_s - u.asked_at < UPLOAD_RETRY_S {
            return;
        }
        u.tries += 1;
        let (from, tries, next, kind) = (u.from, u.tries, u.items.len() as u16, u.kind);
        if tries > 5 {
            self.upload = None;
            self.mission_ack(from, MavMissionResult::MAV_MISSION_OPERATION_CANCELLED, kind);
        } else {
            self.request_item(next);
        }
    }

    /// In AUTO, the DO items at the current place in the sequence are done at once.
    fn run_do_items(&mut self) {
        while self.role() == Some(Role::Auto) {
            let Some(item) = self.mission.get(self.current as usize) else {
                return;
            };
            if item.command != MavCmd::MAV_CMD_DO_CHANGE_SPEED {
                return;
            }
            if item.param2 > 0.0 {
                self.spec.max_speed = item.param2 as f64;
            }
            self.advance();
        }
    }

    /// On to the next item; after the last, hold there (as ArduRover does).
    fn advance(&mut self) {
        if (self.current as usize) + 1 < self.mission.len() {
            self.current += 1;
        } else {
            self.mission_run = Run::Complete;
            self.set_mode(self.spec.frame.hold_mode());
        }
        self.out.push(self.mission_current());
    }

    fn item_reached(&mut self) {
        let seq = self.current;
        self.out
            .push(MavMessage::MISSION_ITEM_REACHED(MISSION_ITEM_REACHED_DATA { seq }));
        self.advance();
        self.run_do_items();
    }

    /// One physics step toward `goal`; whether it is reached.
    fn move_toward(&mut self, goal: Vector3<f64>, dt: f64) -> bool {
        let d = goal - self.pos;
        let dist = d.norm();
        let reach = self.spec.max_speed * dt;
        if dist <= 1e-9 {
            return true;
        }
        match self.spec.frame {
            Frame::Multirotor => {
                self.heading = d.y.atan2(d.x);
                if dist <= reach {
                    self.pos = goal;
                    return true;
                }
                self.pos += d * (reach / dist);
            }
            Frame::Boat => {
                let err = wrap(d.y.atan2(d.x) - self.heading);
                let turn = err.clamp(-self.spec.turn_rate * dt, self.spec.turn_rate * dt);
                self.heading = wrap(self.heading + turn);
                let left = err - turn;
                if dist <= reach && left.abs() < PI / 2.0 {
                    self.pos = goal;
                    return true;
                }
                // Slow while turning; pivot when the goal is behind.
                let step = reach * left.cos().max(0.0);
                self.pos += Vector3::new(self.heading.cos(), self.heading.sin(), 0.0) * step;
            }
        }
        false
    }

    fn time_boot_ms(&self) -> u32 {
        (self.wall_s * 1000.0) as u32
    }

    pub fn heartbeat(&self) -> MavMessage {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED;
        if self.armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        match self.role() {
            Some(Role::Guided) => base |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED,
            Some(Role::Auto) => {
                base |= MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
            }
            _ => {}
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: self.mode,
            mavtype: self.spec.frame.mav_type(),
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode: base,
            system_status: match (self.failsafe, self.armed) {
                (Some(_), _) => MavState::MAV_STATE_CRITICAL,
                (None, true) => MavState::MAV_STATE_ACTIVE,
                (None, false) => MavState::MAV_STATE_STANDBY,
            },
            mavlink_version: 3,
        })
    }

    /// The charge left (a fraction) and the pack's voltage (mV): a 3-cell pack, 12.6 V full,
    /// 11.0 V empty.
    fn battery_now(&self) -> (f64, u16) {
        let fraction = self.remaining_mah() / self.spec.safety.battery_mah;
        (fraction, (11_000.0 + 1_600.0 * fraction) as u16)
    }

    pub fn sys_status(&self) -> MavMessage {
        let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_BATTERY;
        // The geofence bit is healthy while there is no breach, whether or not a fence is
        // enabled (ArduPilot's rule): ground stations announce "fence breach" when it is not.
        let fence = MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE;
        let enforced = if self.spec.safety.fence_enable {
            fence
        } else {
            MavSysStatusSensor::empty()
        };
        MavMessage::SYS_STATUS(SYS_STATUS_DATA {
            onboard_control_sensors_present: sensors | enforced,
            onboard_control_sensors_enabled: sensors | enforced,
            onboard_control_sensors_health: sensors
                | if self.breached {
                    MavSysStatusSensor::empty()
                } else {
                    fence
                },
            load: 150,
            voltage_battery: self.battery_now().1,
            current_battery: (self.draw_a * 100.0).round() as i16,
            battery_remaining: (100.0 * self.battery_now().0).round() as i8,
            ..Default::default()
        })
    }

    /// The position messages (sent at 10 Hz).
    pub fn position(&self) -> Vec<MavMessage> {
        let (lat, lon, alt) = self.spec.site.global_of(&self.pos);
        let hdg = (self.heading.to_degrees().rem_euclid(360.0) * 100.0) as u16;
        let t = self.time_boot_ms();
        let mut out = vec![
            MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms: t,
                lat: (lat * 1e7).round() as i32,
                lon: (lon * 1e7).round() as i32,
                alt: (alt * 1000.0).round() as i32,
                relative_alt: (-self.pos.z * 1000.0).round() as i32,
                vx: (self.vel.x * 100.0) as i16,
                vy: (self.vel.y * 100.0) as i16,
                vz: (self.vel.z * 100.0) as i16,
                hdg,
            }),
            MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: t,
                x: self.pos.x as f32,
                y: self.pos.y as f32,
                z: self.pos.z as f32,
                vx: self.vel.x as f32,
                vy: self.vel.y as f32,
                vz: self.vel.z as f32,
            }),
        ];
        if let (Some(Role::Guided), Some(g)) = (self.role(), self.goal) {
            out.push(MavMessage::POSITION_TARGET_LOCAL_NED(POSITION_TARGET_LOCAL_NED_DATA {
                time_boot_ms: t,
                x: g.x as f32,
                y: g.y as f32,
                z: g.z as f32,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            }));
        }
        out
    }

    /// The messages sent once a second besides HEARTBEAT and SYS_STATUS, as ArduPilot streams
    /// them: BATTERY_STATUS, HOME_POSITION, MISSION_CURRENT, and FENCE_STATUS while a fence is
    /// enforced (MAVSDK reads battery and home only from these).
    pub fn slow(&self) -> Vec<MavMessage> {
        let (fraction, millivolts) = self.battery_now();
        let mut cells = [u16::MAX; 10];
        cells[0] = millivolts;
        let mut out = vec![
            MavMessage::BATTERY_STATUS(BATTERY_STATUS_DATA {
                current_consumed: self.consumed_mah.round() as i32,
                energy_consumed: -1,
                temperature: i16::MAX,
                voltages: cells,
                current_battery: (self.draw_a * 100.0).round() as i16,
                battery_function: MavBatteryFunction::MAV_BATTERY_FUNCTION_ALL,
                mavtype: MavBatteryType::MAV_BATTERY_TYPE_LIPO,
                battery_remaining: (100.0 * fraction).round() as i8,
                ..Default::default()
            }),
            self.home_position(),
            self.mission_current(),
        ];
        out.extend(self.fence_status());
        out
    }

    /// FENCE_STATUS (sent at 1 Hz while a fence is enforced).
    pub fn fence_status(&self) -> Option<MavMessage> {
        self.spec.safety.fence_enable.then(|| {
            MavMessage::FENCE_STATUS(FENCE_STATUS_DATA {
                breach_status: u8::from(self.breached),
                breach_count: self.breach_count,
                breach_type: if self.breached {
                    FenceBreach::FENCE_BREACH_BOUNDARY
                } else {
                    FenceBreach::FENCE_BREACH_NONE
                },
                breach_time: (self.wall_s * 1000.0) as u32,
                ..Default::default()
            })
        })
    }

    /// MISSION_CURRENT with the mission's state, as MAVSDK reads progress from it: the total
    /// leaves out home (item 0).
    pub fn mission_current(&self) -> MavMessage {
        let auto = self.role() == Some(Role::Auto);
        let mission_state = match (self.mission.len() > 1, self.mission_run) {
            (false, _) => MissionState::MISSION_STATE_NO_MISSION,
            (true, Run::NotStarted) => MissionState::MISSION_STATE_NOT_STARTED,
            (true, Run::Complete) => MissionState::MISSION_STATE_COMPLETE,
            (true, Run::Started) if auto => MissionState::MISSION_STATE_ACTIVE,
            (true, Run::Started) => MissionState::MISSION_STATE_PAUSED,
        };
        let total = if self.mission.len() > 1 {
            self.mission.len() as u16 - 1
        } else {
            u16::MAX
        };
        let seq = if self.mission_run == Run::Complete {
            self.mission.len() as u16
        } else {
            self.current
        };
        MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA {
            seq,
            total,
            mission_state,
            mission_mode: if auto { 1 } else { 2 },
            ..Default::default()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_mission::config::MavlinkConfig;
    use fleet_mission::grid::Grid;

    fn sim(frame: Frame) -> SimAutopilot {
        let site = Site::new(&MavlinkConfig::default(), &Grid::new(48, 96, 1.0).unwrap());
        let spec = SimSpec {
            frame,
            sysid: 3,
            site,
            max_speed: 2.0,
            turn_rate: PI / 2.0,
            cruise_alt: 30.0,
            speedup: 1.0,
            safety: Default::default(),
        };
        SimAutopilot::new(spec, Vector3::zeros())
    }

    const GCS: MavHeader = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    };

    fn long(command: MavCmd, p1: f32, p2: f32) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command,
            param1: p1,
            param2: p2,
            target_system: 3,
            target_component: 1,
            ..Default::default()
        })
    }

    fn results(out: &[MavMessage]) -> Vec<MavResult> {
        out.iter()
            .filter_map(|m| {
                if let MavMessage::COMMAND_ACK(a) = m {
                    Some(a.result)
                } else {
                    None
                }
            })
            .collect()
    }

    #[test]
    fn home_parameters_and_the_fence_bit_answer_as_ardupilot_does() {
        let mut s = sim(Frame::Boat);
        // Home: acked, then HOME_POSITION at the boot place (the site's origin here).
        s.handle(&GCS, &long(MavCmd::MAV_CMD_GET_HOME_POSITION, 0.0, 0.0));
        let out = s.take();
        assert_eq!(results(&out), vec![MavResult::MAV_RESULT_ACCEPTED]);
        let Some(MavMessage::HOME_POSITION(h)) = out.get(1) else {
            panic!("no HOME_POSITION after the ack: {out:?}")
        };
        let [lat, lon, _] = s.spec.site.origin;
        assert_eq!(
            (h.latitude, h.longitude),
            ((lat * 1e7).round() as i32, (lon * 1e7).round() as i32)
        );
        s.handle(
            &GCS,
            &long(MavCmd::MAV_CMD_REQUEST_MESSAGE, HOME_POSITION_DATA::ID as f32, 0.0),
        );
        assert!(matches!(s.take().get(1), Some(MavMessage::HOME_POSITION(_))));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_REQUEST_MESSAGE, 33.0, 0.0));
        assert_eq!(results(&s.take()), vec![MavResult::MAV_RESULT_UNSUPPORTED]);

        // The whole list, each value what the simulation uses, counted and indexed.
        s.handle(
            &GCS,
            &MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
                target_system: 3,
                target_component: 1,
            }),
        );
        let values: Vec<PARAM_VALUE_DATA> = s
            .take()
            .into_iter()
            .filter_map(|m| {
                if let MavMessage::PARAM_VALUE(v) = m {
                    Some(v)
                } else {
                    None
                }
            })
            .collect();
        let named = |n: &str| {
            values
                .iter()
                .find(|v| v.param_id.to_str().unwrap() == n)
                .unwrap_or_else(|| panic!("no {n} in {values:?}"))
                .param_value
        };
        assert_eq!(values.len(), 8);
        assert!(values
            .iter()
            .enumerate()
            .all(|(i, v)| v.param_index as usize == i && v.param_count == 8));
        assert!(
            values
                .windows(2)
                .all(|w| w[0].param_id.to_str().unwrap() < w[1].param_id.to_str().unwrap()),
            "sorted by name, as ArduPilot lists them"
        );
        assert_eq!(
            (named("CRUISE_SPEED"), named("SYSID_THISMAV"), named("FENCE_ENABLE")),
            (2.0, 3.0, 0.0)
        );
        assert!((named("ATC_STR_RAT_MAX") - 90.0).abs() < 1e-4);
        // A set takes effect in the simulation and is echoed; a bad or read-only one is not taken.
        let set = |name: &str, v: f32| {
            MavMessage::PARAM_SET(PARAM_SET_DATA {
                param_value: v,
                target_system: 3,
                target_component: 1,
                param_id: name.into(),
                param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
            })
        };
        s.handle(&GCS, &set("CRUISE_SPEED", 3.5));
        assert!(matches!(s.take().as_slice(), [MavMessage::PARAM_VALUE(v)] if v.param_value == 3.5));
        assert_eq!(s.spec.max_speed, 3.5);
        for (name, v, now) in [
            ("CRUISE_SPEED", -1.0, 3.5),
            ("SYSID_THISMAV", 9.0, 3.0),
            ("FENCE_ENABLE", 0.5, 0.0),
            ("FENCE_ACTION", 7.0, 1.0),
        ] {
            s.handle(&GCS, &set(name, v));
            assert!(
                matches!(s.take().as_slice(), [MavMessage::PARAM_VALUE(p)] if p.param_value == now),
                "{name}"
            );
        }
        s.handle(&GCS, &set("NO_SUCH_PARAM", 1.0));
        assert!(s.take().is_empty());
        let read = |index: i16, name: &str| {
            MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                param_index: index,
                target_system: 3,
                target_component: 1,
                param_id: name.into(),
            })
        };
        s.handle(&GCS, &read(-1, "CRUISE_SPEED"));
        s.handle(&GCS, &read(7, ""));
        let got: Vec<String> = s
            .take()
            .into_iter()
            .filter_map(|m| {
                if let MavMessage::PARAM_VALUE(v) = m {
                    Some(v.param_id.to_str().unwrap().to_string())
                } else {
                    None
                }
            })
            .collect();
        assert_eq!(got, ["CRUISE_SPEED", "SYSID_THISMAV"]);

        // No fence breach: the geofence health bit is set.
        let MavMessage::SYS_STATUS(st) = s.sys_status() else {
            panic!()
        };
        assert!(st
            .onboard_control_sensors_health
            .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE));
    }

    #[test]
    fn a_boat_arms_goes_guided_and_reaches_its_target_within_its_limits() {
        let mut s = sim(Frame::Boat);
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 15.0));
        assert_eq!(results(&s.take()), [MavResult::MAV_RESULT_ACCEPTED; 2]);
        // Behind it (heading north, goal south-east): it must turn first.
        let goal = Vector3::new(-6.0, 8.0, 5.0);
        let target = SET_POSITION_TARGET_LOCAL_NED_DATA {
            x: goal.x as f32,
            y: goal.y as f32,
            z: goal.z as f32,
            target_system: 3,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            ..Default::default()
        };
        s.handle(&GCS, &MavMessage::SET_POSITION_TARGET_LOCAL_NED(target));
        let mut t = 0.0;
        let mut last = s.pos;
        let mut last_heading = s.heading;
        while s.pos.xy() != goal.xy() && t < 30.0 {
            s.step(0.05);
            t += 0.05;
            assert!((s.pos - last).norm() <= 2.0 * 0.05 + 1e-9, "speed limit");
            assert!(
                wrap(s.heading - last_heading).abs() <= PI / 2.0 * 0.05 + 1e-9,
                "turn-rate limit"
            );
            assert_eq!(s.pos.z, 0.0, "a boat stays on the surface");
            (last, last_heading) = (s.pos, s.heading);
        }
        // 10 m at 2 m/s, plus the turn: more than 5 s, well under 30.
        assert!(t > 5.0 && t < 30.0, "took {t} s");
    }

    #[test]
    fn an_unarmed_or_held_vehicle_does_not_move_and_unknown_commands_are_unsupported() {
        let mut s = sim(Frame::Multirotor);
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 4.0));
        s.handle(
            &GCS,
            &MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
                x: 10.0,
                target_system: 3,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            }),
        );
        s.step(1.0);
        assert_eq!(s.pos, Vector3::zeros(), "disarmed");
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 0.0, 0.0));
        s.step(1.0);
        assert_eq!(s.pos, Vector3::zeros(), "held");
        assert_eq!(s.role(), Some(Role::Hold));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 1.0, 0.0));
        assert_eq!(s.role(), Some(Role::Guided));
        s.take();
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 99.0));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_GRIPPER, 0.0, 0.0));
        assert_eq!(
            results(&s.take()),
            [MavResult::MAV_RESULT_DENIED, MavResult::MAV_RESULT_UNSUPPORTED]
        );
        // Another system's command is not ours.
        let mut other = long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 0.0);
        *other.target_system_id_mut().unwrap() = 4;
        s.handle(&GCS, &other);
        assert!(s.armed && s.take().is_empty());
    }

    #[test]
    fn a_mission_uploads_with_the_handshake_runs_and_reports_each_item() {
        let mut s = sim(Frame::Boat);
        let site = s.spec.site;
        s.handle(
            &GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 5,
                target_system: 3,
                target_component: 1,
                ..Default::default()
            }),
        );
        // Home (never flown), a waypoint, a speed change to 4 m/s, two more waypoints.
        let wps = [(99.0, 99.0), (5.0, 0.0), (f64::NAN, 4.0), (5.0, 5.0), (0.0, 5.0)];
        for (seq, (n, e)) in wps.iter().enumerate() {
            let out = s.take();
            assert!(
                matches!(&out[..], [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == seq as u16 && r.target_system == 255),
                "{out:?}"
            );
            if n.is_nan() {
                let speed = MISSION_ITEM_INT_DATA {
                    seq: seq as u16,
                    command: MavCmd::MAV_CMD_DO_CHANGE_SPEED,
                    param2: *e as f32,
                    target_system: 3,
                    ..Default::default()
                };
                s.handle(&GCS, &MavMessage::MISSION_ITEM_INT(speed));
                continue;
            }
            let (lat, lon, _) = site.global_of(&Vector3::new(*n, *e, 0.0));
            let item = MISSION_ITEM_INT_DATA {
                seq: seq as u16,
                command: MavCmd::MAV_CMD_NAV_WAYPOINT,
                frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                x: (lat * 1e7).round() as i32,
                y: (lon * 1e7).round() as i32,
                target_system: 3,
                autocontinue: 1,
                ..Default::default()
            };
            s.handle(&GCS, &MavMessage::MISSION_ITEM_INT(item));
        }
        assert!(
            matches!(&s.take()[..], [MavMessage::MISSION_ACK(a)] if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED)
        );
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0));
        let mut reached = vec![];
        for _ in 0..2000 {
            s.step(0.05);
            reached.extend(s.take().into_iter().filter_map(|m| {
                if let MavMessage::MISSION_ITEM_REACHED(r) = m {
                    Some(r.seq)
                } else {
                    None
                }
            }));
        }
        assert_eq!(reached, [1, 3, 4], "the waypoints, from 1 (0 is home)");
        assert!((s.pos - Vector3::new(0.0, 5.0, 0.0)).norm() < 0.05, "{}", s.pos);
        assert_eq!(s.role(), Some(Role::Hold), "holds at the end");
        assert_eq!(s.spec.max_speed, 4.0, "the speed item was done");
        // Download gives the same items back, home as item 0.
        s.handle(
            &GCS,
            &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
                target_system: 3,
                target_component: 1,
                ..Default::default()
            }),
        );
        assert!(matches!(&s.take()[..], [MavMessage::MISSION_COUNT(c)] if c.count == 5));
        s.handle(
            &GCS,
            &MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq: 0,
                target_system: 3,
                target_component: 1,
                ..Default::default()
            }),
        );
        let [lat, lon, _] = site.origin;
        assert!(
            matches!(&s.take()[..], [MavMessage::MISSION_ITEM_INT(i)] if (i.x, i.y) == ((lat * 1e7).round() as i32, (lon * 1e7).round() as i32)),
            "item 0 is home"
        );
    }

    #[test]
    fn return_to_launch_brings_it_home_and_reposition_sends_it_out() {
        let mut s = sim(Frame::Multirotor);
        let site = s.spec.site;
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        // DO_REPOSITION by COMMAND_INT (degrees * 1e7) to 40 m north, 30 m east, 20 m up.
        let (lat, lon, _) = site.global_of(&Vector3::new(40.0, 30.0, 0.0));
        let c = COMMAND_INT_DATA {
            command: MavCmd::MAV_CMD_DO_REPOSITION,
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            z: 20.0,
            target_system: 3,
            ..Default::default()
        };
        s.handle(&GCS, &MavMessage::COMMAND_INT(c));
        assert_eq!(s.role(), Some(Role::Guided));
        for _ in 0..1000 {
            s.step(0.05);
        }
        assert!((s.pos - Vector3::new(40.0, 30.0, -20.0)).norm() < 0.05, "{}", s.pos);
        s.handle(&GCS, &long(MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0));
        assert_eq!(s.role(), Some(Role::Return));
        for _ in 0..1000 {
            s.step(0.05);
        }
        assert!(
            s.pos.xy().norm() < 0.05 && (s.pos.z + 30.0).abs() < 0.05,
            "home at cruise altitude: {}",
            s.pos
        );
        assert!(results(&s.take()).iter().all(|r| *r == MavResult::MAV_RESULT_ACCEPTED));
    }

    #[test]
    fn a_stalled_upload_is_asked_again_then_cancelled() {
        let mut s = sim(Frame::Boat);
        s.handle(
            &GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 2,
                target_system: 3,
                target_component: 1,
                ..Default::default()
            }),
        );
        s.take();
        let mut asks = 0;
        let mut cancelled = false;
        for _ in 0..100 {
            s.step(0.1);
            for m in s.take() {
                match m {
                    MavMessage::MISSION_REQUEST_INT(r) => asks += usize::from(r.seq == 0),
                    MavMessage::MISSION_ACK(a) => {
                        cancelled = a.mavtype == MavMissionResult::MAV_MISSION_OPERATION_CANCELLED
                    }
                    _ => {}
                }
            }
        }
        assert_eq!((asks, cancelled), (5, true));
    }

    /// Upload `items` of `kind` with the handshake; the ack's result.
    fn upload(s: &mut SimAutopilot, kind: MavMissionType, items: &[MISSION_ITEM_INT_DATA]) -> MavMissionResult {
        s.handle(
            &GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: items.len() as u16,
                target_system: 3,
                target_component: 1,
                mission_type: kind,
                ..Default::default()
            }),
        );
        for _ in 0..=items.len() {
            for m in s.take() {
                match m {
                    MavMessage::MISSION_REQUEST_INT(r) => {
                        assert_eq!(r.mission_type, kind);
                        let item = MISSION_ITEM_INT_DATA {
                            seq: r.seq,
                            target_system: 3,
                            mission_type: kind,
                            ..items[r.seq as usize].clone()
                        };
                        s.handle(&GCS, &MavMessage::MISSION_ITEM_INT(item));
                    }
                    MavMessage::MISSION_ACK(a) => {
                        assert_eq!(a.mission_type, kind);
                        return a.mavtype;
                    }
                    _ => {}
                }
            }
        }
        panic!("no MISSION_ACK");
    }

    fn at(site: &Site, command: MavCmd, param1: f32, north: f64, east: f64) -> MISSION_ITEM_INT_DATA {
        let (lat, lon, _) = site.global_of(&Vector3::new(north, east, 0.0));
        MISSION_ITEM_INT_DATA {
            command,
            param1,
            frame: MavFrame::MAV_FRAME_GLOBAL_INT,
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            ..Default::default()
        }
    }

    #[test]
    fn an_enforced_fence_refuses_targets_outside_and_a_breach_returns_to_the_nearest_rally_point() {
        let mut s = sim(Frame::Boat);
        let site = s.spec.site;
        // A 40 m x 40 m square fence (north, east from 0 to 40) and two rally points.
        let corners = [(0.0, 0.0), (0.0, 40.0), (40.0, 40.0), (40.0, 0.0)];
        let fence: Vec<_> = corners
            .iter()
            .map(|&(n, e)| at(&site, MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 4.0, n, e))
            .collect();
        assert_eq!(
            upload(&mut s, MavMissionType::MAV_MISSION_TYPE_FENCE, &fence),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        let rally = [
            at(&site, MavCmd::MAV_CMD_NAV_RALLY_POINT, 0.0, 2.0, 2.0),
            at(&site, MavCmd::MAV_CMD_NAV_RALLY_POINT, 0.0, 30.0, 35.0),
        ];
        assert_eq!(
            upload(&mut s, MavMissionType::MAV_MISSION_TYPE_RALLY, &rally),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        // A mission item is no fence, and the mission list is not touched by either upload.
        let wp = at(&site, MavCmd::MAV_CMD_NAV_WAYPOINT, 0.0, 0.0, 0.0);
        assert_eq!(
            upload(
                &mut s,
                MavMissionType::MAV_MISSION_TYPE_FENCE,
                std::slice::from_ref(&wp)
            ),
            MavMissionResult::MAV_MISSION_UNSUPPORTED
        );
        assert!(s.mission.is_empty() && s.fence_items.len() == 4 && s.rally.len() == 2);
        // Each list downloads by its type.
        s.handle(
            &GCS,
            &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
                target_system: 3,
                target_component: 1,
                mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
            }),
        );
        assert!(
            matches!(&s.take()[..], [MavMessage::MISSION_COUNT(c)] if c.count == 4 && c.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE)
        );

        // Not yet enforced: a target outside is taken.
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 15.0));
        s.take();
        let target = |n: f32, e: f32| {
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
                x: n,
                y: e,
                target_system: 3,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            })
        };
        s.handle(&GCS, &target(60.0, 10.0));
        assert_eq!(s.goal.map(|g| g.x), Some(60.0));
        // Enforced: a target outside is refused (said; the goal stays), one inside is taken,
        // and a reposition outside is denied.
        let set = |name: &str, v: f32| {
            MavMessage::PARAM_SET(PARAM_SET_DATA {
                param_value: v,
                target_system: 3,
                target_component: 1,
                param_id: name.into(),
                param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
            })
        };
        s.handle(&GCS, &set("FENCE_ENABLE", 1.0));
        s.handle(&GCS, &target(10.0, 20.0));
        s.handle(&GCS, &target(10.0, 50.0));
        let out = s.take();
        assert!(
            out.iter().any(
                |m| matches!(m, MavMessage::STATUSTEXT(t) if t.text.to_str().unwrap().contains("outside the fence"))
            ),
            "{out:?}"
        );
        assert_eq!(s.goal.map(|g| (g.x, g.y)), Some((10.0, 20.0)));
        let (lat, lon, _) = site.global_of(&Vector3::new(10.0, 50.0, 0.0));
        let c = COMMAND_INT_DATA {
            command: MavCmd::MAV_CMD_DO_REPOSITION,
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            target_system: 3,
            ..Default::default()
        };
        s.handle(&GCS, &MavMessage::COMMAND_INT(c));
        assert_eq!(results(&s.take()), [MavResult::MAV_RESULT_DENIED]);
        let MavMessage::SYS_STATUS(st) = s.sys_status() else {
            panic!()
        };
        assert!(
            st.onboard_control_sensors_enabled
                .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE)
                && st
                    .onboard_control_sensors_health
                    .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE)
        );

        // A mission that leaves the fence (an operator's, in AUTO): breach, RTL to the nearer
        // rally point, said; the health bit drops while outside, and FENCE_STATUS counts it.
        let out_wp = at(&site, MavCmd::MAV_CMD_NAV_WAYPOINT, 0.0, 30.0, 60.0);
        assert_eq!(
            upload(&mut s, MavMissionType::MAV_MISSION_TYPE_MISSION, &[wp, out_wp]),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0));
        let mut said = vec![];
        let mut unhealthy = false;
        for _ in 0..1200 {
            s.step(0.05);
            said.extend(s.take().into_iter().filter_map(|m| {
                if let MavMessage::STATUSTEXT(t) = m {
                    Some(t.text.to_str().unwrap().to_string())
                } else {
                    None
                }
            }));
            if let MavMessage::SYS_STATUS(st) = s.sys_status() {
                unhealthy |= !st
                    .onboard_control_sensors_health
                    .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE);
            }
        }
        assert_eq!(s.role(), Some(Role::Return));
        assert!(said.iter().any(|t| t.contains("Fence breach: RTL")), "{said:?}");
        assert!(unhealthy && !s.breached, "unhealthy while outside, then back inside");
        assert!(
            (s.pos.xy() - Vector3::new(30.0, 35.0, 0.0).xy()).norm() < 0.05,
            "at the nearer rally point: {}",
            s.pos
        );
        assert!(
            matches!(s.fence_status(), Some(MavMessage::FENCE_STATUS(f)) if f.breach_count == 1 && f.breach_status == 0)
        );
    }

    #[test]
    fn the_battery_drains_with_use_and_running_low_takes_it_home_once() {
        let mut s = sim(Frame::Boat);
        // 100 mAh above the 4,000 mAh low mark.
        s.spec.safety.battery_start_mah = Some(4_100.0);
        s = SimAutopilot::new(s.spec.clone(), Vector3::new(1.0, 1.0, 0.0));
        let battery = |s: &SimAutopilot| {
            if let MavMessage::SYS_STATUS(st) = s.sys_status() {
                (st.battery_remaining, st.current_battery)
            } else {
                panic!()
            }
        };
        assert_eq!(battery(&s), (21, 5), "20.5 % left, 0.05 A disarmed");
        // Disarmed for a simulated hour: 50 mAh at 0.05 A.
        s.step(3600.0);
        assert!((s.consumed_mah - (15_900.0 + 50.0)).abs() < 1e-6, "{}", s.consumed_mah);
        assert!(s.failsafe.is_none(), "no failsafe disarmed");
        // Armed, driving away at full speed: 10 A, so 50 mAh take 18 s.
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 15.0));
        let target = SET_POSITION_TARGET_LOCAL_NED_DATA {
            x: 40.0,
            y: 1.0,
            target_system: 3,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            ..Default::default()
        };
        s.handle(&GCS, &MavMessage::SET_POSITION_TARGET_LOCAL_NED(target));
        s.take();
        let mut t = 0.0;
        while s.failsafe.is_none() && t < 60.0 {
            s.step(0.05);
            t += 0.05;
        }
        assert!((17.5..19.5).contains(&t), "ran low after {t} s");
        assert_eq!(s.role(), Some(Role::Return));
        let said = s.take();
        assert!(
            said.iter().any(|m| matches!(m, MavMessage::STATUSTEXT(x) if x.text.to_str().unwrap().starts_with("Failsafe: battery low") && x.severity == MavSeverity::MAV_SEVERITY_CRITICAL)),
            "{said:?}"
        );
        assert!(matches!(s.heartbeat(), MavMessage::HEARTBEAT(h) if h.system_status == MavState::MAV_STATE_CRITICAL));
        assert_eq!(battery(&s).0, 20);
        // Home, at the launch point; said once.
        for _ in 0..1000 {
            s.step(0.05);
        }
        assert!(
            (s.pos.xy() - Vector3::new(1.0, 1.0, 0.0).xy()).norm() < 0.05,
            "{}",
            s.pos
        );
        assert!(!s.take().iter().any(|m| matches!(m, MavMessage::STATUSTEXT(_))));
    }
}
