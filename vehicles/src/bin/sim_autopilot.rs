//! `sim-autopilot`: a simulated boat or multirotor autopilot on its own MAVLink endpoint, as
//! ArduPilot's SITL is. Point a vehicle node at it (`vehicle --autopilot udpout:HOST:PORT`) or
//! a ground station straight at it (`mavproxy.py --master=udpout:HOST:PORT`).

use anyhow::Context as _;
use clap::{Parser, ValueEnum};
use fleet_math::grid::Grid;
use fleet_mission::config::MissionConfig;
use fleet_mission::signing_key::SigningKey;

use nalgebra::Vector3;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use vehicles::autopilot::modes::Frame;
use vehicles::autopilot::serve;
use vehicles::autopilot::sim::{SimAutopilot, SimSpec};
use vehicles::signing::{LinkSigning, LINK_AUTOPILOT};

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Airframe {
    Boat,
    Multirotor,
}

#[derive(Parser, Debug)]
#[command(
    name = "sim-autopilot",
    version,
    about = "A simulated MAVLink autopilot (boat or multirotor)"
)]
struct Args {
    #[arg(long, value_enum, default_value = "boat")]
    frame: Airframe,
    /// MAVLink system id.
    #[arg(long, default_value_t = 1)]
    sysid: u8,
    /// Where it serves (any `mavlink` connection string; SITL's habit is `udpin:`).
    #[arg(long, default_value = "udpin:127.0.0.1:14600")]
    listen: String,
    /// A companion computer's link (an instrument's driver sending NAMED_VALUE_FLOAT; unsigned),
    /// routed onto the main one as ArduPilot routes between its serial ports.
    #[arg(long)]
    companion: Option<String>,
    /// The mission whose `[mavlink]` section gives the site, speeds and speed-up (default: the
    /// bundled one); the grid is taken as the mission's model grid of 1 m cells.
    #[arg(long)]
    mission: Option<std::path::PathBuf>,
    /// Model-grid rows and columns the site spans.
    #[arg(long, num_args = 2, default_values_t = [48, 96])]
    grid: Vec<usize>,
    /// Start here (grid metres, x east and y north).
    #[arg(long, num_args = 2, default_values_t = [0.0, 0.0])]
    home: Vec<f64>,
    /// Sign everything sent and obey only frames signed with this key (a `fleet secure` key
    /// file: 64 hex characters, mode 0600), as ArduPilot does once signing is set up.
    #[arg(long)]
    signing_key: Option<std::path::PathBuf>,
}

fn main() {
    fleet_net::init_node();
    let args = Args::parse();
    fleet_net::run_node("sim-autopilot", 1, run(args));
}

async fn run(args: Args) -> anyhow::Result<()> {
    let mission = MissionConfig::load(args.mission.as_deref())?;
    let m = &mission.mavlink;
    let grid = Grid::new(args.grid[0], args.grid[1], 1.0)
        .map_err(fleet_exit::bad_input)
        .context("--grid")?;
    let site = m.site(&grid);
    let frame = match args.frame {
        Airframe::Boat => Frame::Boat,
        Airframe::Multirotor => Frame::Multirotor,
    };
    let spec = SimSpec::from_config(frame, args.sysid, site, m);
    let home: Vector3<f64> = site.ned_of((args.home[0], args.home[1]), 0.0);
    let signing = match &args.signing_key {
        Some(p) => Some(LinkSigning::new(
            SigningKey::read(p)
                .map_err(fleet_exit::bad_input)
                .context("--signing-key")?,
            LINK_AUTOPILOT,
            false,
        )),
        None => None,
    };
    let signed = signing.is_some();
    let stop = Arc::new(AtomicBool::new(false));
    let sim = SimAutopilot::new(spec, home);
    let stats = serve::spawn_routed(&args.listen, args.companion.as_deref(), sim, signing, stop.clone())
        .with_context(|| format!("--listen {} / --companion", args.listen))?;
    tracing::info!(
        listen = args.listen,
        sysid = args.sysid,
        ?frame,
        signed,
        "simulated autopilot up"
    );
    let mut signals = fleet_net::StopSignals::new()?;
    let mut tick = tokio::time::interval(Duration::from_secs(10));
    let report = || {
        let n = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        tracing::info!(
            received = n(&stats.received),
            sent = n(&stats.sent),
            unreadable = n(&stats.unreadable),
            unsigned = n(&stats.unsigned),
            bad_signature = n(&stats.bad_signature),
            replay = n(&stats.replay),
            "autopilot"
        );
    };
    loop {
        tokio::select! {
            _ = signals.recv() => break,
            _ = tick.tick() => report(),
        }
    }
    stop.store(true, Ordering::Relaxed);
    report();
    Ok(())
}
