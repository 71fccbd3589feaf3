//! The operator's commands to a running mission, from the ground station's seat (under
//! `fleet secure` it connects as the gateway's user, the only one the access control lets put
//! them):
//!
//! `fleet-operator --mission m.toml sensor boat-1 ok [--from-step 40]` trusts boat-1's sensor
//! (every value as it came), `excluded` withholds its values, `auto` hands it back to the
//! tests. The server journals the command and re-fits the model from that step; this waits
//! until the server's status says it took it (exit 0), refused it (exit 2), or the wait is
//! over (exit 1).

use clap::{Parser, Subcommand, ValueEnum};
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::{self, keys::Keys, Body, Context, Health, SensorOverride, ServerStatus};
use fleet_net::Role;
use std::time::Duration;

#[derive(Parser, Debug)]
#[command(name = "fleet-operator", about = "The operator's commands to a running mission")]
struct Args {
    #[command(flatten)]
    node: fleet_net::NodeArgs,
    /// How long to wait for the server to take the command, in seconds.
    #[arg(long, default_value_t = 20.0)]
    timeout: f64,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Set a vehicle's sensor verdict from a step on.
    Sensor {
        /// The vehicle's id.
        vehicle: String,
        verdict: OperatorVerdict,
        /// The mission step it takes effect from (0: the whole mission).
        #[arg(long, default_value_t = 0)]
        from_step: u64,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum OperatorVerdict {
    /// Trust every value as it came.
    Ok,
    /// Withhold its values from the model.
    Excluded,
    /// Back to the tests.
    Auto,
}

fn main() {
    fleet_net::init_node();
    let args = Args::parse();
    fleet_net::run_node("fleet-operator", 1, run(args));
}

async fn run(args: Args) -> anyhow::Result<()> {
    let mission = MissionConfig::load(args.node.mission.as_deref())?;
    let keys = Keys::new(&mission.mission)?;
    let Command::Sensor {
        vehicle,
        verdict,
        from_step,
    } = args.command;
    let o = SensorOverride {
        vehicle: vehicle.parse().map_err(fleet_exit::bad_input)?,
        from_step,
        set: match verdict {
            OperatorVerdict::Ok => Some(Health::Ok),
            OperatorVerdict::Excluded => Some(Health::Excluded),
            OperatorVerdict::Auto => None,
        },
    };
    if !mission.vehicles().iter().any(|v| v.id == o.vehicle) {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "{vehicle} is not a vehicle of mission {:?}",
            mission.mission
        )));
    }
    let network = mission.network.for_node(fleet_mission::security::GATEWAY);
    let zenoh_config = args.node.zenoh_config(Role::Vehicle, &network, &mission.link)?;
    fleet_net::exit_when_refused(
        "fleet-operator",
        &zenoh_config,
        args.node.zenoh_file(Role::Vehicle, &network),
    );
    let session = fleet_net::open(zenoh_config).await?;
    let status = session
        .declare_subscriber(keys.server_status())
        .await
        .map_err(fleet_net::NetError::zenoh("the server's status"))?;
    let wait = Duration::from_secs_f64(args.timeout.max(0.0));
    let deadline = tokio::time::Instant::now() + wait;
    let ctx = Context::cell_free();
    let next = || async {
        loop {
            let sample = tokio::time::timeout_at(deadline, status.recv_async())
                .await
                .ok()?
                .ok()?;
            if let Ok(Body::Status(s)) = fleet_net::decode(&sample, &ctx) {
                return Some(s);
            }
        }
    };
    let refused = |s: &ServerStatus| s.rejected.get("invalid_override").copied().unwrap_or(0);
    let Some(before) = next().await else {
        anyhow::bail!("no status from the server of mission {:?} in {wait:?}", mission.mission);
    };
    let body = protocol::encode(&Body::Override(o.clone()));
    session
        .put(keys.sensor_override(o.vehicle.as_str()), body)
        .await
        .map_err(fleet_net::NetError::zenoh("the override"))?;
    while let Some(s) = next().await {
        if s.overrides > before.overrides {
            let now = s
                .health
                .get(&o.vehicle)
                .map_or("ok".to_string(), |h| h.state.to_string());
            println!(
                "{vehicle}: taken from step {from_step}; its sensor is {now} (model version {})",
                s.version
            );
            return Ok(());
        }
        if refused(&s) > refused(&before) {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "the server refused the override (its log says why)"
            )));
        }
    }
    anyhow::bail!("the server did not take the override in {wait:?} (is this gateway's user allowed to put it?)")
}
