//! `gcs-gateway`: offers every vehicle of the mission to ground stations on one MAVLink
//! endpoint (see `vehicles::gateway`). Runs beside the model server; `fleet up` starts it when
//! the mission's `[mavlink] gcs` is set.

use anyhow::Context as _;
use clap::Parser;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::keys::Keys;
use fleet_mission::signing_key::SigningKey;
use fleet_net::Role;
use std::sync::Arc;
use std::time::Duration;
use tracing::{debug, info, warn};
use vehicles::gateway::{RefusalLog, Router};
use vehicles::link::{MavLink, Received};
use vehicles::signing::{LinkSigning, LINK_GATEWAY};

#[derive(Parser, Debug)]
#[command(
    name = "gcs-gateway",
    version,
    about = "hetfleet's ground-station gateway: the whole fleet on one MAVLink endpoint"
)]
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
    // With a key, the ground station must sign (MAVProxy: `signing key <passphrase>`).
    let signing = match &mission.mavlink.signing_key {
        Some(p) => Some(LinkSigning::new(
            SigningKey::read(p)
                .map_err(fleet_exit::bad_input)
                .context("[mavlink] signing_key")?,
            LINK_GATEWAY,
            false,
        )),
        None => None,
    };
    let gcs = Arc::new(
        MavLink::open(&address, signing).map_err(|e| anyhow::anyhow!("ground-station endpoint {address}: {e}"))?,
    );
    let network = mission.network.for_node(fleet_mission::security::GATEWAY);
    let zenoh_config = args.node.zenoh_config(Role::Vehicle, &network)?;
    fleet_net::exit_when_refused(
        "gcs-gateway",
        &zenoh_config,
        args.node.zenoh_file(Role::Vehicle, &network),
    );
    let session = fleet_net::open(zenoh_config).await?;
    let from_vehicles = session
        .declare_subscriber(keys.all_mavlink())
        .await
        .map_err(fleet_net::NetError::zenoh("declaring a subscriber"))?;
    let _token = session
        .liveliness()
        .declare_token(keys.alive("gcs-gateway"))
        .await
        .map_err(fleet_net::NetError::zenoh("declaring the liveliness token"))?;
    // Every vehicle's system id, pinned from the mission (never learned from the streams).
    let systems: Vec<(String, u8)> = mission
        .vehicles()
        .iter()
        .map(|v| Ok((v.id.to_string(), mission.sysid(&v.id)?)))
        .collect::<anyhow::Result<_>>()?;
    let mut router = Router::new(systems);
    let (systems, signed) = (router.systems(), gcs.signed());
    info!(
        gcs = address,
        mission = mission.mission,
        ?systems,
        signed,
        "ground-station gateway up"
    );

    // The ground station's frames (as they came, signature and all), or why the signing check
    // refused one, from the link's reader.
    let mut from_gcs = gcs.reader("gcs-rx")?;
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
                        // Signed here with the ground-station key (the vehicle's own link key
                        // never leaves the vehicle).
                        let _ = gcs.send(&h, &m);
                        down += 1;
                    }
                    Err(r) => if let Some(line) = refusals.note(&r) { warn!(%vehicle, "{line}") },
                }
            }
            Some(got) = from_gcs.recv() => {
                let got = match got {
                    Received::Frame(_, _, bytes) => Ok(bytes),
                    Received::Refused(r) => Err(router.refused_by_signing(r)),
                    Received::Unreadable(e) => {
                        debug!("unreadable frame from the ground station: {e}");
                        continue;
                    }
                    Received::Idle | Received::Closed => continue,
                };
                match got.and_then(|bytes| router.from_gcs(&bytes).map(|to| (bytes, to))) {
                    Ok((bytes, vehicles)) => {
                        for v in vehicles {
                            if let Err(e) = session.put(keys.gcs(&v), bytes.clone()).await {
                                warn!(vehicle = v, "forwarding a ground-station frame: {e}");
                            }
                        }
                        up += 1;
                    }
                    Err(r) => if let Some(line) = refusals.note(&r) { warn!("{line}") },
                }
            }
            _ = stats.tick() => info!(to_gcs = down, from_gcs = up, refused = ?router.refused, "gateway"),
            sig = stop.recv() => { info!(signal = sig, "stopping"); break }
        }
    }
    info!(to_gcs = down, from_gcs = up, refused = ?router.refused, "gateway stopped");
    session
        .close()
        .await
        .map_err(fleet_net::NetError::zenoh("closing the Zenoh session"))?;
    Ok(())
}
