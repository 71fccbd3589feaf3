//! `fleet replay <recording.mcap> --out DIR`: the model server's core run again on a mission's
//! recorded operations, offline; the final model must equal the recorded one bit for bit.

use anyhow::{bail, Result};
use fleet_mission::protocol::{self, Body};
use fleet_records::recording::{CoreOp, Recording, RecordingError};
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// A recording `fleet up` (or `model-server --record`) wrote.
    pub recording: PathBuf,
    /// Write the replayed model, estimate, variance and plans here (as a run directory has them).
    #[arg(long, default_value = "fleet-replay")]
    pub out: PathBuf,
    /// Replay in time: the recorded pace times this factor (2: twice as fast); default: at once
    /// (with --web: the recorded pace).
    #[arg(long)]
    pub speed: Option<f64>,
    /// Follow the replay in the live view here (e.g. 127.0.0.1:8080): the recording is played
    /// onto Zenoh at the mission's endpoints (`model-server --replay`) and `fleet-watch` serves it.
    #[arg(long)]
    pub web: Option<std::net::SocketAddr>,
    /// With --web: keep the view up this many seconds after the replay (Ctrl-C ends it sooner).
    #[arg(long, default_value_t = 600)]
    pub web_linger_s: u64,
}

/// The live half of `--web`: the recording played onto Zenoh and the view on it, supervised
/// like `fleet up`'s nodes.
fn start_live(args: &Args, rec: &Recording, speed: f64) -> Result<super::supervise::Supervisor> {
    use std::process::{Command, Stdio};
    let addr = args.web.expect("called with --web");
    std::fs::create_dir_all(&args.out)?;
    // The view reads the mission from a file; the boundary file need not travel with the
    // recording, and the view does not plan, so it is left out.
    let mut doc: toml::Table = rec
        .mission_toml
        .parse()
        .map_err(|e| anyhow::anyhow!("the recording's mission: {e}"))?;
    if let Some(m) = doc.get_mut("mavlink").and_then(|m| m.as_table_mut()) {
        m.remove("boundary");
    }
    let mission = args.out.join("mission.toml");
    std::fs::write(&mission, toml::to_string(&doc)?)?;
    let mut fleet = super::supervise::Supervisor::default();
    let log = |name: &str| -> Result<(std::fs::File, PathBuf)> {
        let p = args.out.join(format!("{name}.log"));
        Ok((std::fs::File::create(&p)?, p))
    };
    let (l, p) = log("replay-server")?;
    let mut c = Command::new(super::up::sibling("model-server")?);
    c.arg("--replay")
        .arg(&args.recording)
        .arg("--speed")
        .arg(speed.to_string())
        .stdout(Stdio::null())
        .stderr(l);
    fleet.spawn("model-server", c, p)?;
    let (l, p) = log("fleet-watch")?;
    let mut c = Command::new(super::up::sibling("fleet-watch")?);
    c.arg("--mission")
        .arg(&mission)
        .arg("--http")
        .arg(addr.to_string())
        .stdout(Stdio::null())
        .stderr(l);
    // The run's truth, when the recording is still in its run directory (the view's MSE).
    if let Some(truth) = args
        .recording
        .parent()
        .map(|d| d.join("truth.npy"))
        .filter(|t| t.is_file())
    {
        c.arg("--truth").arg(truth);
    }
    fleet.spawn("fleet-watch", c, p)?;
    println!("live view: http://{addr}/ (replaying at {speed}x)");
    Ok(fleet)
}

fn classify(e: RecordingError) -> anyhow::Error {
    let bad = e.is_bad_file();
    fleet_exit::bad_input_if(e, bad)
}

pub fn run(args: Args) -> Result<()> {
    if let Some(s) = args.speed {
        if !(s.is_finite() && s > 0.0) {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "--speed {s}: give a positive factor (1: the recorded pace)"
            )));
        }
    }
    let rec = Recording::read(&args.recording).map_err(classify)?;
    if let Some(addr) = args.web {
        std::net::TcpListener::bind(addr).map_err(|e| {
            fleet_exit::bad_input(anyhow::anyhow!("--web {addr}: cannot serve the live view there ({e})"))
        })?;
    }
    let speed = args.speed.or(args.web.map(|_| 1.0));
    let stop = super::supervise::catch_stop_signals()?;
    let mut live = if args.web.is_some() {
        Some(start_live(&args, &rec, speed.expect("set with --web"))?)
    } else {
        None
    };
    let ops = rec
        .messages
        .iter()
        .filter(|m| m.topic == fleet_records::recording::CORE_TOPIC)
        .count();
    let pb = super::progress_bar(ops as u64, "replay");
    let (mut first, start) = (None, Instant::now());
    let mut ingested = 0u64;
    let core = rec
        .replay(&args.recording, |log_ns, op| {
            if let Some(sig) = stop.received() {
                // The live nodes go with us (their parent-death signal).
                std::process::exit(128 + sig);
            }
            if let Some(speed) = speed {
                let t0 = *first.get_or_insert(log_ns);
                let due = Duration::from_nanos(((log_ns.saturating_sub(t0)) as f64 / speed) as u64);
                if let Some(wait) = due.checked_sub(start.elapsed()) {
                    std::thread::sleep(wait);
                }
            }
            ingested += matches!(op, CoreOp::Ingest { .. }) as u64;
            pb.inc(1);
        })
        .map_err(classify)?;
    pb.finish_and_clear();
    fleet_records::outputs::write(&args.out, &core, rec.mission.pace.horizon)?;
    if let Some(fleet) = live.as_mut() {
        // The view follows the played-back traffic; when that ends, the view stays a while.
        fleet.wait_nodes(Duration::from_secs(120), &["fleet-watch"])?;
        if let Some(addr) = args.web.filter(|_| args.web_linger_s > 0) {
            linger(addr, args.web_linger_s, &stop);
        }
        fleet.stop();
    }
    println!(
        "replayed {} operations of mission {} ({ingested} batches in, {} accepted, {} duplicates) into {}",
        ops,
        rec.mission.mission,
        core.counters.batches - core.counters.duplicates,
        core.counters.duplicates,
        args.out.display()
    );
    compare_models(&core, &rec)
}

/// The live view stays up `linger_s` seconds after the replay (a stop signal ends it sooner).
fn linger(addr: std::net::SocketAddr, linger_s: u64, stop: &super::supervise::StopSignals) {
    println!("the replay is done; the live view stays at http://{addr}/ for {linger_s} s (Ctrl-C ends it)");
    let until = Instant::now() + Duration::from_secs(linger_s);
    while Instant::now() < until && stop.received().is_none() {
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The replayed final model against the recorded one: identical, bit for bit, or why not. The
/// model is put (and recorded) without its modes; a recording of an older build holds them.
fn compare_models(core: &fleet_mission::server::ServerCore, rec: &Recording) -> Result<()> {
    let replayed = core.model_update().map(|m| {
        let mut lean = m.clone();
        lean.take_modes();
        [lean, m].map(|m| protocol::encode(&Body::Model(m)))
    });
    let recorded = rec.final_model().map(|m| m.data.clone());
    match (replayed, recorded) {
        (Some(a), Some(b)) if a.contains(&b) => {
            println!(
                "final model v{}: identical to the recorded one, bit for bit ({} bytes)",
                core.version,
                b.len()
            );
            Ok(())
        }
        (Some(_), Some(_)) => bail!(
            "the replayed final model (v{}) differs from the recorded one: the core is not \
            deterministic, or the recording is not this build's",
            core.version
        ),
        (None, None) => {
            println!("no model: the recording ends before the first epoch was assimilated");
            Ok(())
        }
        (Some(_), None) => bail!(
            "the recording holds no published model, but its operations make one (v{})",
            core.version
        ),
        (None, Some(_)) => bail!("the recording holds a published model, but its operations make none"),
    }
}
