//! `gcs-gateway`: offers every vehicle of the mission to ground stations on one MAVLink
//! endpoint (see `vehicles::gateway`). Runs beside the model server; `fleet up` starts it when
//! the mission's `[mavlink] gcs` is set.

use clap::Parser;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::keys::Keys;
use fleet_net::Role;
use mavlink::dialects::common::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::MavConnection;
use std::sync::Arc;
use std::time::Duration;
use tracing::{debug, info, warn};
use vehicles::bridge::frame_bytes;
use vehicles::gateway::{RefusalLog, Router};

#[derive(Parser, Debug)]
#[command(name = "gcs-gateway", version, about = "hetfleet's ground-station gateway: the whole fleet on one MAVLink endpoint")]
struct Args {
    #[command(flatten)]
    node: fleet_net::NodeArgs,
    /// The ground-station endpoint (default: the mission's `[mavlink] gcs`).
    #[arg(long)]
    gcs: Option<String>,
}

fn main() {
    fleet_net::init_node();
    let args = Args::parse();
    fleet_net::run_node("gcs-gateway", 1, run(args));
}

async fn run(args: Args) -> anyhow::Result<()> {
    let mission = MissionConfig::load(args.node.mission.as_deref())?;
    let keys = Keys::new(&mission.mission)?;
    let address = args.gcs.clone().unwrap_or_else(|| mission.mavlink.gcs.clone());
    if address.is_empty() {
        anyhow::bail!("no ground-station endpoint: set [mavlink] gcs in the mission or give --gcs");
    }
    let gcs = Arc::new(mavlink::connect::<MavMessage>(&address).map_err(|e| anyhow::anyhow!("ground-station endpoint {address}: {e}"))?);
    let network = mission.network.for_node(fleet_mission::security::GATEWAY);
    let zenoh_config = args.node.zenoh_config(Role::Vehicle, &network)?;
    fleet_net::exit_when_refused("gcs-gateway", &zenoh_config, args.node.zenoh_file(Role::Vehicle, &network));
    let session = fleet_net::open(zenoh_config).await?;
    let from_vehicles = session.declare_subscriber(keys.all_mavlink()).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let _token = session.liveliness().declare_token(keys.alive("gcs-gateway")).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    // Every vehicle's system id, pinned from the mission (never learned from the streams).
    let systems: Vec<(String, u8)> = mission.vehicles().iter().map(|v| Ok((v.id.clone(), mission.sysid(&v.id)?))).collect::<anyhow::Result<_>>()?;
    let mut router = Router::new(systems);
    info!(gcs = address, mission = mission.mission, systems = ?router.systems(), "ground-station gateway up");

    // The ground station's frames, read on a thread (the connection blocks).
    let (tx, mut from_gcs) = tokio::sync::mpsc::unbounded_channel::<Vec<u8>>();
    let reader = gcs.clone();
    std::thread::Builder::new().name("gcs-rx".into()).spawn(move || loop {
        match reader.recv() {
            Ok((h, m)) => {
                if tx.send(frame_bytes(h, &m)).is_err() {
                    return;
                }
            }
            // Nobody listening yet on a udpout endpoint: ICMP refusals come back as errors.
            Err(MessageReadError::Io(_)) => std::thread::sleep(Duration::from_millis(50)),
            Err(e) => debug!("unreadable frame from the ground station: {e}"),
        }
    })?;

    let mut refusals = RefusalLog::new(Duration::from_secs(10));
    let mut stop = fleet_net::StopSignals::new()?;
    let mut stats = tokio::time::interval(Duration::from_secs(10));
    let (mut up, mut down) = (0u64, 0u64);
    loop {
        tokio::select! {
            s = from_vehicles.recv_async() => {
                let Ok(s) = s else { break };
                fleet_net::mark_connected();
                let Some(vehicle) = keys.vehicle_of(s.key_expr().as_str()) else { continue };
                let bytes = s.payload().to_bytes();
                match router.from_vehicle(&vehicle, &bytes) {
                    Ok((h, m)) => {
                        let _ = gcs.send(&h, &m);
                        down += 1;
                    }
                    Err(r) => if let Some(line) = refusals.note(&r) { warn!(vehicle, "{line}") },
                }
            }
            Some(bytes) = from_gcs.recv() => match router.from_gcs(&bytes) {
                Ok(vehicles) => {
                    for v in vehicles {
                        if let Err(e) = session.put(keys.gcs(&v), bytes.clone()).await {
                            warn!(vehicle = v, "forwarding a ground-station frame: {e}");
                        }
                    }
                    up += 1;
                }
                Err(r) => if let Some(line) = refusals.note(&r) { warn!("{line}") },
            },
            _ = stats.tick() => info!(to_gcs = down, from_gcs = up, refused = ?router.refused, "gateway"),
            sig = stop.recv() => { info!(signal = sig, "stopping"); break }
        }
    }
    session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}
