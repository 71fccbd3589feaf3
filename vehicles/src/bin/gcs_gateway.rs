//! `gcs-gateway`: offers every vehicle of the mission to ground stations on one MAVLink
//! endpoint (see `vehicles::gateway`). Runs beside the model server; `fleet up` starts it when
//! the mission's `[mavlink] gcs` is set.

use anyhow::Context as _;
use clap::Parser;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::keys::Keys;
use fleet_mission::signing_key::SigningKey;
use fleet_net::{Role, Traffic};
use std::sync::Arc;
use std::time::Duration;
use tracing::{debug, info, warn};
use vehicles::gateway::{HealthNotices, RefusalLog, Router};
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

/// The ground-station endpoint: its address, and the link (signed when the mission has a key:
/// the ground station must sign, as MAVProxy does with `signing key <passphrase>`).
fn open_gcs(args: &Args, mission: &MissionConfig) -> anyhow::Result<(String, Arc<MavLink>)> {
    let address = args.gcs.clone().unwrap_or_else(|| mission.mavlink.gcs.clone());
    if address.is_empty() {
        anyhow::bail!("no ground-station endpoint: set [mavlink] gcs in the mission or give --gcs");
    }
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
    let link =
        MavLink::open(&address, signing).map_err(|e| anyhow::anyhow!("ground-station endpoint {address}: {e}"))?;
    Ok((address, Arc::new(link)))
}

/// Every vehicle's system id, pinned from the mission (never learned from the streams).
fn router_of(mission: &MissionConfig) -> anyhow::Result<Router> {
    let systems: Vec<(String, u8)> = mission
        .vehicles()
        .iter()
        .map(|v| Ok((v.id.to_string(), mission.sysid(&v.id)?)))
        .collect::<anyhow::Result<_>>()?;
    Ok(Router::new(systems))
}

/// The gateway's state: the routes, the refusals said, and the frames carried each way.
struct Gateway {
    keys: Keys,
    gcs: Arc<MavLink>,
    session: fleet_net::zenoh::Session,
    router: Router,
    refusals: RefusalLog,
    /// The sensors' verdicts told to the ground station, from the server's status.
    health: HealthNotices,
    up: u64,
    down: u64,
}

async fn run(args: Args) -> anyhow::Result<()> {
    let mission = MissionConfig::load(args.node.mission.as_deref())?;
    let keys = Keys::new(&mission.mission)?;
    let (address, gcs) = open_gcs(&args, &mission)?;
    let network = mission.network.for_node(fleet_mission::security::GATEWAY);
    let zenoh_config = args.node.zenoh_config(Role::Vehicle, &network, &mission.link)?;
    let file = args.node.zenoh_file(Role::Vehicle, &network);
    fleet_net::exit_when_refused("gcs-gateway", &zenoh_config, file);
    let session = fleet_net::open(zenoh_config).await?;
    let e = fleet_net::NetError::zenoh;
    let from_vehicles = session
        .declare_subscriber(keys.all_mavlink())
        .await
        .map_err(e("the vehicles' frames"))?;
    let status = session
        .declare_subscriber(keys.server_status())
        .await
        .map_err(e("the server's status"))?;
    let token = session.liveliness().declare_token(keys.alive("gcs-gateway")).await;
    let _token = token.map_err(e("the liveliness token"))?;
    let router = router_of(&mission)?;
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
    let mut g = Gateway {
        keys,
        gcs,
        session,
        router,
        refusals: RefusalLog::new(Duration::from_secs(10)),
        health: HealthNotices::default(),
        up: 0,
        down: 0,
    };
    let mut stop = fleet_net::StopSignals::new()?;
    let mut stats = tokio::time::interval(Duration::from_secs(10));
    loop {
        tokio::select! {
            s = from_vehicles.recv_async() => match s {
                Ok(s) => g.on_vehicle_frames(&s),
                Err(_) => break,
            },
            Some(got) = from_gcs.recv() => g.on_gcs_read(got).await,
            Ok(s) = status.recv_async() => g.on_status(&s),
            _ = stats.tick() => info!(to_gcs = g.down, from_gcs = g.up, refused = ?g.router.refused, "gateway"),
            sig = stop.recv() => { info!(signal = sig, "stopping"); break }
        }
    }
    info!(to_gcs = g.down, from_gcs = g.up, refused = ?g.router.refused, "gateway stopped");
    fleet_net::close(&g.session).await;
    Ok(())
}

impl Gateway {
    /// A vehicle's autopilot frames (one put carries several: see the vehicle's pipe), each to
    /// the ground station: signed here with the ground-station key (the vehicle's own link key
    /// never leaves the vehicle).
    fn on_vehicle_frames(&mut self, s: &fleet_net::zenoh::sample::Sample) {
        fleet_net::mark_connected();
        let Some(vehicle) = self.keys.vehicle_of(s.key_expr().as_str()) else {
            return;
        };
        let bytes = s.payload().to_bytes();
        let (frames, bad_tail) = vehicles::link::split_frames(&bytes);
        let results: Vec<_> = frames.iter().map(|f| self.router.from_vehicle(&vehicle, f)).collect();
        let tail = bad_tail.map(|e| self.router.unreadable(format!("{vehicle}: {e}")));
        for r in results.into_iter().chain(tail.map(Err)) {
            match r {
                Ok((h, m)) => {
                    let _ = self.gcs.send(&h, &m);
                    self.down += 1;
                }
                Err(r) => {
                    if let Some(line) = self.refusals.note(&r) {
                        warn!(%vehicle, "{line}")
                    }
                }
            }
        }
    }

    /// The server's status: a STATUSTEXT for each vehicle whose sensor's verdict changed.
    fn on_status(&mut self, s: &fleet_net::zenoh::sample::Sample) {
        let ctx = fleet_mission::protocol::Context::cell_free();
        let bytes = s.payload().to_bytes();
        let Ok(fleet_mission::protocol::Body::Status(status)) = fleet_mission::protocol::decode(&bytes, &ctx) else {
            return debug!("a server status the gateway could not read");
        };
        for (h, m) in self.health.of(&status, &self.router) {
            if let mavlink::dialects::ardupilotmega::MavMessage::STATUSTEXT(t) = &m {
                info!(
                    system = h.system_id,
                    text = t.text.to_str().unwrap_or_default(),
                    "sensor health to the ground station"
                );
            }
            let _ = self.gcs.send(&h, &m);
            self.down += 1;
        }
    }

    /// A read from the ground station: passed to the vehicle(s) it addresses, or refused.
    async fn on_gcs_read(&mut self, got: Received) {
        let got = match got {
            Received::Frame(_, _, bytes) => Ok(bytes),
            Received::Refused(r) => Err(self.router.refused_by_signing(r)),
            Received::Unreadable(e) => return debug!("unreadable frame from the ground station: {e}"),
            Received::Idle | Received::Closed => return,
        };
        match got.and_then(|bytes| self.router.from_gcs(&bytes).map(|to| (bytes, to))) {
            Ok((bytes, vehicles)) => {
                for v in vehicles {
                    let key = self.keys.gcs(&v);
                    if let Err(e) = fleet_net::put_bytes(&self.session, &key, bytes.clone(), Traffic::Mavlink).await {
                        warn!(vehicle = v, "forwarding a ground-station frame: {e}");
                    }
                }
                self.up += 1;
            }
            Err(r) => {
                if let Some(line) = self.refusals.note(&r) {
                    warn!("{line}")
                }
            }
        }
    }
}
