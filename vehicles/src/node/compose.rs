//! Where the vehicle node is put together from its parts: the autopilot (a simulated one
//! started here, in this process, when the mission says `sim`; a real one reached by its
//! connection string), the MAVLink bridge to it, and the pipe that carries the autopilot's
//! frames to the ground-station gateway over Zenoh. The bridge never knows whether its
//! autopilot is simulated.

use super::setup::Setup;
use crate::Args;
use anyhow::Context as _;
use fleet_mission::config::{MavlinkConfig, MissionConfig};
use fleet_mission::protocol::keys::Keys;
use fleet_mission::signing_key::SigningKey;
use fleet_net::zenoh;
use nalgebra::Vector3;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use vehicles::autopilot::modes::Frame;
use vehicles::autopilot::safety::Action;
use vehicles::autopilot::serve;
use vehicles::autopilot::sim::{SimAutopilot, SimSpec};
use vehicles::bridge::{Bridge, BridgeSpec, ToGcs};
use vehicles::signing::{LinkSigning, LINK_AUTOPILOT};

/// The MAVLink bridge, unless the autopilot is `none`, and the autopilot's frames for the
/// ground-station side.
pub fn open_bridge(
    setup: &Setup,
    args: &Args,
    mission: &MissionConfig,
) -> anyhow::Result<Option<(Bridge, mpsc::UnboundedReceiver<ToGcs>)>> {
    if !setup.has_autopilot() {
        return Ok(None);
    }
    let spec = bridge_spec(setup, args, mission)?;
    let address = if setup.autopilot == "sim" {
        start_sim(&spec, mission.mavlink.sim_companion_port)?
    } else {
        setup.autopilot.clone()
    };
    let (gcs_tx, gcs_rx) = mpsc::unbounded_channel();
    Ok(Some((Bridge::connect(&address, spec, Some(gcs_tx))?, gcs_rx)))
}

/// What the bridge needs to know of its vehicle and the site.
fn bridge_spec(setup: &Setup, args: &Args, mission: &MissionConfig) -> anyhow::Result<BridgeSpec> {
    let (m, grid, index) = (&mission.mavlink, &setup.grid, setup.index);
    let site = m.site(grid);
    // Launched from points along the south shore, inside the fence by the margin and the turn.
    let launch: Vec<Vector3<f64>> = fleet_mission::launch::launch_points(mission, grid)
        .map_err(fleet_exit::bad_input)?
        .iter()
        .map(|&[e, n]| Vector3::new(n, e, 0.0))
        .collect();
    let mut vehicle = SimSpec::from_config(Frame::of(setup.kind), mission.sysid(&setup.id)?, site, m);
    if let Some(mah) = args.sim_battery_start_mah {
        if !(mah.is_finite() && (0.0..=m.battery_mah).contains(&mah)) {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "--sim-battery-start-mah {mah}: must be within 0..{} (the mission's battery_mah)",
                m.battery_mah
            )));
        }
        vehicle.safety.battery_start_mah = Some(mah);
    }
    Ok(BridgeSpec {
        vehicle,
        acceptance_m: m.acceptance_m,
        heartbeat_timeout: Duration::from_millis(m.heartbeat_timeout_ms),
        home: launch[index],
        fence_m: fleet_mission::launch::fence_polygon_m(mission, grid),
        // (The mission file's name was checked when it was read.)
        fence_action: Action::from_name(&m.fence_action).unwrap_or(Action::Continue) as u8 as f32,
        drive_without_fence: m.drive_without_fence,
        rally: launch,
        signing: autopilot_key(m, &setup.id)?,
        mavlink_hz: mission.link.mavlink_hz,
        ready_timeout: Duration::from_secs_f64(m.ready_timeout_s),
        clearance_m: fleet_mission::launch::required_clearance(mission),
    })
}

/// The autopilot link's key, and whether its unsigned frames are taken.
fn autopilot_key(m: &MavlinkConfig, id: &str) -> anyhow::Result<Option<(SigningKey, bool)>> {
    let Some(p) = m.autopilot_key_of(id) else {
        return Ok(None);
    };
    let key = SigningKey::read(&p)
        .map_err(fleet_exit::bad_input)
        .context("[mavlink] autopilot_signing_key")?;
    Ok(Some((key, m.accept_unsigned_telemetry)))
}

/// A simulated autopilot in this process, served as SITL serves one (`udpin:` on a free
/// loopback port, signed with the link's key when there is one; a companion link on
/// `companion_port` + its system id when the mission asks); the address to reach it.
/// It runs until the process ends.
fn start_sim(spec: &BridgeSpec, companion_port: Option<u16>) -> anyhow::Result<String> {
    let companion = companion_port
        .map(|p| p.checked_add(spec.vehicle.sysid as u16))
        .map(|p| p.ok_or_else(|| fleet_exit::bad_input(anyhow::anyhow!("[mavlink] sim_companion_port: too high"))))
        .transpose()?
        .map(|p| format!("udpin:127.0.0.1:{p}"));
    // The kernel numbers the port, and the link binds it a moment after it is let go: another
    // socket the kernel numbers can land on it in between, so a taken port is drawn again.
    let mut tries = 0;
    loop {
        let port = std::net::UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port();
        let signing = spec
            .signing
            .as_ref()
            .map(|(k, _)| LinkSigning::new(k.clone(), LINK_AUTOPILOT, false));
        let sim = SimAutopilot::new(spec.vehicle.clone(), spec.home);
        let stop = Arc::new(AtomicBool::new(false));
        match serve::spawn_routed(
            &format!("udpin:127.0.0.1:{port}"),
            companion.as_deref(),
            sim,
            signing,
            stop,
        ) {
            Ok(_) => return Ok(format!("udpout:127.0.0.1:{port}")),
            Err(e) if e.kind() == std::io::ErrorKind::AddrInUse && tries < 8 => tries += 1,
            Err(e) => {
                return Err(e).with_context(|| {
                    format!(
                        "the simulated autopilot on 127.0.0.1:{port}, its companion link {}",
                        companion.unwrap_or_default()
                    )
                })
            }
        }
    }
}

/// Messages and bytes a task sent, counted where the node can read them.
#[derive(Debug, Clone, Default)]
pub struct Counted(Arc<(std::sync::atomic::AtomicU64, std::sync::atomic::AtomicU64)>);

impl Counted {
    fn add(&self, bytes: usize) {
        use std::sync::atomic::Ordering::Relaxed;
        self.0 .0.fetch_add(1, Relaxed);
        self.0 .1.fetch_add(bytes as u64, Relaxed);
    }

    /// Messages and bytes so far.
    pub fn get(&self) -> (u64, u64) {
        use std::sync::atomic::Ordering::Relaxed;
        (self.0 .0.load(Relaxed), self.0 .1.load(Relaxed))
    }
}

/// The most bytes of frames one put to the gateway carries (a few of a radio's packets).
const BUNDLE_BYTES: usize = 1024;

/// The autopilot's frames out to the ground-station gateway: a pipe of its own, so a slow
/// link to the gateway never holds the node's loop; what it sends is counted in `sent`.
/// Periodic frames wait up to `linger` (one period of the forwarded stream) to share a put:
/// over a radio each put costs its own TCP/IP and Zenoh headers and an acknowledgement, more
/// than a position report itself. An event goes at once, with what waited before it.
pub fn pipe_to_gateway(
    session: &zenoh::Session,
    keys: &Keys,
    id: &str,
    mut frames: mpsc::UnboundedReceiver<ToGcs>,
    linger: Duration,
    sent: Counted,
) {
    let (s, key) = (session.clone(), keys.mavlink(id));
    tokio::spawn(async move {
        while let Some(first) = frames.recv().await {
            let deadline = tokio::time::Instant::now() + linger;
            let mut bundle = first.frame;
            let mut event = first.event;
            while !event && bundle.len() < BUNDLE_BYTES {
                match tokio::time::timeout_at(deadline, frames.recv()).await {
                    Ok(Some(f)) => {
                        bundle.extend_from_slice(&f.frame);
                        event = f.event;
                    }
                    Ok(None) | Err(_) => break,
                }
            }
            sent.add(bundle.len());
            let _ = fleet_net::put_bytes(&s, &key, bundle, fleet_net::Traffic::Mavlink).await;
        }
    });
}
