//! The bridge's actor: one task that owns everything the bridge knows about its autopilot and
//! wakes only when something happens. Its events, merged in one `select!`:
//!
//! | event | what it does |
//! |---|---|
//! | a read from the link | counts it, updates the state, answers an upload, forwards it, advances the set-up |
//! | a command from the node | a guided target (routed round the fence), a failsafe, GUIDED, a GCS frame, an instrument |
//! | the 1 Hz tick | the companion's HEARTBEAT; set-up steps not yet answered are asked again |
//! | the heartbeat timeout | the autopilot is lost |
//!
//! After each event the state goes out on `watch` channels: the whole state (position at the
//! autopilot's rate, for the drive), the status (link, mode, arming, failsafe: telemetry), and
//! the counters (read, never woken on).

mod fence;
mod modes;

use super::mode_request::ModeRequest;
use super::named::NamedSource;
use super::readiness::{self, is_arming_refusal};
use super::ROUTE_INSET_M;
use super::{airborne, guided, AutopilotState, BridgeSpec, Command, GcsSink, LinkCounters, COMPANION_COMPONENT};
use crate::autopilot::modes::Control;
use crate::link::{frame_bytes, MavLink, Received};
use crate::upload::{self, Upload};
use fleet_mission::protocol::{AutopilotLink, AutopilotStatus};
use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use nalgebra::Vector3;
use std::sync::Arc;
use tokio::sync::{mpsc, watch};
use tokio::time::{Duration, Instant};
use tracing::{info, warn};

/// GUIDED and arming are asked for at most this many times (once a second) once the autopilot
/// is ready, then left to the operator.
const SETUP_TRIES: u32 = 10;
/// The autopilot's settings are asked for at most this many times (once a second).
const PARAM_TRIES: u32 = 5;

/// The receiving ends of what the actor publishes.
pub(super) struct Channels {
    pub state: watch::Receiver<AutopilotState>,
    pub status: watch::Receiver<AutopilotStatus>,
    pub counters: watch::Receiver<LinkCounters>,
}

/// Where the one-time set-up is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Setup {
    /// Not asked yet (waiting for the autopilot to be ready).
    NotAsked,
    /// GUIDED and arming asked for this many times.
    Asked(u32),
    /// A copter armed in GUIDED, told to take off, since then.
    TakingOff(Instant),
    /// Armed in GUIDED, or given up (left to the operator).
    Done,
}

struct Actor {
    conn: Arc<MavLink>,
    spec: Arc<BridgeSpec>,
    gcs: Option<GcsSink>,
    state: AutopilotState,
    counters: LinkCounters,
    heartbeat_at: Option<Instant>,
    /// The first HEARTBEAT: readiness is waited for from then, up to `ready_timeout`.
    found_at: Option<Instant>,
    param_tries: u32,
    setup: Setup,
    /// The set-up ended with the planner driving it (so a disarm in GUIDED is set up again).
    driven: bool,
    /// Before the set-up, the fence and rally points go up and the fence is enabled.
    uploads: Vec<Upload>,
    enable_tries: u32,
    prepared: bool,
    /// The instrument on this link (`mavlink:NAME`), once the node asks for it.
    named: Option<NamedSource>,
    /// The vehicle's own mode request (a failsafe, a rejoin) until the heartbeat shows it.
    mode_request: Option<ModeRequest>,
    /// What of the autopilot's stream goes on to the ground stations.
    throttle: crate::throttle::Throttle,
    state_tx: watch::Sender<AutopilotState>,
    status_tx: watch::Sender<AutopilotStatus>,
    counters_tx: watch::Sender<LinkCounters>,
}

/// Start the actor on a thread of its own (a current-thread runtime: the bridge works the
/// same under the node's runtime, a test's, or none).
pub(super) fn spawn(
    conn: Arc<MavLink>,
    spec: Arc<BridgeSpec>,
    frames: mpsc::UnboundedReceiver<Received>,
    commands: mpsc::UnboundedReceiver<Command>,
    gcs: Option<GcsSink>,
) -> std::io::Result<Channels> {
    let (state_tx, state) = watch::channel(AutopilotState::default());
    let (status_tx, status) = watch::channel(status_of(&spec, &AutopilotState::default(), &LinkCounters::default()));
    let (counters_tx, counters) = watch::channel(LinkCounters::default());
    let uploads = uploads_of(&spec);
    let throttle = crate::throttle::Throttle::new(spec.mavlink_hz);
    let actor = Actor {
        conn,
        spec,
        gcs,
        state: AutopilotState::default(),
        counters: LinkCounters::default(),
        heartbeat_at: None,
        found_at: None,
        param_tries: 0,
        setup: Setup::NotAsked,
        driven: false,
        uploads,
        enable_tries: 0,
        prepared: false,
        named: None,
        mode_request: None,
        throttle,
        state_tx,
        status_tx,
        counters_tx,
    };
    let runtime = tokio::runtime::Builder::new_current_thread().enable_time().build()?;
    std::thread::Builder::new()
        .name("mavlink-bridge".into())
        .spawn(move || runtime.block_on(actor.run(frames, commands)))?;
    Ok(Channels {
        state,
        status,
        counters,
    })
}

/// The fence and rally lists to upload (none when the mission gives none).
fn uploads_of(spec: &BridgeSpec) -> Vec<Upload> {
    let latlon = |ned: Vector3<f64>| {
        let (lat, lon, _) = spec.vehicle.site.global_of(&ned);
        [lat, lon]
    };
    let fence: Vec<[f64; 2]> = spec
        .fence_m
        .iter()
        .map(|&[e, n]| latlon(Vector3::new(n, e, 0.0)))
        .collect();
    let rally: Vec<[f64; 2]> = spec.rally.iter().map(|p| latlon(*p)).collect();
    [
        (MavMissionType::MAV_MISSION_TYPE_FENCE, upload::fence_items(&fence)),
        (MavMissionType::MAV_MISSION_TYPE_RALLY, upload::rally_items(&rally)),
    ]
    .into_iter()
    .filter(|(_, items)| !items.is_empty())
    .map(|(kind, items)| Upload::new(kind, items))
    .collect()
}

/// The status telemetry carries (the ground station's refusals are the handle's to add).
fn status_of(spec: &BridgeSpec, s: &AutopilotState, c: &LinkCounters) -> AutopilotStatus {
    AutopilotStatus {
        link: s.link,
        sysid: s.sysid.unwrap_or(0),
        mode: s.mode.map_or_else(|| "unknown".into(), |m| spec.vehicle.frame.name(m)),
        armed: s.armed,
        guided: guided(spec, s),
        unreadable: c.unreadable,
        refused_from_gcs: 0,
        failsafe: s.breach.clone().or_else(|| s.failsafe.clone()),
        waiting: s.waiting.clone(),
    }
}

impl Actor {
    async fn run(
        mut self,
        mut frames: mpsc::UnboundedReceiver<Received>,
        mut commands: mpsc::UnboundedReceiver<Command>,
    ) {
        let mut second = tokio::time::interval(Duration::from_secs(1));
        second.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            // The autopilot is lost when its heartbeat is overdue (no timer before the first).
            let lost_at = self
                .heartbeat_at
                .filter(|_| self.state.link != AutopilotLink::Lost)
                .map(|t| t + self.spec.heartbeat_timeout);
            tokio::select! {
                got = frames.recv() => match got {
                    Some(r) => self.on_read(r),
                    None => return warn!("the autopilot link closed: the bridge stops reading it"),
                },
                command = commands.recv() => match command {
                    Some(c) => self.on_command(c),
                    // The node let go of its bridge.
                    None => return,
                },
                _ = second.tick() => self.on_second(),
                _ = sleep_until_some(lost_at) => {}
            }
            self.publish();
        }
    }

    /// The state out: to the drive and to telemetry when it changed, the counters silently.
    fn publish(&mut self) {
        self.state.link = self.link();
        let state = &self.state;
        self.state_tx.send_if_modified(|s| {
            let changed = s != state;
            if changed {
                *s = state.clone();
            }
            changed
        });
        let status = status_of(&self.spec, &self.state, &self.counters);
        self.status_tx.send_if_modified(|s| {
            // (The counters alone do not make a change worth a message.)
            let changed = AutopilotStatus {
                unreadable: s.unreadable,
                ..status.clone()
            } != *s;
            *s = status;
            changed
        });
        let counters = self.counters;
        self.counters_tx.send_if_modified(|c| {
            *c = counters;
            false
        });
    }

    fn link(&self) -> AutopilotLink {
        match (self.heartbeat_at, self.setup) {
            (Some(t), _) if t.elapsed() >= self.spec.heartbeat_timeout => AutopilotLink::Lost,
            (Some(_), Setup::Done) => AutopilotLink::Up,
            _ => AutopilotLink::Connecting,
        }
    }

    fn own_header(&self) -> MavHeader {
        MavHeader {
            system_id: self.spec.vehicle.sysid as u32,
            component_id: COMPANION_COMPONENT,
            sequence: 0,
        }
    }

    fn send(&mut self, msg: &MavMessage) {
        match self.conn.send(&self.own_header(), msg) {
            Ok(()) => self.counters.sent += 1,
            Err(e) => warn!("to the autopilot: {e}"),
        }
    }

    fn on_read(&mut self, r: Received) {
        match r {
            Received::Frame(h, m, _) => {
                self.counters.received += 1;
                self.on_frame(&h, &m);
                if let Some(gcs) = self
                    .gcs
                    .as_ref()
                    .filter(|_| self.throttle.pass(&m, std::time::Instant::now()))
                {
                    let event = crate::throttle::is_event(&m);
                    let _ = gcs.send(super::ToGcs {
                        frame: frame_bytes(h, &m),
                        event,
                    });
                }
                self.advance(false);
            }
            Received::Refused(r) => {
                if self.counters.refused_signing == 0 {
                    warn!(
                        reason = r.reason(),
                        "a frame from the autopilot failed the signing check (refused; further ones are counted in \
                         telemetry)"
                    );
                }
                self.counters.refused_signing += 1;
            }
            Received::Unreadable(_) => self.counters.unreadable += 1,
            Received::Idle | Received::Closed => {}
        }
    }

    /// A frame from the autopilot (a companion's, ours or another's, is not the autopilot).
    fn on_frame(&mut self, h: &MavHeader, m: &MavMessage) {
        let from = u8::try_from(h.system_id).ok();
        let sysid = self.state.sysid;
        let autopilot = h.component_id != COMPANION_COMPONENT && from.is_some() && (sysid.is_none() || sysid == from);
        if let Some(named) = self.named.as_mut().filter(|_| sysid.is_some() && sysid == from) {
            named.on_frame(m, autopilot);
        }
        if !autopilot {
            return;
        }
        match m {
            MavMessage::HEARTBEAT(hb) if hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID => {
                self.on_heartbeat(h.system_id, hb);
            }
            // The autopilot's side of our fence and rally uploads and their read-back (some
            // autopilots still ask with the old MISSION_REQUEST).
            #[allow(deprecated)]
            MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq,
                mission_type,
                target_component,
                ..
            })
            | MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
                seq,
                mission_type,
                target_component,
                ..
            }) if *target_component == COMPANION_COMPONENT => {
                let target = from.unwrap_or(0);
                self.answer_uploads(|u| u.on_request(*mission_type, *seq, target).into_iter().collect());
            }
            MavMessage::MISSION_ACK(a) if a.target_component == COMPANION_COMPONENT => {
                self.answer_uploads(|u| u.on_ack(a.mission_type, a.mavtype, from.unwrap_or(0)));
            }
            MavMessage::MISSION_COUNT(c) if c.target_component == COMPANION_COMPONENT => {
                self.answer_uploads(|u| u.on_count(c.mission_type, c.count, from.unwrap_or(0)));
            }
            MavMessage::MISSION_ITEM_INT(i) if i.target_component == COMPANION_COMPONENT => {
                self.answer_uploads(|u| u.on_item(i, from.unwrap_or(0)));
            }
            // What the autopilot says (a fence breach, a failsafe) goes in the log.
            MavMessage::STATUSTEXT(t) if t.severity as u8 <= MavSeverity::MAV_SEVERITY_WARNING as u8 => {
                let text = t.text.to_str().unwrap_or("(not UTF-8)").to_string();
                warn!(sysid = h.system_id, "the autopilot says: {text}");
                if is_arming_refusal(&text) {
                    // Why it will not arm: for the operator, not a failsafe.
                    self.state.readiness.refusal = Some(text);
                } else if t.severity as u8 <= MavSeverity::MAV_SEVERITY_CRITICAL as u8 {
                    self.state.failsafe = Some(text);
                }
            }
            MavMessage::FENCE_STATUS(f) => self.on_fence_status(f),
            MavMessage::SYS_STATUS(st) if st.battery_remaining >= 0 => {
                self.state.battery = Some((st.battery_remaining as f64 / 100.0).min(1.0));
            }
            MavMessage::GLOBAL_POSITION_INT(g) if sysid.is_some() => self.on_global_position(g),
            MavMessage::PARAM_VALUE(p) => {
                let name = p.param_id.to_str().unwrap_or_default();
                if name == "FENCE_ENABLE" {
                    self.state.fence_enabled = p.param_value == 1.0;
                } else if self.state.limits.on_param(name, p.param_value) {
                    self.on_limit(name);
                }
            }
            MavMessage::COMMAND_ACK(a) if a.command == MavCmd::MAV_CMD_DO_SET_MODE && refused(a.result) => {
                self.on_mode_refused(a.result)
            }
            m => self.state.readiness.on_message(m),
        }
    }

    /// Where the autopilot is, on the Earth (the frame every autopilot shares; its local NED
    /// has its EKF's origin, wherever it booted). (0, 0) is no fix.
    fn on_global_position(&mut self, g: &GLOBAL_POSITION_INT_DATA) {
        if g.hdg != u16::MAX {
            self.state.heading_deg = Some(g.hdg as f64 / 100.0);
        }
        if g.lat == 0 && g.lon == 0 {
            return;
        }
        let site = &self.spec.vehicle.site;
        let mut ned = site.ned_of_global(g.lat as f64 * 1e-7, g.lon as f64 * 1e-7, site.origin[2]);
        ned.z = -(g.relative_alt as f64) / 1000.0;
        if ned.iter().all(|v| v.is_finite()) && g.lat.abs() <= 900_000_000 && g.lon.abs() <= 1_800_000_000 {
            self.state.ned = Some(ned);
        } else {
            self.counters.unreadable += 1;
        }
    }

    /// A setting read from the autopilot: said once all are in, with what the bridge does.
    fn on_limit(&mut self, name: &str) {
        let l = &self.state.limits;
        if name.contains("SYSID") {
            if let Some((n, v)) = &l.sysid {
                if *v != self.spec.vehicle.sysid as f64 {
                    warn!(
                        param = n.as_str(),
                        value = v,
                        mission = self.spec.vehicle.sysid,
                        "the autopilot's system id is not the mission's"
                    );
                }
            }
            return;
        }
        if !l.complete(self.spec.vehicle.frame) {
            return;
        }
        info!(
            fence_margin = l.fence_margin,
            wp_radius = l.wp_radius,
            turn_radius = l.turn_radius,
            "the autopilot's own settings: targets count as reached within its WP_RADIUS, routes keep its margin plus turn"
        );
        if l.clearance() > self.spec.clearance_m + 1e-6 {
            warn!(
                autopilot = l.clearance(),
                mission = self.spec.clearance_m,
                "the autopilot keeps more room from the fence (FENCE_MARGIN + TURN_RADIUS) than the mission's launch and \
                 rally points have: it may refuse to arm or breach on returning; set [mavlink] fence_margin_m and \
                 turn_radius_m to its values"
            );
        }
    }

    fn on_heartbeat(&mut self, system_id: u32, hb: &HEARTBEAT_DATA) {
        let frame = self.spec.vehicle.frame;
        let mission_sysid = self.spec.vehicle.sysid;
        if self.state.sysid.is_none() {
            info!(sysid = system_id, kind = ?hb.mavtype, mode = frame.name(hb.custom_mode), "autopilot found");
            if system_id != mission_sysid as u32 {
                warn!(
                    autopilot = system_id,
                    mission = mission_sysid,
                    "the autopilot's system id is not the one the mission gives this vehicle: the ground-station \
                     gateway accepts and routes only the mission's (set MAV_SYSID to it; SYSID_THISMAV before ArduPilot 4.7)"
                );
            }
        }
        if self.found_at.is_none() {
            self.found_at = Some(Instant::now());
            self.ask_for_streams(system_id as u8);
        }
        if self.mode_request.is_some_and(|r| r.shown_by(hb.custom_mode)) {
            self.mode_request = None;
        }
        self.note_uncommanded(hb.custom_mode);
        let s = &mut self.state;
        s.sysid = u8::try_from(system_id).ok();
        // GUIDED ends a failsafe, unless it is a heartbeat sent before the failsafe's mode took.
        if frame.role(hb.custom_mode) == Some(Control::Guided) && self.mode_request.is_none() {
            s.failsafe = None;
        }
        s.mode = Some(hb.custom_mode);
        s.armed = hb.base_mode.contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
        self.heartbeat_at = Some(Instant::now());
    }

    /// A mode the autopilot took from GUIDED that neither the vehicle nor an operator through
    /// the gateway asked for (a failsafe, `FENCE_ACTION` on a breach, which ArduPilot takes
    /// without a word): the reason, until it is GUIDED again.
    fn note_uncommanded(&mut self, mode: u32) {
        let frame = self.spec.vehicle.frame;
        let s = &mut self.state;
        let left_guided = s
            .mode
            .is_some_and(|m| m != mode && frame.role(m) == Some(Control::Guided))
            && frame.role(mode) != Some(Control::Guided);
        if !left_guided {
            return;
        }
        if std::mem::take(&mut s.operator_mode) || self.mode_request.is_some() || s.failsafe.is_some() {
            return;
        }
        let why = format!("the autopilot left GUIDED for {} by itself", frame.name(mode));
        warn!(
            sysid = s.sysid,
            "{why}: left out of the allocation until it is GUIDED again"
        );
        s.failsafe = Some(why);
    }

    fn on_command(&mut self, c: Command) {
        if let Command::Listen(source) = c {
            self.named = Some(*source);
            return;
        }
        let Some(target) = self.state.sysid else { return };
        match c {
            Command::Listen(_) => {}
            Command::Goto(goal) => self.goto(target, goal),
            Command::Failsafe { mode, why } => {
                self.state.failsafe = Some(why);
                self.request_mode(target, mode);
            }
            Command::Rejoin => self.request_mode(target, self.spec.vehicle.frame.mode(Control::Guided)),
            Command::Forward(h, m) => {
                if is_mode_change(&m) {
                    self.state.operator_mode = true;
                    if self.mode_request.take().is_some() {
                        info!("an operator's mode change: the vehicle's own mode request is dropped");
                    }
                }
                if let Err(e) = self.conn.send(&h, &m) {
                    warn!("a ground station's frame to the autopilot: {e}");
                }
            }
        }
    }

    /// A guided target; the first leg of the way round a concave fence's notch.
    fn goto(&mut self, target: u8, goal: Vector3<f64>) {
        let from = self.state.ned.map(|p| [p.y, p.x]);
        let fence = &self.spec.fence_m;
        let inset = ROUTE_INSET_M.max(self.state.limits.clearance());
        let first = from.and_then(|f| {
            fleet_mission::fence::route(fence, f, [goal.y, goal.x], inset)
                .first()
                .copied()
        });
        let leg = first
            .map(|[e, n]| Vector3::new(n, e, goal.z))
            .filter(|l| (l - goal).xy().norm() > 1e-6);
        self.state.leg = leg;
        let ned = leg.unwrap_or(goal);
        // On the Earth, altitude above home: the autopilot's local frame has its EKF's origin,
        // which is where it booted, not the site's corner. Position only: ignore velocity,
        // acceleration, yaw and yaw rate.
        let (lat, lon, _) = self.spec.vehicle.site.global_of(&ned);
        let mask = PositionTargetTypemask::from_bits_truncate(0b0000_1101_1111_1000);
        #[allow(deprecated)]
        let frame = MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT;
        self.send(&MavMessage::SET_POSITION_TARGET_GLOBAL_INT(
            SET_POSITION_TARGET_GLOBAL_INT_DATA {
                lat_int: (lat * 1e7).round() as i32,
                lon_int: (lon * 1e7).round() as i32,
                alt: -ned.z as f32,
                type_mask: mask,
                target_system: target,
                target_component: 1,
                coordinate_frame: frame,
                ..Default::default()
            },
        ));
    }

    /// The messages the bridge reads, at the rates it needs (an autopilot that streams them
    /// already acks and goes on).
    fn ask_for_streams(&mut self, target: u8) {
        for (id, interval_us) in readiness::intervals() {
            self.send(&Self::command(
                target,
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                id as f32,
                interval_us,
            ));
        }
    }

    /// The autopilot's settings the bridge keeps to, asked for by name until answered.
    fn ask_for_limits(&mut self, target: u8) {
        if self.state.limits.complete(self.spec.vehicle.frame) || self.param_tries >= PARAM_TRIES {
            return;
        }
        self.param_tries += 1;
        for name in readiness::wanted(self.spec.vehicle.frame) {
            self.send(&MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                param_index: -1,
                target_system: target,
                target_component: 1,
                param_id: (*name).into(),
            }));
        }
    }

    fn command(target: u8, command: MavCmd, param1: f32, param2: f32) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command,
            param1,
            param2,
            target_system: target,
            target_component: 1,
            ..Default::default()
        })
    }

    fn set_mode(&mut self, target: u8, mode: u32) {
        let flag = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits() as f32;
        self.send(&Self::command(target, MavCmd::MAV_CMD_DO_SET_MODE, flag, mode as f32));
    }

    /// The companion's HEARTBEAT at 1 Hz (it also tells a `udpin:` autopilot where we are);
    /// unanswered set-up steps are asked again.
    fn on_second(&mut self) {
        self.send(&MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        }));
        if let Some(target) = self.state.sysid {
            self.follow_mode_request(target);
        }
        self.advance(true);
    }

    /// The set-up, a step further: the fence and rally points up and the fence enabled; then,
    /// once the autopilot is ready (or `ready_timeout` has passed), GUIDED and arming, asked
    /// again each `second` until it shows both, at most [`SETUP_TRIES`] times; a copter then
    /// takes off to its cruise altitude. An autopilot that disarms itself in GUIDED (a copter
    /// idle on the ground) is set up again, not left out.
    fn advance(&mut self, second: bool) {
        let Some(target) = self.state.sysid else { return };
        if second {
            self.ask_for_limits(target);
        }
        if !self.prepared(target, second) {
            return;
        }
        let guided_mode = self.spec.vehicle.frame.mode(Control::Guided);
        let in_guided = self.state.mode == Some(guided_mode);
        let armed = self.state.armed;
        let ready = self.setup != Setup::NotAsked || self.ready_to_ask();
        self.setup = match self.setup {
            Setup::Done if self.driven && in_guided && !armed && self.state.link != AutopilotLink::Lost => {
                self.driven = false;
                warn!(
                    sysid = target,
                    "the autopilot is disarmed in GUIDED (it landed, or disarmed itself): arming it again"
                );
                Setup::NotAsked
            }
            Setup::Done => {
                // Driven after all (the operator set it up): nothing to wait for.
                if in_guided && armed && airborne(&self.spec, &self.state) {
                    self.state.waiting = None;
                    self.driven = true;
                }
                Setup::Done
            }
            _ if in_guided && armed && airborne(&self.spec, &self.state) => {
                info!(sysid = target, "autopilot armed and in GUIDED: the planner drives it");
                self.driven = true;
                self.state.readiness.refusal = None;
                self.state.waiting = None;
                Setup::Done
            }
            _ if in_guided && armed => self.take_off(target, second),
            Setup::NotAsked if !ready => Setup::NotAsked,
            Setup::Asked(n) if !second => Setup::Asked(n),
            Setup::Asked(n) if n >= SETUP_TRIES => self.give_up(target),
            setup => {
                self.set_mode(target, guided_mode);
                self.send(&Self::command(target, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
                self.state.waiting = Some(match &self.state.readiness.refusal {
                    Some(r) => format!("arming ({r})"),
                    None => "GUIDED and arming".into(),
                });
                Setup::Asked(if let Setup::Asked(n) = setup { n + 1 } else { 1 })
            }
        };
    }

    /// Whether to ask for GUIDED and arming now: the autopilot says it is ready, or it has had
    /// `ready_timeout` to be (then its own checks decide, and their refusal is reported).
    fn ready_to_ask(&mut self) -> bool {
        let waiting = self.state.readiness.waiting_for(self.state.ned.is_some());
        let timed_out = self.found_at.is_some_and(|t| t.elapsed() >= self.spec.ready_timeout);
        if let (Some(w), true) = (&waiting, timed_out) {
            warn!(
                sysid = self.state.sysid,
                waiting = w.as_str(),
                "the autopilot is not ready after ready_timeout_s: asking for GUIDED and arming anyway"
            );
        }
        self.state.waiting.clone_from(&waiting);
        waiting.is_none() || timed_out
    }

    /// A copter armed in GUIDED on the ground: MAV_CMD_NAV_TAKEOFF to the cruise altitude,
    /// again each second until it climbs, up to `ready_timeout`.
    fn take_off(&mut self, target: u8, second: bool) -> Setup {
        let since = match self.setup {
            Setup::TakingOff(t) => t,
            _ => Instant::now(),
        };
        if since.elapsed() >= self.spec.ready_timeout {
            return self.give_up(target);
        }
        let fresh = !matches!(self.setup, Setup::TakingOff(_));
        let on_ground = self.state.ned.is_none_or(|n| -n.z < 1.0);
        if fresh || (second && on_ground) {
            let alt = self.spec.vehicle.cruise_alt as f32;
            self.send(&MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_NAV_TAKEOFF,
                param7: alt,
                target_system: target,
                target_component: 1,
                ..Default::default()
            }));
            self.state.waiting = Some(format!("takeoff to {alt} m"));
        }
        Setup::TakingOff(since)
    }

    /// GUIDED, arming or the takeoff did not happen: the vehicle is the operator's, and the
    /// autopilot's last refusal says why.
    fn give_up(&mut self, target: u8) -> Setup {
        let mode = self.spec.vehicle.frame.name(self.state.mode.unwrap_or(0));
        let why = self.state.readiness.refusal.clone().unwrap_or_default();
        warn!(
            sysid = target,
            mode,
            armed = self.state.armed,
            refusal = why.as_str(),
            "the autopilot did not take GUIDED, arming or the takeoff: left to the operator"
        );
        self.state.waiting = Some(format!("the operator (not ready to drive: {mode}; {why})"));
        Setup::Done
    }
}

/// Sleep until `at`, or forever without one.
async fn sleep_until_some(at: Option<Instant>) {
    match at {
        Some(t) => tokio::time::sleep_until(t).await,
        None => std::future::pending().await,
    }
}

/// A refusal that asking again does not change (TEMPORARILY_REJECTED and IN_PROGRESS may).
fn refused(result: MavResult) -> bool {
    matches!(
        result,
        MavResult::MAV_RESULT_DENIED | MavResult::MAV_RESULT_FAILED | MavResult::MAV_RESULT_UNSUPPORTED
    )
}

/// Whether a ground station's frame changes the autopilot's mode (SET_MODE is deprecated, and
/// ground stations still send it).
#[allow(deprecated)]
fn is_mode_change(m: &MavMessage) -> bool {
    use MavCmd::{MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_RETURN_TO_LAUNCH};
    match m {
        MavMessage::SET_MODE(_) => true,
        MavMessage::COMMAND_LONG(c) => matches!(c.command, MAV_CMD_DO_SET_MODE | MAV_CMD_NAV_RETURN_TO_LAUNCH),
        MavMessage::COMMAND_INT(c) => matches!(c.command, MAV_CMD_DO_SET_MODE | MAV_CMD_NAV_RETURN_TO_LAUNCH),
        _ => false,
    }
}
