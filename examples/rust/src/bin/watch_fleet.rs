//! A client of a live mission: it joins the mission's Zenoh network as any program may, and
//! prints each model the server publishes and each vehicle's telemetry as it comes, decoded
//! with the fleet's own protocol (`fleet_mission::protocol`). It changes nothing.
//!
//! `watch_fleet <mission.toml> <endpoint> [models]`: the mission file (for its id and grid),
//! the server's Zenoh endpoint (`tcp/127.0.0.1:7447`), and how many models to print before it
//! exits (default 3). Exit 0 when it has seen them, 1 if none came within a minute.

use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::{keys::Keys, Body, Context};
use fleet_net::zenoh;
use std::time::Duration;

#[tokio::main]
async fn main() {
    if let Err(e) = run().await {
        fleet_exit::fail("watch_fleet", &e);
    }
}

async fn run() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [mission, endpoint, rest @ ..] = args.as_slice() else {
        anyhow::bail!("usage: watch_fleet <mission.toml> <endpoint> [models]");
    };
    let wanted: usize = rest.first().map_or(Ok(3), |n| n.parse())?;
    let mission = MissionConfig::load(Some(std::path::Path::new(mission)))?;
    let keys = Keys::new(&mission.mission)?;
    let (rows, cols, _) = mission
        .model_shape()
        .ok_or_else(|| anyhow::anyhow!("the mission's grid is its truth file's: give the truth's mission"))?;
    let ctx = Context::new(fleet_math::grid::Grid::new(rows, cols, 1.0)?);

    // A client of the server's router: no scouting, the one endpoint, waiting for it to come up
    // (a client exits when it cannot connect unless told to keep trying).
    let mut cfg = zenoh::Config::default();
    let set =
        |cfg: &mut zenoh::Config, k: &str, v: &str| cfg.insert_json5(k, v).map_err(|e| anyhow::anyhow!("{k}: {e}"));
    set(&mut cfg, "mode", "\"client\"")?;
    set(&mut cfg, "connect/endpoints", &format!("[\"{endpoint}\"]"))?;
    set(&mut cfg, "scouting/multicast/enabled", "false")?;
    set(&mut cfg, "connect/timeout_ms", "-1")?;
    set(&mut cfg, "connect/exit_on_failure", "false")?;
    let session = fleet_net::open(cfg).await?;
    let models = session
        .declare_subscriber(keys.model_latest())
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let telemetry = session
        .declare_subscriber(keys.telemetry("*"))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;

    let mut seen = 0;
    while seen < wanted {
        tokio::select! {
            sample = models.recv_async() => {
                let sample = sample.map_err(|e| anyhow::anyhow!("{e}"))?;
                if let Body::Model(m) = fleet_net::decode(&sample, &ctx)? {
                    let mean = m.variance.iter().map(|&v| f64::from(v)).sum::<f64>() / m.variance.len().max(1) as f64;
                    println!("model v{} epoch {} step {}: rank {}, mean reported variance {mean:.3e}",
                        m.version, m.epoch, m.step, m.eigenvalues.len());
                    seen += 1;
                }
            }
            sample = telemetry.recv_async() => {
                let sample = sample.map_err(|e| anyhow::anyhow!("{e}"))?;
                if let Body::Telemetry(t) = fleet_net::decode(&sample, &ctx)? {
                    println!("telemetry {} step {}: at ({:.1}, {:.1}) m, outbox {}",
                        t.vehicle, t.step, t.position[0], t.position[1], t.outbox_depth);
                }
            }
            _ = tokio::time::sleep(Duration::from_secs(60)) => anyhow::bail!("no model within a minute"),
        }
    }
    fleet_net::close(&session).await;
    Ok(())
}
