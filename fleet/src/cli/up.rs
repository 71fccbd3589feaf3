//! `fleet up [mission.toml]`: the whole fleet on this machine. Makes the mission's truth once,
//! starts the model server and every vehicle as separate processes on loopback Zenoh, shows
//! progress from the server's event stream, and ends with the report (the networked run
//! beside the offline loop on the same truth and seed) and the fleet's statistics.
//!
//! `up` owns its nodes: they run in one process group of their own, a signal to `up`
//! (SIGTERM, SIGINT, SIGHUP) stops the whole group, and each node dies with `up` even if `up`
//! is killed outright (the parent-death signal). A new run is prepared beside the previous one
//! and replaces it only once its server is up, so a failed start leaves the previous run as it
//! was.

use super::supervise::{self, Supervisor};
use anyhow::{bail, Context};
use fleet::experiment::team;
use fleet::mission::report::{write_mission_report, ServerEvent, ServerSummary};
use fleet_exit::InputResult;
use fleet_math::process::FieldSeries;
use fleet_mission::config::{MissionConfig, DEFAULT_MISSION};
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Mission file (default: the bundled mission, config/mission.toml).
    mission: Option<PathBuf>,
    /// Directory for the run: report.md, mse.png, estimate.nc, the truth, logs, events and the
    /// server's outputs (replaced as a whole by the next run).
    #[arg(long, default_value = "fleet-run")]
    out: PathBuf,
    /// Give up if the mission is not finished after this many seconds.
    #[arg(long, default_value_t = 900)]
    timeout_s: u64,
    /// Serve the live view here (e.g. 127.0.0.1:8080) while the mission runs (`fleet-watch`).
    #[arg(long)]
    web: Option<std::net::SocketAddr>,
    /// With --web: keep the view up this many seconds after the mission, to look at the
    /// finished run and save its report (Ctrl-C ends it sooner; 0: stop with the mission).
    #[arg(long, default_value_t = 600)]
    web_linger_s: u64,
    /// What recording.mcap keeps: `lean` (what `fleet replay` needs to rebuild the model bit
    /// for bit and the Foxglove channels, compressed; one model in ten and the last) or `full`
    /// (also every model as published, uncompressed).
    #[arg(long, default_value = "lean")]
    record: fleet_records::recording::RecordMode,
    /// Serve the mission to Foxglove here while it runs (its WebSocket protocol, loopback; e.g.
    /// 127.0.0.1:8765): `fleet-watch --foxglove`, with the channels a recording has.
    #[arg(long)]
    foxglove: Option<std::net::SocketAddr>,
}

/// What a run leaves in `--out` (replaced as a whole by the next run's).
const RUN_FILES: [&str; 17] = [
    "state",
    "logs",
    "truth.npy",
    "truth.json",
    "recording.mcap",
    "mission.toml",
    "events.jsonl",
    "report.md",
    "mse.png",
    "summary.json",
    "model.cbor",
    "estimate.npy",
    "variance.npy",
    "plans.json",
    "estimate.nc",
    "readings.nc",
    "readings.ndjson",
];

/// A sibling binary of this executable (the workspace builds them side by side).
pub(super) fn sibling(name: &str) -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("locating this executable")?;
    let path = exe.with_file_name(name);
    if !path.exists() {
        bail!(
            "{} not found next to {}: build the workspace first (`cargo build --release --workspace`)",
            name,
            exe.display()
        );
    }
    Ok(path)
}

fn log_file(dir: &Path, name: &str) -> anyhow::Result<(std::fs::File, PathBuf)> {
    let path = dir.join(format!("{name}.log"));
    let f = std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    Ok((f, path))
}

/// Notices for the operator: above the progress bar on a terminal, plain lines otherwise, and
/// always in `logs/fleet-up.log`.
struct Notices {
    pb: indicatif::ProgressBar,
    tty: bool,
    log: std::fs::File,
}

impl Notices {
    fn say(&mut self, text: String) {
        if self.tty {
            self.pb.println(&text);
        } else {
            println!("{text}");
        }
        let _ = writeln!(self.log, "{text}");
    }
}

/// Refuse endpoints another process holds before anything is started or replaced.
fn check_ports_free(mission: &MissionConfig) -> anyhow::Result<()> {
    for ep in &mission.network.listen {
        let Some(addr) = ep
            .strip_prefix("tcp/")
            .and_then(|a| a.parse::<std::net::SocketAddr>().ok())
        else {
            continue;
        };
        if let Err(e) = std::net::TcpListener::bind(addr) {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "[network] listen {ep}: {e} (another fleet or program is using it; stop it or change the endpoint)"
            )));
        }
    }
    if let Some(addr) = mission
        .mavlink
        .gcs
        .strip_prefix("udpin:")
        .and_then(|a| a.parse::<std::net::SocketAddr>().ok())
    {
        if let Err(e) = std::net::UdpSocket::bind(addr) {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "[mavlink] gcs {}: {e}",
                mission.mavlink.gcs
            )));
        }
    }
    Ok(())
}

/// Replace the previous run in `out` by the staged one.
fn commit_start(out: &Path, staging: &Path) -> anyhow::Result<()> {
    for name in RUN_FILES {
        let old = out.join(name);
        if old.is_dir() {
            std::fs::remove_dir_all(&old).with_context(|| format!("removing the previous run's {}", old.display()))?;
        } else if old.exists() {
            std::fs::remove_file(&old).with_context(|| format!("removing the previous run's {}", old.display()))?;
        }
        let new = staging.join(name);
        if new.exists() {
            std::fs::rename(&new, &old).with_context(|| format!("moving {} into place", new.display()))?;
        }
    }
    let _ = std::fs::remove_dir_all(staging);
    Ok(())
}

/// The binaries `up` starts, found beside this one.
struct Binaries {
    server: PathBuf,
    vehicle: PathBuf,
    gateway: Option<PathBuf>,
    watch: Option<PathBuf>,
}

impl Binaries {
    fn find(args: &Args, mission: &MissionConfig) -> anyhow::Result<Self> {
        Ok(Self {
            server: sibling("model-server")?,
            vehicle: sibling("vehicle")?,
            gateway: (!mission.mavlink.gcs.is_empty())
                .then(|| sibling("gcs-gateway"))
                .transpose()?,
            watch: (args.web.is_some() || args.foxglove.is_some())
                .then(|| sibling("fleet-watch"))
                .transpose()?,
        })
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let mission = MissionConfig::load(args.mission.as_deref())?;
    let bins = Binaries::find(&args, &mission)?;
    check_ports_free(&mission)?;
    if let Some(addr) = args.web {
        std::net::TcpListener::bind(addr)
            .with_context(|| format!("--web {addr}: cannot serve the live view there"))
            .input()?;
    }
    if let Some(addr) = args.foxglove {
        if !addr.ip().is_loopback() {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "--foxglove {addr}: fleet up serves Foxglove on loopback only; for another address run \
                `fleet-watch --foxglove {addr} --credential user:password` beside it"
            )));
        }
        std::net::TcpListener::bind(addr)
            .with_context(|| format!("--foxglove {addr}: cannot serve Foxglove there"))
            .input()?;
    }
    let out = &args.out;
    std::fs::create_dir_all(out)
        .with_context(|| format!("creating {}", out.display()))
        .input()?;
    // Staged beside the previous run until the server is up.
    let staging = out.join(format!(".starting-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&staging);
    let cleanup = StagingGuard(Some(staging.clone()));
    keep_mission(&args, &staging)?;
    let (truth, frames) = make_truth(&mission, &staging, t0)?;
    let stop = supervise::catch_stop_signals()?;
    let mut fleet = Supervisor::default();
    let events = start_server(&args, &bins, &mut fleet, &staging)?;
    wait_until_ready(&stop, &mut fleet, &events, &staging, out)?;
    commit_start(out, &staging)?;
    drop(cleanup);
    start_nodes(&args, &bins, &mission, &mut fleet)?;
    let (summary, events) = follow(&args, &mission, frames, &stop, &mut fleet, &events)?;
    // Vehicles leave once their last batch is acknowledged; then the server exits.
    fleet.wait_nodes(Duration::from_secs(60), &["gcs-gateway", "fleet-watch"])?;
    if args.web.is_none() {
        fleet.stop();
    }
    finish(&args, &mission, truth.as_ref(), &summary, &events, t0)?;
    if let Some(addr) = args.web {
        linger(addr, args.web_linger_s, &stop);
        fleet.stop();
    }
    Ok(())
}

/// Where the nodes read the mission: the operator's file (its relative paths are relative to
/// it), or the run's copy of the bundled one.
fn mission_file(args: &Args, dir: &Path) -> PathBuf {
    args.mission.clone().unwrap_or_else(|| dir.join("mission.toml"))
}

/// The run keeps its mission (for the record and `fleet export`).
fn keep_mission(args: &Args, staging: &Path) -> anyhow::Result<()> {
    let logs = staging.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    match &args.mission {
        None => std::fs::write(staging.join("mission.toml"), DEFAULT_MISSION)?,
        Some(p) => {
            std::fs::copy(p, staging.join("mission.toml"))
                .with_context(|| format!("copying {} into the run", p.display()))?;
        }
    }
    Ok(())
}

/// The mission's truth, made once and saved for every node (none in the field: the vehicles
/// read instruments); its number of steps.
fn make_truth(mission: &MissionConfig, staging: &Path, t0: Instant) -> anyhow::Result<(Option<FieldSeries>, usize)> {
    let pb = super::progress_bar(mission.frames_hint() as u64, "truth");
    let truth = mission.truth(|k| pb.set_position(k as u64))?;
    pb.finish_and_clear();
    let (grid, frames) = mission.workspace(truth.as_ref().map(FieldSeries::shape))?;
    // The autopilots' launch points must clear the fence's margin: refused here, not at the shore.
    if mission.mavlink.autopilot != "none" {
        fleet_mission::launch::launch_points(mission, &grid)?;
    }
    if let Some(truth) = &truth {
        fleet_math::process::dataset::save(
            staging.join("truth.npy"),
            truth,
            Some(&serde_json::json!({"process": "fleet up", "mission": mission.mission, "dt": truth.dt})),
        )?;
    }
    println!(
        "mission {}: {} x {} grid, {frames} steps, {} vehicles ({})",
        mission.mission,
        grid.rows,
        grid.cols,
        mission.vehicles().len(),
        match &truth {
            Some(_) => format!("truth made in {:.1} s", t0.elapsed().as_secs_f64()),
            None => "no truth: instruments only, scored by held-out readings".into(),
        }
    );
    println!("site: {}", mission.site_said(&grid));
    Ok((truth, frames))
}

/// `--truth <path>` for a node, when the run has a truth.
fn truth_arg(c: &mut Command, path: &Path) {
    if path.is_file() {
        c.arg("--truth").arg(path);
    }
}

/// What the server says on its standard output, line by line: an event, or why a line is not
/// one.
type Said = Result<ServerEvent, String>;

/// mimalloc's purge delay (ms; -1: never give freed memory back to the system).
const PURGE_DELAY: &str = "MIMALLOC_PURGE_DELAY";

/// The model server, started on the staged run; its events (also kept in `events.jsonl`).
fn start_server(
    args: &Args,
    bins: &Binaries,
    fleet: &mut Supervisor,
    staging: &Path,
) -> anyhow::Result<mpsc::Receiver<Said>> {
    let mut server = Command::new(&bins.server);
    // mimalloc keeps the memory the server frees for its next epoch instead of returning it to
    // the system, where each epoch's N x r matrices came back as fresh pages the kernel zeroed
    // (docs/decisions/064 and the third pass, 066, measured what it bought). Only the
    // environment sets it early enough: `mi_option_set` at start-up did not take. A value the
    // user set is kept.
    if std::env::var_os(PURGE_DELAY).is_none() {
        server.env(PURGE_DELAY, "-1");
    }
    server.arg("--mission").arg(mission_file(args, staging));
    truth_arg(&mut server, &staging.join("truth.npy"));
    server.arg("--state-dir").arg(staging.join("state"));
    // Moved into --out with the rest once the server is up (the open file goes with its name).
    server.arg("--record").arg(staging.join("recording.mcap"));
    server.arg("--record-mode").arg(args.record.to_string());
    let (server_log, _) = log_file(&staging.join("logs"), "server")?;
    server
        .arg("--events")
        .arg("--out")
        .arg(&args.out)
        .arg("--exit-when-done")
        .stdout(Stdio::piped())
        .stderr(server_log);
    let mut stdout = fleet.spawn("model-server", server, args.out.join("logs/server.log"))?;
    let stdout = stdout.take().expect("piped stdout");
    let (tx, rx) = mpsc::channel();
    let mut events_file = std::fs::File::create(staging.join("events.jsonl"))?;
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout).lines().map_while(Result::ok) {
            let event = serde_json::from_str::<ServerEvent>(&line)
                .map_err(|e| format!("the server said something that is not an event ({e}): {line}"));
            if event.is_ok() {
                let _ = writeln!(events_file, "{line}");
            }
            if tx.send(event).is_err() {
                break;
            }
        }
    });
    Ok(rx)
}

/// The start: until the server is up, a failure leaves the previous run as it was.
fn wait_until_ready(
    stop: &supervise::StopSignals,
    fleet: &mut Supervisor,
    events: &mpsc::Receiver<Said>,
    staging: &Path,
    out: &Path,
) -> anyhow::Result<()> {
    let server_log_path = staging.join("logs/server.log");
    let ready_by = Instant::now() + Duration::from_secs(120);
    loop {
        if let Some(sig) = stop.received() {
            fleet.stop();
            bail!(
                "stopped by signal {sig} before the server was up (the previous run in {} is unchanged)",
                out.display()
            );
        }
        if let Ok(Ok(ServerEvent::Ready { .. })) = events.recv_timeout(Duration::from_millis(100)) {
            return Ok(());
        }
        if let Some(dead) = fleet.exited() {
            // Its log is still in the staging directory.
            let why = supervise::last_line(&server_log_path);
            return Err(dead.into_error(why, &format!("the previous run in {} is unchanged", out.display())));
        }
        if Instant::now() > ready_by {
            fleet.stop();
            bail!(
                "the model server was not up after 120 s (its log: {}; the previous run in {} is unchanged)",
                server_log_path.display(),
                out.display()
            );
        }
    }
}

/// The ground-station gateway, every vehicle, and the live view if asked for.
fn start_nodes(args: &Args, bins: &Binaries, mission: &MissionConfig, fleet: &mut Supervisor) -> anyhow::Result<()> {
    let out = &args.out;
    let (logs, state, truth_path) = (out.join("logs"), out.join("state"), out.join("truth.npy"));
    let mission_path = mission_file(args, out);
    if let Some(bin) = &bins.gateway {
        let mut c = Command::new(bin);
        let (log, path) = log_file(&logs, "gcs-gateway")?;
        c.arg("--mission").arg(&mission_path).stdout(Stdio::null()).stderr(log);
        fleet.spawn("gcs-gateway", c, path)?;
        println!(
            "ground stations: the fleet is on {} (MAVLink 2; each vehicle its own system id)",
            mission.mavlink.gcs
        );
    }
    for v in mission.vehicles() {
        let mut c = Command::new(&bins.vehicle);
        c.arg("--mission").arg(&mission_path);
        truth_arg(&mut c, &truth_path);
        c.arg("--state-dir").arg(&state);
        let (log, path) = log_file(&logs, &v.id)?;
        c.arg("--id").arg(v.id.as_str()).stdout(Stdio::null()).stderr(log);
        fleet.spawn(&v.id, c, path)?;
    }
    if let Some(bin) = &bins.watch {
        let mut c = Command::new(bin);
        c.arg("--mission").arg(&mission_path);
        truth_arg(&mut c, &truth_path);
        let (log, path) = log_file(&logs, "fleet-watch")?;
        if let Some(addr) = args.foxglove {
            c.arg("--foxglove").arg(addr.to_string());
            println!("Foxglove: ws://{addr} (open it in Foxglove with docs/foxglove-layout.json)");
        }
        // Without --web the page is on an ephemeral loopback port, for nobody.
        let http = args.web.unwrap_or(std::net::SocketAddr::from(([127, 0, 0, 1], 0)));
        c.arg("--http")
            .arg(http.to_string())
            .arg("--run-dir")
            .arg(out)
            .stdout(Stdio::null())
            .stderr(log);
        fleet.spawn("fleet-watch", c, path)?;
        // The mission does not depend on its view: if the view dies, it is said, not fatal.
        fleet.optional("fleet-watch");
        if let Some(addr) = args.web {
            println!("live view: http://{addr}/");
        }
    }
    Ok(())
}

/// The mission as it goes, from the server's events: progress, notices, and the end (the
/// server's summary and every event but the last), or why it cannot finish.
fn follow(
    args: &Args,
    mission: &MissionConfig,
    frames: usize,
    stop: &supervise::StopSignals,
    fleet: &mut Supervisor,
    rx: &mpsc::Receiver<Said>,
) -> anyhow::Result<(ServerSummary, Vec<ServerEvent>)> {
    let logs = args.out.join("logs");
    let pb = super::progress_bar(mission.schedule(frames).epochs(), "epochs");
    let mut notices = Notices {
        pb: pb.clone(),
        tty: std::io::IsTerminal::is_terminal(&std::io::stderr()),
        log: std::fs::File::create(logs.join("fleet-up.log"))?,
    };
    let deadline = Instant::now() + Duration::from_secs(args.timeout_s);
    let (mut alive, mut events) = (0usize, vec![]);
    let summary = loop {
        if let Some(sig) = stop.received() {
            pb.finish_and_clear();
            fleet.stop();
            let state = args.out.join("state");
            notices.say(format!(
                "stopped by signal {sig}: every node of the fleet stopped; the run's state is in {} \
                (nodes restarted on it resume)",
                state.display()
            ));
            std::process::exit(128 + sig);
        }
        if Instant::now() > deadline {
            bail!(
                "the mission did not finish in {} s (logs in {})",
                args.timeout_s,
                logs.display()
            );
        }
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(Ok(ServerEvent::Finished { summary })) => break summary,
            Ok(Ok(e)) => {
                on_event(&e, &pb, &mut notices, &mut alive, &logs)?;
                events.push(e);
            }
            Ok(Err(said)) => notices.say(said),
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => return Err(server_gone(fleet, &logs)),
        }
        check_nodes(fleet, &mut notices)?;
    };
    pb.finish_and_clear();
    Ok((*summary, events))
}

/// One server event, shown: progress, or a notice for the operator. A refused batch ends the
/// mission (its epoch cannot complete).
fn on_event(
    e: &ServerEvent,
    pb: &indicatif::ProgressBar,
    notices: &mut Notices,
    alive: &mut usize,
    logs: &Path,
) -> anyhow::Result<()> {
    match e {
        ServerEvent::Epoch {
            epoch,
            version,
            mse,
            alive: a,
            ..
        } => {
            *alive = *a;
            pb.set_position(epoch + 1);
            pb.set_message(format!(
                "v{version} {a} alive mse {}",
                mse.map_or("-".into(), |m| format!("{m:.2e}"))
            ));
        }
        ServerEvent::Link { alive: up, .. } => *alive = if *up { *alive + 1 } else { alive.saturating_sub(1) },
        ServerEvent::Ready { .. } => pb.set_message("server ready"),
        ServerEvent::Hold { vehicle, held, mode } => notices.say(format!(
            "{vehicle}: {} ({mode})",
            if *held {
                "left out of the allocation"
            } else {
                "back in the allocation"
            }
        )),
        ServerEvent::Late {
            vehicle,
            epoch,
            version,
        } => notices.say(format!(
            "{vehicle}: late batch of epoch {epoch} re-fitted the model (v{version})"
        )),
        ServerEvent::Refused {
            vehicle, seq, detail, ..
        } => {
            notices.say(format!("{vehicle}: batch {seq} refused by the server: {detail}"));
            bail!(
                "{vehicle}'s batch {seq} was refused ({detail}): its epoch cannot complete, so the \
                mission cannot finish (logs in {})",
                logs.display()
            );
        }
        ServerEvent::Waiting {
            epoch,
            waited_s,
            behind,
        } => {
            for (vehicle, why) in behind {
                notices.say(format!("epoch {epoch} has waited {waited_s:.0} s for {vehicle}: {why}"));
            }
        }
        ServerEvent::Lost { vehicle, seqs } => notices.say(format!(
            "{vehicle}: batches {seqs:?} were acknowledged but are not in the journal: lost"
        )),
        ServerEvent::Sensor(v) => notices.say(format!(
            "{}: sensor {} at step {} ({})",
            v.vehicle, v.to, v.step, v.reason
        )),
        ServerEvent::Override(o) => notices.say(format!(
            "{}: sensor {} from step {}, by the operator",
            o.vehicle,
            o.set.map_or_else(|| "back to its tests".to_string(), |h| h.to_string()),
            o.from_step
        )),
        ServerEvent::Finished { .. } => {}
    }
    Ok(())
}

/// The server's pipe closed: it has exited; why, in its own words.
fn server_gone(fleet: &mut Supervisor, logs: &Path) -> anyhow::Error {
    // (Its exit status arrives a moment after its pipe closes.)
    std::thread::sleep(Duration::from_millis(200));
    let dead = fleet.exited();
    let why = supervise::last_line(&logs.join("server.log"));
    match dead {
        Some(d) => d.into_error(why, "the mission did not finish"),
        None => anyhow::anyhow!(
            "the model server closed its output before the mission finished: {}",
            why.unwrap_or_default()
        ),
    }
}

/// A node that died ends the mission; the live view's death is only said.
fn check_nodes(fleet: &mut Supervisor, notices: &mut Notices) -> anyhow::Result<()> {
    if let Some(dead) = fleet.exited() {
        let why = supervise::last_line(&dead.log);
        return Err(dead.into_error(why, "the mission did not finish"));
    }
    if let Some(view) = fleet.optional_exited() {
        let why = supervise::last_line(&view.log).unwrap_or_default();
        notices.say(format!(
            "the live view stopped ({}): the mission goes on without it; {why} (log: {})",
            view.status,
            view.log.display()
        ));
    }
    Ok(())
}

/// The report (the networked run beside the offline loop on the same truth and seed) and the
/// NetCDF export.
fn finish(
    args: &Args,
    mission: &MissionConfig,
    truth: Option<&FieldSeries>,
    summary: &ServerSummary,
    events: &[ServerEvent],
    t0: Instant,
) -> anyhow::Result<()> {
    let out = &args.out;
    let offline = truth.map(|t| team::run(&mission.team, t, |_, _| {})).transpose()?;
    let command = format!(
        "fleet up{} --out {}",
        args.mission
            .as_ref()
            .map_or(String::new(), |p| format!(" {}", p.display())),
        out.display()
    );
    gather_readings(out, mission)?;
    let (grid, _) = mission.workspace(truth.map(FieldSeries::shape))?;
    let md = write_mission_report(out, mission, summary, offline.as_ref(), &grid, &command, events)?;
    println!("{md}");
    // Everything else is written first: a NetCDF that cannot be written fails the run at the
    // end, and `fleet export` can write it again from the run directory.
    let nc = fleet::export::Run::load(out).and_then(|run| {
        fleet::export::netcdf::write(&run, &out.join("estimate.nc"))?;
        fleet::export::trajectory::write(&run, &out.join("readings.nc"))
    });
    let written = match &nc {
        Ok(Some(_)) => " estimate.nc, readings.nc,",
        Ok(None) => " estimate.nc,",
        Err(_) => "",
    };
    println!(
        "wrote {}/report.md, mse.png,{written} events.jsonl, summary.json, model.cbor, recording.mcap and logs/ \
            ({:.1} s in all)",
        out.display(),
        t0.elapsed().as_secs_f64()
    );
    nc.map(|_| ())
        .map_err(|e| anyhow::Error::new(e).context("writing estimate.nc and readings.nc"))
}

/// The vehicles' readings logs (`state/<id>.readings.ndjson`, instrument vehicles only) as one
/// `readings.ndjson`, in the mission's order of vehicles (nothing when no vehicle has one).
fn gather_readings(out: &Path, mission: &MissionConfig) -> anyhow::Result<()> {
    let logs: Vec<PathBuf> = mission
        .vehicles()
        .iter()
        .map(|v| out.join("state").join(format!("{}.readings.ndjson", v.id)))
        .filter(|p| p.is_file())
        .collect();
    if logs.is_empty() {
        return Ok(());
    }
    let path = out.join("readings.ndjson");
    let mut all = std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    for log in logs {
        let mut f = std::fs::File::open(&log).with_context(|| format!("reading {}", log.display()))?;
        std::io::copy(&mut f, &mut all).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// With --web: the live view stays up `linger_s` seconds after the mission (a stop signal now
/// just ends the view: exit 0).
fn linger(addr: std::net::SocketAddr, linger_s: u64, stop: &supervise::StopSignals) {
    if linger_s == 0 {
        return;
    }
    println!("the live view stays at http://{addr}/ for {linger_s} s (the finished run, its report); Ctrl-C ends it");
    let until = Instant::now() + Duration::from_secs(linger_s);
    while Instant::now() < until && stop.received().is_none() {
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Removes the staging directory however `run` ends (after a committed start it is gone).
struct StagingGuard(Option<PathBuf>);

impl Drop for StagingGuard {
    fn drop(&mut self) {
        if let Some(d) = self.0.take() {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}
