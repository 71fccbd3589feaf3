//! The vehicle node's MAVLink bridge to its autopilot, reached by a connection string
//! (`udpin:`, `udpout:`, `tcpout:`, `serial:`; a simulated autopilot is started by whoever
//! composes the node, and reached the same way). It learns the autopilot's system id from its
//! HEARTBEAT, uploads the site's fence and rally points, arms it and sets GUIDED once, sends
//! the planner's sensing places as guided targets, reads the true position back, and declares
//! the autopilot lost when HEARTBEATs stop. Every message from the autopilot is also handed to
//! the ground-station side as a MAVLink 2 frame; frames from ground stations addressed to this
//! autopilot are passed on to it. Unreadable input is counted and skipped; nothing here panics
//! on what comes off a link.
//!
//! The bridge is an actor ([`actor`]): one task owns the link's state and wakes on what
//! happens (a frame read, a command, the 1 Hz companion heartbeat, the heartbeat timeout). It
//! publishes the autopilot's state on `watch` channels and takes commands on an `mpsc`; the
//! [`Bridge`] handle (and its cloneable [`Driver`]) is how the node reads and commands it.

mod actor;
mod mode_request;
mod named;
pub mod readiness;

use crate::autopilot::modes::{Control, Frame};
use crate::autopilot::sim::SimSpec;
use crate::link::{parse_frame, MavLink};
use crate::signing::{LinkSigning, LINK_BRIDGE};
use fleet_mission::protocol::{AutopilotLink, AutopilotStatus};
use fleet_mission::signing_key::SigningKey;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MavHeader, Message};
use nalgebra::Vector3;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tracing::{info, warn};

/// The companion computer's component id (MAV_COMP_ID_ONBOARD_COMPUTER).
pub const COMPANION_COMPONENT: u8 = 191;
/// Corners of a routed way are this far inside the fence (m).
pub const ROUTE_INSET_M: f64 = 1.0;

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
    /// Drive the vehicle even when its autopilot did not confirm the fence (`[mavlink]
    /// drive_without_fence`): otherwise it waits, the reason on telemetry.
    pub drive_without_fence: bool,
    /// Rally points (local NED), where RTL takes it: the fleet's launch points.
    pub rally: Vec<Vector3<f64>>,
    /// Each periodic message of the autopilot's stream goes to the ground stations at most
    /// this often (Hz; `[link] mavlink_hz`); events always go.
    pub mavlink_hz: f64,
    /// How long to wait for the autopilot to be ready before asking for GUIDED and arming
    /// anyway (`[mavlink] ready_timeout_s`).
    pub ready_timeout: Duration,
    /// How far inside the fence the mission set the launch and rally points (m): an autopilot
    /// keeping a larger margin plus turn is warned of.
    pub clearance_m: f64,
}

impl BridgeSpec {
    /// A bridge to `vehicle` with nothing to set up (no fence, rally points or signing), that
    /// passes the whole stream on, arrives within 0.25 m and asks to arm after 10 s at most:
    /// what a test or a bench starts from, changing what it is about.
    pub fn plain(vehicle: SimSpec) -> Self {
        Self {
            vehicle,
            acceptance_m: 0.25,
            heartbeat_timeout: Duration::from_secs(2),
            home: Vector3::zeros(),
            signing: None,
            fence_m: vec![],
            fence_action: 1.0,
            drive_without_fence: false,
            rally: vec![],
            mavlink_hz: f64::INFINITY,
            ready_timeout: Duration::from_secs(10),
            clearance_m: 0.0,
        }
    }
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

/// The autopilot as the bridge last heard it: a value, published whole on every change.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AutopilotState {
    pub link: AutopilotLink,
    pub sysid: Option<u8>,
    pub mode: Option<u32>,
    pub armed: bool,
    /// Local NED (m), when the autopilot has said where it is.
    pub ned: Option<Vector3<f64>>,
    /// The leg of a routed way being driven now (local NED), when it is not the target itself.
    pub leg: Option<Vector3<f64>>,
    /// What the autopilot last said at critical level or worse (a failsafe, a fence breach),
    /// or the vehicle's own failsafe, until it is back in GUIDED.
    pub failsafe: Option<String>,
    /// Battery (fraction) and heading (degrees from north), if it reports them.
    pub battery: Option<f64>,
    pub heading_deg: Option<f64>,
    pub fence_enabled: bool,
    /// Outside the fence, as the autopilot's FENCE_STATUS says (ArduPilot acts on a breach by
    /// its `FENCE_ACTION` without a text): why, until it reports the vehicle inside again.
    pub breach: Option<String>,
    /// An operator's mode change passed on to the autopilot, not yet shown by its HEARTBEAT:
    /// the mode that follows is the operator's, not one the autopilot took by itself.
    pub operator_mode: bool,
    /// What the autopilot has said of its readiness, and its own settings the bridge keeps to.
    pub readiness: readiness::Readiness,
    pub limits: readiness::Limits,
    /// What it waits for before the planner may drive it (a GPS fix, the EKF, its pre-arm
    /// checks, a takeoff), or why it was left to the operator; `None` once it is driven.
    pub waiting: Option<String>,
}

/// What the node asks of the bridge's actor.
#[derive(Debug)]
pub(crate) enum Command {
    /// Drive to a place (local NED), routed round the fence.
    Goto(Vector3<f64>),
    /// The vehicle's own failsafe: this mode, and why, until it is back in GUIDED.
    Failsafe { mode: u32, why: String },
    /// GUIDED again.
    Rejoin,
    /// A ground station's frame, checked, for the autopilot (boxed: a message is large).
    Forward(MavHeader, Box<MavMessage>),
    /// Read the instrument whose NAMED_VALUE_FLOAT come on this link.
    Listen(Box<named::NamedSource>),
}

/// A frame for the ground-station side, and whether it is an event (a reply, a text: sent at
/// once) rather than one of the periodic stream (which may wait to share a put with others).
#[derive(Debug)]
pub struct ToGcs {
    pub frame: Vec<u8>,
    pub event: bool,
}

/// Frames for the ground-station side.
pub type GcsSink = mpsc::UnboundedSender<ToGcs>;

/// The bridge's handle for driving: cloneable, so the node's drive task has its own.
#[derive(Clone)]
pub struct Driver {
    spec: Arc<BridgeSpec>,
    state: watch::Receiver<AutopilotState>,
    commands: mpsc::UnboundedSender<Command>,
}

/// The node's handle on its bridge: the [`Driver`] (through `Deref`), the autopilot's status,
/// the link's counters and the ground station's frames in. Dropping it ends the bridge.
pub struct Bridge {
    driver: Driver,
    status: watch::Receiver<AutopilotStatus>,
    counters: watch::Receiver<LinkCounters>,
    gcs: (u64, u64),
}

impl std::ops::Deref for Bridge {
    type Target = Driver;
    fn deref(&self) -> &Driver {
        &self.driver
    }
}

impl Bridge {
    /// Open the autopilot link and start the bridge's actor on a thread of its own (`gcs`
    /// receives every autopilot message as a frame).
    pub fn connect(address: &str, spec: BridgeSpec, gcs: Option<GcsSink>) -> anyhow::Result<Self> {
        let signing = spec
            .signing
            .as_ref()
            .map(|(k, unsigned)| LinkSigning::new(k.clone(), LINK_BRIDGE, *unsigned));
        let conn =
            Arc::new(MavLink::open(address, signing).map_err(|e| anyhow::anyhow!("autopilot at {address}: {e}"))?);
        info!(autopilot = address, signed = conn.signed(), "MAVLink bridge up");
        if spec.drive_without_fence && !spec.fence_m.is_empty() {
            warn!("[mavlink] drive_without_fence = true: driven even if the autopilot does not confirm the fence");
        }
        let frames = conn.reader("mavlink-autopilot-rx")?;
        let spec = Arc::new(spec);
        let (commands, inbox) = mpsc::unbounded_channel();
        let channels = actor::spawn(conn, spec.clone(), frames, inbox, gcs)?;
        Ok(Self {
            driver: Driver {
                spec,
                state: channels.state,
                commands,
            },
            status: channels.status,
            counters: channels.counters,
            gcs: (0, 0),
        })
    }

    /// The link as telemetry reports it.
    pub fn status(&self) -> AutopilotStatus {
        AutopilotStatus {
            refused_from_gcs: self.gcs.1,
            ..self.status.borrow().clone()
        }
    }

    /// A receiver that wakes when the status changes (link, mode, arming, failsafe).
    pub fn status_changes(&self) -> watch::Receiver<AutopilotStatus> {
        self.status.clone()
    }

    pub fn counters(&self) -> LinkCounters {
        LinkCounters {
            from_gcs: self.gcs.0,
            refused_from_gcs: self.gcs.1,
            ..*self.counters.borrow()
        }
    }

    /// The readings of the instrument that sends NAMED_VALUE_FLOAT `name` on this link (the
    /// `mavlink:NAME` source), on a bounded queue of `capacity`.
    pub fn named_values(&self, name: &str, capacity: usize) -> mpsc::Receiver<crate::sensor::Input> {
        let (tx, rx) = mpsc::channel(capacity);
        let source = named::NamedSource::new(name.to_string(), tx);
        let _ = self.driver.commands.send(Command::Listen(Box::new(source)));
        rx
    }

    /// The driving handle, for a task of its own.
    pub fn driver(&self) -> Driver {
        self.driver.clone()
    }

    /// A frame from a ground station: passed on when it is readable and addressed to this
    /// autopilot (or to every system); otherwise refused with the reason.
    pub fn from_gcs(&mut self, bytes: &[u8]) -> Result<(), String> {
        let result = parse_frame(bytes).and_then(|(h, m)| {
            let ours = self.driver.state.borrow().sysid.unwrap_or(self.spec.vehicle.sysid);
            match m.target_system_id() {
                Some(t) if t != 0 && t != ours => Err(format!("{} for system {t}, not {ours}", m.message_name())),
                _ => self
                    .driver
                    .commands
                    .send(Command::Forward(h, Box::new(m)))
                    .map_err(|_| "the bridge has stopped".to_string()),
            }
        });
        match &result {
            Ok(()) => self.gcs.0 += 1,
            Err(_) => self.gcs.1 += 1,
        }
        result
    }
}

impl Driver {
    /// The autopilot's state now.
    pub fn state(&self) -> AutopilotState {
        self.state.borrow().clone()
    }

    /// Wait for the autopilot's next change of state (`false`: the bridge has stopped).
    pub async fn changed(&mut self) -> bool {
        self.state.changed().await.is_ok()
    }

    /// The link state alone.
    pub fn link(&self) -> AutopilotLink {
        self.state.borrow().link
    }

    /// Whether the planner may send it targets now: armed, in GUIDED, not lost (and a copter
    /// in the air).
    pub fn drivable(&self) -> bool {
        let s = self.state.borrow();
        guided(&self.spec, &s) && s.link != AutopilotLink::Lost && airborne(&self.spec, &s)
    }

    /// Whether a grid point is outside the site's fence (never sent: an autopilot refuses it,
    /// ArduCopter without a word, or drives out and breaches).
    pub fn outside_fence(&self, grid_xy: (f64, f64)) -> bool {
        let n = self.target_ned(grid_xy);
        !self.spec.fence_m.is_empty() && !fleet_mission::fence::inside(&self.spec.fence_m, [n.y, n.x])
    }

    /// How far (m, horizontal) the autopilot is from what it is driving to now: the leg of a
    /// way routed round the fence, or the grid point itself; `None` before a position.
    pub fn to_go(&self, grid_xy: (f64, f64)) -> Option<f64> {
        let s = self.state.borrow();
        let aim = s.leg.unwrap_or_else(|| self.target_ned(grid_xy));
        s.ned.map(|p| (p - aim).xy().norm())
    }

    /// A target counts as reached within the mission's acceptance, or the autopilot's own
    /// `WP_RADIUS` when that is larger (it stops trying within it).
    fn acceptance(&self) -> f64 {
        let radius = self.state.borrow().limits.wp_radius.unwrap_or(0.0);
        self.spec.acceptance_m.max(radius)
    }

    /// Where the autopilot says it is, in grid metres.
    pub fn position(&self) -> Option<(f64, f64)> {
        self.state.borrow().ned.map(|n| self.spec.vehicle.site.grid_of(&n))
    }

    /// The autopilot's battery (fraction), if it reports one.
    pub fn battery(&self) -> Option<f64> {
        self.state.borrow().battery
    }

    /// The autopilot's heading as telemetry has it (radians from +x, east, counter-clockwise).
    pub fn heading(&self) -> Option<f64> {
        let deg = self.state.borrow().heading_deg?;
        Some((std::f64::consts::FRAC_PI_2 - deg.to_radians()).rem_euclid(std::f64::consts::TAU))
    }

    /// Whether the autopilot took the site's fence and enforces it.
    pub fn fence_enabled(&self) -> bool {
        self.state.borrow().fence_enabled
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
        if self.state.borrow().sysid.is_none() || !self.drivable() {
            return false;
        }
        self.commands.send(Command::Goto(self.target_ned(grid_xy))).is_ok()
    }

    /// Whether the autopilot is within the acceptance distance of a grid point.
    pub fn arrived(&self, grid_xy: (f64, f64)) -> bool {
        let goal = self.target_ned(grid_xy);
        let acceptance = self.acceptance();
        let near = |n: Vector3<f64>| (n.xy() - goal.xy()).norm() <= acceptance;
        self.state.borrow().ned.is_some_and(near)
    }

    /// Whether it has reached the corner it was routed to (time for the next leg).
    pub fn at_corner(&self) -> bool {
        let reach = self.acceptance().max(ROUTE_INSET_M / 2.0);
        let s = self.state.borrow();
        s.leg.zip(s.ned).is_some_and(|(l, n)| (n.xy() - l.xy()).norm() <= reach)
    }

    /// A failsafe of the vehicle's own (its link to the server lost): the autopilot to
    /// `role` (Return or Hold), and `why` in telemetry until it is back in GUIDED.
    pub fn failsafe(&self, role: Control, why: &str) -> bool {
        if self.state.borrow().sysid.is_none() {
            return false;
        }
        let frame = self.spec.vehicle.frame;
        let mode = if role == Control::Hold {
            frame.hold_mode()
        } else {
            frame.mode(role)
        };
        let why = why.to_string();
        self.commands.send(Command::Failsafe { mode, why }).is_ok()
    }

    /// Back from the vehicle's own failsafe: GUIDED again, so the planner drives it.
    pub fn rejoin(&self) {
        let _ = self.commands.send(Command::Rejoin);
    }
}

/// Whether a copter is at (nine tenths of) its cruise altitude; a boat always is.
fn airborne(spec: &BridgeSpec, s: &AutopilotState) -> bool {
    match spec.vehicle.frame {
        Frame::Boat => true,
        Frame::Multirotor => s.ned.is_some_and(|n| -n.z >= 0.9 * spec.vehicle.cruise_alt),
    }
}

/// Whether the autopilot is armed and in GUIDED.
fn guided(spec: &BridgeSpec, s: &AutopilotState) -> bool {
    s.mode
        .is_some_and(|m| spec.vehicle.frame.role(m) == Some(Control::Guided))
        && s.armed
        && s.breach.is_none()
}
