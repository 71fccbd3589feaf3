//! `fleet up [mission.toml]`: the whole fleet on this machine. Makes the mission's truth once,
//! starts the model server and every vehicle as separate processes on loopback Zenoh, shows
//! progress from the server's event stream, and ends with the report (the networked run
//! beside the offline loop on the same truth and seed) and the fleet's statistics.

use anyhow::{bail, Context};
use fleet::experiment::team;
use fleet::mission::config::{MissionConfig, DEFAULT_MISSION};
use fleet::mission::report::{write_mission_report, ServerEvent};
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Mission file (default: the bundled mission, config/mission.toml).
    mission: Option<PathBuf>,
    /// Directory for the truth, logs, summary.json, report.md and mse.png.
    #[arg(long, default_value = "fleet-run")]
    out: PathBuf,
    /// Give up if the mission is not finished after this many seconds.
    #[arg(long, default_value_t = 900)]
    timeout_s: u64,
}

/// Children killed when `up` ends, however it ends.
struct Fleet(Vec<(String, Child)>);

impl Drop for Fleet {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            if matches!(c.try_wait(), Ok(None)) {
                let _ = c.kill();
                let _ = c.wait();
            }
        }
    }
}

/// A sibling binary of this executable (the workspace builds them side by side).
fn sibling(name: &str) -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("locating this executable")?;
    let path = exe.with_file_name(name);
    if !path.exists() {
        bail!("{} not found next to {}: build the workspace first (`cargo build --release --workspace`)", name, exe.display());
    }
    Ok(path)
}

fn log_file(dir: &Path, name: &str) -> anyhow::Result<std::fs::File> {
    std::fs::File::create(dir.join(format!("{name}.log"))).with_context(|| format!("creating the log of {name}"))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let mission = MissionConfig::load(args.mission.as_deref())?;
    let out = &args.out;
    let logs = out.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    // Every node reads the same file: the default is written out beside the run.
    let mission_path = match &args.mission {
        Some(p) => p.clone(),
        None => {
            let p = out.join("mission.toml");
            std::fs::write(&p, DEFAULT_MISSION)?;
            p
        }
    };
    let (server_bin, vehicle_bin) = (sibling("model-server")?, sibling("vehicle")?);

    let pb = super::progress_bar(mission.truth.frames as u64, "truth");
    let truth = mission.truth(|k| pb.set_position(k as u64))?;
    pb.finish_and_clear();
    let (grid, frames) = mission.workspace(&truth)?;
    let truth_path = out.join("truth.npy");
    fleet::process::dataset::save(&truth_path, &truth, None)?;
    println!("mission {}: {} x {} grid, {frames} steps, {} vehicles (truth made in {:.1} s)", mission.mission, grid.rows, grid.cols, mission.vehicles().len(), t0.elapsed().as_secs_f64());

    // A new run starts from empty outboxes and an empty journal.
    let state = out.join("state");
    let _ = std::fs::remove_dir_all(&state);
    let node_args = |c: &mut Command| {
        c.arg("--mission").arg(&mission_path).arg("--truth").arg(&truth_path).arg("--state-dir").arg(&state);
    };
    let mut fleet = Fleet(vec![]);
    let mut server = Command::new(&server_bin);
    node_args(&mut server);
    server.arg("--events").arg("--out").arg(out).arg("--exit-when-done").stdout(Stdio::piped()).stderr(log_file(&logs, "server")?);
    let mut server = server.spawn().with_context(|| format!("starting {}", server_bin.display()))?;
    let stdout = server.stdout.take().expect("piped stdout");
    fleet.0.push(("server".into(), server));
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout).lines().map_while(Result::ok) {
            match serde_json::from_str::<ServerEvent>(&line) {
                Ok(e) => {
                    if tx.send(e).is_err() {
                        break;
                    }
                }
                Err(e) => eprintln!("server said something that is not an event ({e}): {line}"),
            }
        }
    });
    // The ground-station gateway runs until the run ends (dropped, so killed, at the end).
    let mut _gateway = Fleet(vec![]);
    if !mission.mavlink.gcs.is_empty() {
        let bin = sibling("gcs-gateway")?;
        let mut c = Command::new(&bin);
        c.arg("--mission").arg(&mission_path).stdout(Stdio::null()).stderr(log_file(&logs, "gcs-gateway")?);
        _gateway.0.push(("gcs-gateway".into(), c.spawn().with_context(|| format!("starting {}", bin.display()))?));
        println!("ground stations: the fleet is on {} (MAVLink 2; each vehicle its own system id)", mission.mavlink.gcs);
    }
    for v in mission.vehicles() {
        let mut c = Command::new(&vehicle_bin);
        node_args(&mut c);
        c.arg("--id").arg(&v.id).stdout(Stdio::null()).stderr(log_file(&logs, &v.id)?);
        fleet.0.push((v.id.clone(), c.spawn().with_context(|| format!("starting {}", vehicle_bin.display()))?));
    }

    let epochs = mission.schedule(frames).epochs();
    let pb = super::progress_bar(epochs, "epochs");
    let deadline = Instant::now() + Duration::from_secs(args.timeout_s);
    let mut alive = 0usize;
    let summary = loop {
        if Instant::now() > deadline {
            bail!("the mission did not finish in {} s (logs in {})", args.timeout_s, logs.display());
        }
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(ServerEvent::Epoch { epoch, version, mse, alive: a, .. }) => {
                alive = a;
                pb.set_position(epoch + 1);
                pb.set_message(format!("v{version} {a} alive mse {}", mse.map_or("-".into(), |m| format!("{m:.2e}"))));
            }
            Ok(ServerEvent::Link { alive: up, .. }) => {
                alive = if up { alive + 1 } else { alive.saturating_sub(1) };
            }
            Ok(ServerEvent::Ready { .. }) => pb.set_message("server ready"),
            Ok(ServerEvent::Hold { vehicle, held, mode }) => pb.println(format!("{vehicle}: {} ({mode})", if held { "left out of the allocation" } else { "back in the allocation" })),
            Ok(ServerEvent::Late { vehicle, epoch, version }) => pb.println(format!("{vehicle}: late batch of epoch {epoch} re-fitted the model (v{version})")),
            Ok(ServerEvent::Finished { summary }) => break summary,
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => bail!("the model server stopped before the mission finished (see {})", logs.join("server.log").display()),
        }
        for (name, c) in &mut fleet.0 {
            if let Ok(Some(status)) = c.try_wait() {
                if !status.success() {
                    bail!("{name} exited with {status} (see {})", logs.join(format!("{name}.log")).display());
                }
            }
        }
    };
    pb.finish_and_clear();
    // Vehicles leave once their last batch is acknowledged; then the server exits.
    let wait_until = Instant::now() + Duration::from_secs(60);
    for (name, c) in &mut fleet.0 {
        loop {
            match c.try_wait()? {
                Some(s) if s.success() => break,
                Some(s) => bail!("{name} exited with {s} (see {})", logs.join(format!("{name}.log")).display()),
                None if Instant::now() > wait_until => bail!("{name} did not exit after the mission"),
                None => std::thread::sleep(Duration::from_millis(50)),
            }
        }
    }

    let offline = team::run(&mission.team, &truth, |_, _| {})?;
    let command = format!("fleet up{} --out {}", args.mission.as_ref().map_or(String::new(), |p| format!(" {}", p.display())), out.display());
    let md = write_mission_report(out, &mission, &summary, &offline, truth.dt, &command)?;
    println!("{md}");
    println!("wrote {}/report.md, mse.png, summary.json, model.cbor and logs/ ({:.1} s in all)", out.display(), t0.elapsed().as_secs_f64());
    Ok(())
}
