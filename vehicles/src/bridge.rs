//! The vehicle node's MAVLink bridge to its autopilot, reached by a connection string (`sim`
//! starts a simulated one in this process on a loopback UDP port; `udpin:`, `udpout:`,
//! `tcpout:`, `serial:` reach a real one). It learns the autopilot's system id from its
//! HEARTBEAT, arms it and sets GUIDED once, sends the planner's sensing places as guided
//! targets, reads the true position back, and declares the autopilot lost when HEARTBEATs stop.
//! Every message from the autopilot is also handed to the ground-station side as a MAVLink 2
//! frame; frames from ground stations addressed to this autopilot are passed on to it.
//! Unreadable input is counted and skipped; nothing here panics on what comes off a link.

use crate::autopilot::modes::{Frame, Role};
use crate::autopilot::serve;
use crate::autopilot::sim::{SimAutopilot, SimSpec};
use crate::link::{MavLink, Received};
use crate::signing::{LinkSigning, LINK_AUTOPILOT, LINK_BRIDGE};
use crate::upload::{self, Upload};
use fleet_mission::protocol::{AutopilotLink, AutopilotStatus};
use fleet_mission::signing_key::SigningKey;
use mavlink::dialects::common::*;
use mavlink::{MavHeader, MavlinkVersion, Message};
use nalgebra::Vector3;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tracing::{info, warn};

/// The companion computer's component id (MAV_COMP_ID_ONBOARD_COMPUTER).
pub const COMPANION_COMPONENT: u8 = 191;
/// Corners of a routed way are this far inside the fence (m).
pub const ROUTE_INSET_M: f64 = 1.0;
/// Longest MAVLink 2 frame.
pub const MAX_FRAME: usize = 280;

/// Where a bridge's autopilot is and how it moves.
#[derive(Debug, Clone)]
pub struct BridgeSpec {
    /// The airframe, the vehicle's system id in the mission (the simulated autopilot's; a real
    /// one has its own), the site and cruise altitude; for `sim` also its speeds and speed-up.
    pub vehicle: SimSpec,
    pub acceptance_m: f64,
    pub heartbeat_timeout: Duration,
    /// Where a `sim` autopilot starts (local NED).
    pub home: Vector3<f64>,
    /// The autopilot link's signing key (a `sim` autopilot gets it too), and whether its
    /// unsigned frames are taken (an autopilot that cannot sign).
    pub signing: Option<(SigningKey, bool)>,
    /// The site's fence, metres `[east, north]` of the origin (the mission's boundary, or the
    /// grid's extent): uploaded to the autopilot and enabled with `fence_action`
    /// (`FENCE_ACTION`'s number), and the way to each target is routed round it.
    pub fence_m: Vec<[f64; 2]>,
    pub fence_action: f32,
    /// Rally points (local NED), where RTL takes it: the fleet's launch points.
    pub rally: Vec<Vector3<f64>>,
}

/// Counters of the autopilot link (MAVLink messages).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct LinkCounters {
    pub received: u64,
    pub unreadable: u64,
    pub sent: u64,
    pub from_gcs: u64,
    pub refused_from_gcs: u64,
    /// Frames from the autopilot the signing check refused.
    pub refused_signing: u64,
}

#[derive(Debug, Default)]
struct Seen {
    sysid: Option<u8>,
    mode: Option<u32>,
    armed: bool,
    ned: Option<Vector3<f64>>,
    heartbeat: Option<Instant>,
    /// Arming and GUIDED are asked for once; `Some(true)` when done (or given up).
    setup: Option<bool>,
    /// Before that, the fence and rally points go up and the fence is enabled.
    uploads: Vec<Upload>,
    fence_enabled: bool,
    enable_tries: u32,
    prepared: bool,
    /// The leg of a routed way being driven now (local NED), when it is not the target itself.
    leg: Option<Vector3<f64>>,
    /// What the autopilot last said at critical level or worse (a failsafe, a fence breach),
    /// until it is back in GUIDED; its battery (fraction) and heading (degrees from north).
    failsafe: Option<String>,
    battery: Option<f64>,
    heading_deg: Option<f64>,
    counters: LinkCounters,
}

/// Frames for the ground-station side.
pub type GcsSink = tokio::sync::mpsc::UnboundedSender<Vec<u8>>;

pub struct Bridge {
    conn: Arc<MavLink>,
    spec: BridgeSpec,
    seen: Arc<Mutex<Seen>>,
    stop: Arc<AtomicBool>,
}

/// A free loopback UDP port (for the in-process simulated autopilot).
fn free_udp_port() -> std::io::Result<u16> {
    Ok(std::net::UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port())
}

fn latlon(spec: &BridgeSpec, ned: Vector3<f64>) -> [f64; 2] {
    let (lat, lon, _) = spec.vehicle.site.global_of(&ned);
    [lat, lon]
}

/// A MAVLink 2 frame of a message.
pub fn frame_bytes(header: MavHeader, msg: &MavMessage) -> Vec<u8> {
    let mut buf = Vec::with_capacity(64);
    // Writing to a Vec cannot fail.
    let _ = mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, header, msg);
    buf
}

/// The message of one MAVLink frame (v1 or v2), checked (CRC, known id, length).
pub fn parse_frame(bytes: &[u8]) -> Result<(MavHeader, MavMessage), String> {
    if bytes.len() > MAX_FRAME {
        return Err(format!("{} bytes: longer than a MAVLink frame", bytes.len()));
    }
    mavlink::MavlinkReader::new(bytes)
        .read_any_message::<MavMessage>()
        .map_err(|e| format!("not a MAVLink frame: {e}"))
}

fn lock(seen: &Mutex<Seen>) -> std::sync::MutexGuard<'_, Seen> {
    seen.lock().unwrap_or_else(|p| p.into_inner())
}

impl Bridge {
    /// Open the autopilot link; `gcs` receives every autopilot message as a frame.
    pub fn connect(address: &str, spec: BridgeSpec, gcs: Option<GcsSink>) -> anyhow::Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let address = if address == "sim" {
            let port = free_udp_port()?;
            let sim_signing = spec
                .signing
                .as_ref()
                .map(|(k, _)| LinkSigning::new(k.clone(), LINK_AUTOPILOT, false));
            serve::spawn(
                &format!("udpin:127.0.0.1:{port}"),
                SimAutopilot::new(spec.vehicle.clone(), spec.home),
                sim_signing,
                stop.clone(),
            )?;
            format!("udpout:127.0.0.1:{port}")
        } else {
            address.to_string()
        };
        let signing = spec
            .signing
            .as_ref()
            .map(|(k, unsigned)| LinkSigning::new(k.clone(), LINK_BRIDGE, *unsigned));
        let conn =
            Arc::new(MavLink::open(&address, signing).map_err(|e| anyhow::anyhow!("autopilot at {address}: {e}"))?);
        info!(autopilot = address, signed = conn.signed(), "MAVLink bridge up");
        let fence: Vec<[f64; 2]> = spec
            .fence_m
            .iter()
            .map(|&[e, n]| latlon(&spec, Vector3::new(n, e, 0.0)))
            .collect();
        let rally: Vec<[f64; 2]> = spec.rally.iter().map(|p| latlon(&spec, *p)).collect();
        let uploads = [
            (MavMissionType::MAV_MISSION_TYPE_FENCE, upload::fence_items(&fence)),
            (MavMissionType::MAV_MISSION_TYPE_RALLY, upload::rally_items(&rally)),
        ]
        .into_iter()
        .filter(|(_, items)| !items.is_empty())
        .map(|(kind, items)| Upload::new(kind, items))
        .collect();
        let bridge = Self {
            conn,
            spec,
            seen: Arc::new(Mutex::new(Seen {
                uploads,
                ..Seen::default()
            })),
            stop,
        };
        bridge.spawn_reader(gcs)?;
        bridge.spawn_heartbeat()?;
        Ok(bridge)
    }

    fn own_header(&self) -> MavHeader {
        MavHeader {
            system_id: self.spec.vehicle.sysid as u32,
            component_id: COMPANION_COMPONENT,
            sequence: 0,
        }
    }

    fn send(&self, msg: &MavMessage) {
        match self.conn.send(&self.own_header(), msg) {
            Ok(()) => lock(&self.seen).counters.sent += 1,
            Err(e) => warn!("to the autopilot: {e}"),
        }
    }

    fn spawn_reader(&self, gcs: Option<GcsSink>) -> std::io::Result<()> {
        let (conn, seen, frame, stop) = (
            self.conn.clone(),
            self.seen.clone(),
            self.spec.vehicle.frame,
            self.stop.clone(),
        );
        let mission_sysid = self.spec.vehicle.sysid;
        std::thread::Builder::new().name("mavlink-autopilot-rx".into()).spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                match conn.recv() {
                    Received::Frame(h, m, _) => {
                        {
                            let mut s = lock(&seen);
                            s.counters.received += 1;
                            // A companion (ours or another) is not the autopilot.
                            let from = u8::try_from(h.system_id).ok();
                            let autopilot = h.component_id != COMPANION_COMPONENT && from.is_some() && (s.sysid.is_none() || s.sysid == from);
                            match &m {
                                MavMessage::HEARTBEAT(hb) if hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID && autopilot => {
                                    if s.sysid.is_none() {
                                        info!(sysid = h.system_id, kind = ?hb.mavtype, mode = frame.name(hb.custom_mode), "autopilot found");
                                        if h.system_id != mission_sysid as u32 {
                                            warn!(autopilot = h.system_id, mission = mission_sysid, "the autopilot's \
                                                system id is not the one the mission gives this vehicle: the \
                                                ground-station gateway accepts and routes only the mission's (set \
                                                SYSID_THISMAV to it)");
                                        }
                                    }
                                    s.sysid = from;
                                    if frame.role(hb.custom_mode) == Some(Role::Guided) {
                                        s.failsafe = None;
                                    }
                                    s.mode = Some(hb.custom_mode);
                                    s.armed = hb.base_mode.contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
                                    s.heartbeat = Some(Instant::now());
                                }
                                // The autopilot's side of our fence and rally uploads (some
                                // autopilots still ask with the old MISSION_REQUEST).
                                #[allow(deprecated)]
                                MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA { seq, mission_type, target_component, .. }) | MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA { seq, mission_type, target_component, .. })
                                    if autopilot && *target_component == COMPANION_COMPONENT =>
                                {
                                    let reply = s.uploads.iter().find_map(|u| u.item(*mission_type, *seq, from.unwrap_or(0)));
                                    if let Some(r) = reply {
                                        let header = MavHeader { system_id: mission_sysid as u32, component_id: COMPANION_COMPONENT, sequence: 0 };
                                        if conn.send(&header, &r).is_ok() {
                                            s.counters.sent += 1;
                                        }
                                    }
                                }
                                MavMessage::MISSION_ACK(a) if autopilot && a.target_component == COMPANION_COMPONENT => {
                                    for u in &mut s.uploads {
                                        u.ack(a.mission_type, a.mavtype);
                                    }
                                }
                                // What the autopilot says (a fence breach, a failsafe) goes in the log.
                                MavMessage::STATUSTEXT(t) if autopilot && t.severity as u8 <= MavSeverity::MAV_SEVERITY_WARNING as u8 => {
                                    let text = t.text.to_str().unwrap_or("(not UTF-8)").to_string();
                                    warn!(sysid = h.system_id, "the autopilot says: {text}");
                                    if t.severity as u8 <= MavSeverity::MAV_SEVERITY_CRITICAL as u8 {
                                        s.failsafe = Some(text);
                                    }
                                }
                                MavMessage::SYS_STATUS(st) if autopilot && st.battery_remaining >= 0 => s.battery = Some((st.battery_remaining as f64 / 100.0).min(1.0)),
                                MavMessage::GLOBAL_POSITION_INT(g) if autopilot && g.hdg != u16::MAX => s.heading_deg = Some(g.hdg as f64 / 100.0),
                                MavMessage::PARAM_VALUE(p) if autopilot && p.param_id.to_str().is_ok_and(|n| n == "FENCE_ENABLE") => s.fence_enabled = p.param_value == 1.0,
                                MavMessage::LOCAL_POSITION_NED(p) if autopilot && s.sysid.is_some() => {
                                    let ned = Vector3::new(p.x as f64, p.y as f64, p.z as f64);
                                    if ned.iter().all(|v| v.is_finite()) {
                                        s.ned = Some(ned);
                                    } else {
                                        s.counters.unreadable += 1;
                                    }
                                }
                                _ => {}
                            }
                        }
                        if let Some(gcs) = &gcs {
                            let _ = gcs.send(frame_bytes(h, &m));
                        }
                    }
                    Received::Idle => std::thread::sleep(Duration::from_millis(20)),
                    Received::Refused(r) => {
                        let mut s = lock(&seen);
                        if s.counters.refused_signing == 0 {
                            warn!(reason = r.reason(), "a frame from the autopilot failed the signing check (refused; \
                                further ones are counted in telemetry)");
                        }
                        s.counters.refused_signing += 1;
                    }
                    Received::Unreadable(_) => lock(&seen).counters.unreadable += 1,
                }
            }
        })?;
        Ok(())
    }

    /// The companion's HEARTBEAT at 1 Hz (it also tells a `udpin:` autopilot where we are), and
    /// the one-time set-up: arm and GUIDED, asked again each second until the autopilot shows
    /// both, for at most 10 s.
    fn spawn_heartbeat(&self) -> std::io::Result<()> {
        let me = Self {
            conn: self.conn.clone(),
            spec: self.spec.clone(),
            seen: self.seen.clone(),
            stop: self.stop.clone(),
        };
        std::thread::Builder::new()
            .name("mavlink-companion".into())
            .spawn(move || {
                let (mut tries, mut tick) = (0, 0u64);
                while !me.stop.load(Ordering::Relaxed) {
                    // Every 100 ms: the set-up's progress; every second: the heartbeat and asking again.
                    std::thread::sleep(Duration::from_millis(100));
                    tick += 1;
                    let (target, mode, armed, setup) = {
                        let s = lock(&me.seen);
                        (s.sysid, s.mode, s.armed, s.setup)
                    };
                    let guided = me.spec.vehicle.frame.mode(Role::Guided);
                    let second = tick % 10 == 1;
                    if second {
                        me.send(&MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                            custom_mode: 0,
                            mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
                            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
                            base_mode: MavModeFlag::empty(),
                            system_status: MavState::MAV_STATE_ACTIVE,
                            mavlink_version: 3,
                        }));
                    }
                    let Some(target) = target else { continue };
                    if !me.prepared(target, second) {
                        continue;
                    }
                    match setup {
                        Some(true) => {}
                        _ if mode == Some(guided) && armed => {
                            lock(&me.seen).setup = Some(true);
                            info!(sysid = target, "autopilot armed and in GUIDED: the planner drives it");
                        }
                        Some(false) if !second => {}
                        _ if tries >= 10 => {
                            lock(&me.seen).setup = Some(true);
                            warn!(
                                sysid = target,
                                mode = me.spec.vehicle.frame.name(mode.unwrap_or(0)),
                                armed,
                                "the autopilot did not take GUIDED and arming: left to the operator"
                            );
                        }
                        _ => {
                            tries += 1;
                            lock(&me.seen).setup = Some(false);
                            let cmd = |command, param1, param2| {
                                MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                                    command,
                                    param1,
                                    param2,
                                    target_system: target,
                                    target_component: 1,
                                    ..Default::default()
                                })
                            };
                            me.send(&cmd(
                                MavCmd::MAV_CMD_DO_SET_MODE,
                                MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits() as f32,
                                guided as f32,
                            ));
                            me.send(&cmd(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
                        }
                    }
                }
            })?;
        Ok(())
    }

    /// The fence and rally points uploaded, then the fence enabled with the mission's action,
    /// each asked again each second; whether that is done (or given up: an autopilot without
    /// fences is still driven, inside the fence by the planner alone).
    fn prepared(&self, target: u8, second: bool) -> bool {
        let mut out = vec![];
        let done = {
            let mut s = lock(&self.seen);
            if s.prepared {
                return true;
            }
            // Each step goes out at once, and again each second while unanswered.
            if let Some(u) = s.uploads.iter_mut().find(|u| !u.finished()) {
                if second || !u.started() {
                    out.extend(u.count(target));
                }
                false
            } else if s
                .uploads
                .iter()
                .any(|u| u.kind == MavMissionType::MAV_MISSION_TYPE_FENCE && u.accepted())
                && !s.fence_enabled
                && s.enable_tries < upload::TRIES
            {
                if second || s.enable_tries == 0 {
                    s.enable_tries += 1;
                    let set = |name: &str, v: f32| {
                        MavMessage::PARAM_SET(PARAM_SET_DATA {
                            param_value: v,
                            target_system: target,
                            target_component: 1,
                            param_id: name.into(),
                            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
                        })
                    };
                    out = vec![set("FENCE_ACTION", self.spec.fence_action), set("FENCE_ENABLE", 1.0)];
                }
                false
            } else {
                s.prepared = true;
                let states: Vec<String> = s
                    .uploads
                    .iter()
                    .map(|u| format!("{:?}: {:?}", u.kind, u.state))
                    .collect();
                if s.uploads.is_empty() {
                    // No fence to upload (none given): nothing to say.
                } else if s.fence_enabled {
                    info!(sysid = target, uploads = ?states, "fence and rally points uploaded, fence enabled");
                } else {
                    warn!(sysid = target, uploads = ?states, "the autopilot did not take the fence (or enable it): \
                        the planner alone keeps it inside");
                }
                true
            }
        };
        for m in &out {
            self.send(m);
        }
        done
    }

    fn link_of(&self, s: &Seen) -> AutopilotLink {
        match (s.heartbeat, s.setup) {
            (Some(t), _) if t.elapsed() > self.spec.heartbeat_timeout => AutopilotLink::Lost,
            (Some(_), Some(true)) => AutopilotLink::Up,
            _ => AutopilotLink::Connecting,
        }
    }

    fn guided_of(&self, s: &Seen) -> bool {
        s.mode
            .is_some_and(|m| self.spec.vehicle.frame.role(m) == Some(Role::Guided))
            && s.armed
    }

    /// The link as telemetry reports it.
    pub fn status(&self) -> AutopilotStatus {
        let s = lock(&self.seen);
        AutopilotStatus {
            link: self.link_of(&s),
            sysid: s.sysid.unwrap_or(0),
            mode: s
                .mode
                .map_or_else(|| "unknown".into(), |m| self.spec.vehicle.frame.name(m)),
            armed: s.armed,
            guided: self.guided_of(&s),
            unreadable: s.counters.unreadable,
            refused_from_gcs: s.counters.refused_from_gcs,
            failsafe: s.failsafe.clone(),
        }
    }

    /// The autopilot's battery (fraction), if it reports one.
    pub fn battery(&self) -> Option<f64> {
        lock(&self.seen).battery
    }

    /// The autopilot's heading as telemetry has it (radians from +x, east, counter-clockwise).
    pub fn heading(&self) -> Option<f64> {
        lock(&self.seen)
            .heading_deg
            .map(|d| (std::f64::consts::FRAC_PI_2 - d.to_radians()).rem_euclid(std::f64::consts::TAU))
    }

    /// The link state alone (polled while waiting; no allocation).
    pub fn link(&self) -> AutopilotLink {
        self.link_of(&lock(&self.seen))
    }

    /// Whether the planner may send it targets now.
    pub fn drivable(&self) -> bool {
        let s = lock(&self.seen);
        self.guided_of(&s) && self.link_of(&s) != AutopilotLink::Lost
    }

    pub fn counters(&self) -> LinkCounters {
        lock(&self.seen).counters
    }

    /// Where the autopilot says it is, in grid metres.
    pub fn position(&self) -> Option<(f64, f64)> {
        lock(&self.seen).ned.map(|n| self.spec.vehicle.site.grid_of(&n))
    }

    fn target_ned(&self, grid_xy: (f64, f64)) -> Vector3<f64> {
        let up = match self.spec.vehicle.frame {
            Frame::Boat => 0.0,
            Frame::Multirotor => self.spec.vehicle.cruise_alt,
        };
        self.spec.vehicle.site.ned_of(grid_xy, up)
    }

    /// Send a guided target (a grid point); false when the autopilot is not ours to drive.
    pub fn goto(&self, grid_xy: (f64, f64)) -> bool {
        let Some(target) = lock(&self.seen).sysid else {
            return false;
        };
        if !self.drivable() {
            return false;
        }
        let goal = self.target_ned(grid_xy);
        // Round a concave fence's notch: the first leg of the way inside it.
        let ned = {
            let mut s = lock(&self.seen);
            let from = s.ned.map(|p| [p.y, p.x]);
            let first = from.and_then(|f| {
                fleet_mission::fence::route(&self.spec.fence_m, f, [goal.y, goal.x], ROUTE_INSET_M)
                    .first()
                    .copied()
            });
            let leg = first
                .map(|[e, n]| Vector3::new(n, e, goal.z))
                .filter(|l| (l - goal).xy().norm() > 1e-6);
            s.leg = leg;
            leg.unwrap_or(goal)
        };
        // Position only: ignore velocity, acceleration, yaw and yaw rate.
        let mask = PositionTargetTypemask::from_bits_truncate(0b0000_1101_1111_1000);
        self.send(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(
            SET_POSITION_TARGET_LOCAL_NED_DATA {
                x: ned.x as f32,
                y: ned.y as f32,
                z: ned.z as f32,
                type_mask: mask,
                target_system: target,
                target_component: 1,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            },
        ));
        true
    }

    /// A failsafe of the vehicle's own (its link to the server lost): the autopilot to
    /// `role` (Return or Hold), and `why` in telemetry until it is back in GUIDED.
    pub fn failsafe(&self, role: Role, why: &str) -> bool {
        let Some(target) = lock(&self.seen).sysid else {
            return false;
        };
        let frame = self.spec.vehicle.frame;
        let mode = if role == Role::Hold {
            frame.hold_mode()
        } else {
            frame.mode(role)
        };
        lock(&self.seen).failsafe = Some(why.to_string());
        self.set_mode(target, mode);
        true
    }

    /// Back from the vehicle's own failsafe: GUIDED again, so the planner drives it.
    pub fn rejoin(&self) {
        // (The lock is let go before sending: the send counts under the same lock.)
        let target = lock(&self.seen).sysid;
        if let Some(target) = target {
            self.set_mode(target, self.spec.vehicle.frame.mode(Role::Guided));
        }
    }

    fn set_mode(&self, target: u8, mode: u32) {
        self.send(&MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_DO_SET_MODE,
            param1: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits() as f32,
            param2: mode as f32,
            target_system: target,
            target_component: 1,
            ..Default::default()
        }));
    }

    /// Whether the autopilot took the site's fence and enforces it.
    pub fn fence_enabled(&self) -> bool {
        lock(&self.seen).fence_enabled
    }

    /// Whether it has reached the corner it was routed to (time for the next leg).
    pub fn at_corner(&self) -> bool {
        let s = lock(&self.seen);
        s.leg
            .zip(s.ned)
            .is_some_and(|(l, n)| (n.xy() - l.xy()).norm() <= self.spec.acceptance_m.max(ROUTE_INSET_M / 2.0))
    }

    /// Whether the autopilot is within the acceptance distance of a grid point.
    pub fn arrived(&self, grid_xy: (f64, f64)) -> bool {
        let goal = self.target_ned(grid_xy);
        lock(&self.seen)
            .ned
            .is_some_and(|n| (n.xy() - goal.xy()).norm() <= self.spec.acceptance_m)
    }

    /// A frame from a ground station: passed on when it is readable and addressed to this
    /// autopilot (or to every system); otherwise refused with the reason.
    pub fn from_gcs(&self, bytes: &[u8]) -> Result<(), String> {
        let result = parse_frame(bytes).and_then(|(h, m)| {
            let ours = lock(&self.seen).sysid.unwrap_or(self.spec.vehicle.sysid);
            match m.target_system_id() {
                Some(t) if t != 0 && t != ours => Err(format!("{} for system {t}, not {ours}", m.message_name())),
                _ => self.conn.send(&h, &m).map_err(|e| format!("to the autopilot: {e}")),
            }
        });
        let mut s = lock(&self.seen);
        match &result {
            Ok(()) => s.counters.from_gcs += 1,
            Err(_) => s.counters.refused_from_gcs += 1,
        }
        result
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}
