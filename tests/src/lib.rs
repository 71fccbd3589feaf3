//! Helpers for the cross-process tests: where the workspace's binaries and reference data are.

use fleet::mission::report::{ServerEvent, ServerSummary};
use std::path::PathBuf;
use std::process::{Command, Output};

pub mod lossy_link;

/// The workspace root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

/// Path of a workspace binary built in the same profile as this test (`cargo test --release`
/// builds it into the same target directory).
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe.parent().and_then(|d| d.parent()).expect("target dir");
    dir.join(name)
}

/// Run a workspace binary with arguments, from the workspace root.
pub fn run(name: &str, args: &[&str]) -> Output {
    let path = bin(name);
    Command::new(&path)
        .args(args)
        .current_dir(root())
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "cannot start {}: {e} (build it with `cargo build --release --workspace`)",
                path.display()
            )
        })
}

/// `fleet experiment` on `text` written to `<dir>/<name>.toml`; its output and report directory.
pub fn experiment_file(dir: &std::path::Path, name: &str, text: &str) -> (Output, PathBuf) {
    let toml = dir.join(format!("{name}.toml"));
    std::fs::write(&toml, text).expect("writing the experiment");
    let rep = dir.join(name);
    let out = run(
        "fleet",
        &["experiment", toml.to_str().unwrap(), "--out", rep.to_str().unwrap()],
    );
    (out, rep)
}

/// A scratch directory for one test (removed and made afresh).
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("hetfleet-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch dir");
    d
}

/// A loopback port free now over both TCP and UDP, never handed out twice by this process.
///
/// A test names the port and its processes bind it seconds later. A port from the kernel's
/// ephemeral range (what binding port 0 gives) can be taken in between by any socket the kernel
/// numbers itself (a UDP sender, a simulated autopilot's link): so the port is drawn from below
/// that range, where only a socket that asks for it by number can land.
pub fn free_port() -> u16 {
    static GIVEN: std::sync::Mutex<std::collections::BTreeSet<u16>> =
        std::sync::Mutex::new(std::collections::BTreeSet::new());
    let ephemeral_low = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|w| w.parse::<u16>().ok()))
        .unwrap_or(32768);
    let (low, high) = (10_000u16, ephemeral_low.max(12_000));
    let span = u32::from(high - low);
    let seed = std::process::id().wrapping_mul(2_654_435_761) % span;
    let mut given = GIVEN.lock().unwrap_or_else(|e| e.into_inner());
    (0..span)
        .map(|i| low + ((seed + i) % span) as u16)
        .find(|&p| {
            !given.contains(&p)
                && std::net::TcpListener::bind(("127.0.0.1", p)).is_ok()
                && std::net::UdpSocket::bind(("127.0.0.1", p)).is_ok()
        })
        .inspect(|&p| {
            given.insert(p);
        })
        .expect("a free loopback port below the ephemeral range")
}

/// `config/mission-tiny.toml` with its endpoints replaced, written into `dir`.
pub fn tiny_mission(dir: &std::path::Path, listen: &[String], connect: &[String]) -> PathBuf {
    let text = std::fs::read_to_string(root().join("config/mission-tiny.toml")).expect("the tiny mission");
    let list = |v: &[String]| {
        format!(
            "[{}]",
            v.iter().map(|e| format!("{e:?}")).collect::<Vec<_>>().join(", ")
        )
    };
    let text = text
        .replace(
            r#"listen = ["tcp/127.0.0.1:7461"]"#,
            &format!("listen = {}", list(listen)),
        )
        .replace(
            r#"connect = ["tcp/127.0.0.1:7461"]"#,
            &format!("connect = {}", list(connect)),
        );
    let path = dir.join("mission.toml");
    std::fs::write(&path, text).expect("writing the mission");
    path
}

/// The tiny mission paced (`step_ms` a step, so there is time to break things mid-way), with
/// a short plan timeout and a 1 s link lease.
pub fn paced_mission(dir: &std::path::Path, listen: &[String], connect: &[String], step_ms: u64) -> PathBuf {
    let m = tiny_mission(dir, listen, connect);
    edit(
        &m,
        "plan_timeout_ms = 20000",
        &format!("plan_timeout_ms = 1500\nstep_ms = {step_ms}"),
    );
    edit(&m, "listen = [", "lease_ms = 1000\nlisten = [");
    m
}

/// Child processes killed when dropped (a failing test leaves nothing running).
#[derive(Default)]
pub struct Procs(pub Vec<std::process::Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// The model server started with `--events`; its events arrive on `events`.
pub struct Server {
    pub events: std::sync::mpsc::Receiver<ServerEvent>,
    /// Its place in the `Procs` it was started into.
    pub index: usize,
}

/// Start `model-server` with `args` (plus `--events`), stderr to `log` (appended, so a
/// restarted server's log follows the first one's).
pub fn start_server(procs: &mut Procs, args: &[&str], log: &std::path::Path) -> Server {
    use std::io::BufRead;
    let mut child = Command::new(bin("model-server"))
        .args(args)
        .arg("--events")
        .current_dir(root())
        .stdout(std::process::Stdio::piped())
        .stderr(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(log)
                .expect("server log"),
        )
        .spawn()
        .expect("starting model-server (build with `cargo build --release --workspace`)");
    let out = child.stdout.take().expect("piped");
    procs.0.push(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(out).lines().map_while(Result::ok) {
            if let Ok(e) = serde_json::from_str(&line) {
                if tx.send(e).is_err() {
                    break;
                }
            }
        }
    });
    Server {
        events: rx,
        index: procs.0.len() - 1,
    }
}

impl Server {
    /// Whether another epoch enters the model within `timeout`.
    pub fn next_epoch(&self, timeout: std::time::Duration) -> bool {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            match self
                .events
                .recv_timeout(deadline.saturating_duration_since(std::time::Instant::now()))
            {
                Ok(ServerEvent::Epoch { .. }) => return true,
                Ok(_) => {}
                Err(_) => return false,
            }
        }
    }

    /// Wait until epoch `e` is in the model (panics after `secs`).
    pub fn epoch(&self, e: u64, secs: u64) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.events.recv_timeout(left) {
                Ok(ServerEvent::Epoch { epoch, .. }) if epoch >= e => return,
                Ok(_) => {}
                Err(err) => panic!("epoch {e} not reached in {secs} s: {err}"),
            }
        }
    }

    /// Wait for the mission's summary (panics after `secs`).
    pub fn finished(&self, secs: u64) -> ServerSummary {
        self.finished_with_events(secs).0
    }

    /// The summary, and every event before it (panics after `secs`).
    pub fn finished_with_events(&self, secs: u64) -> (ServerSummary, Vec<ServerEvent>) {
        self.try_finished_with_events(secs)
            .unwrap_or_else(|why| panic!("{why}"))
    }

    /// The summary and every event before it, or why the mission did not finish in `secs`.
    pub fn try_finished_with_events(&self, secs: u64) -> Result<(ServerSummary, Vec<ServerEvent>), String> {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        let mut seen = vec![];
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.events.recv_timeout(left) {
                Ok(ServerEvent::Finished { summary }) => return Ok((*summary, seen)),
                Ok(e) => seen.push(e),
                Err(e) => {
                    return Err(format!(
                        "the mission did not finish in {secs} s: {e}; {}",
                        where_it_stood(&seen)
                    ))
                }
            }
        }
    }
}

/// Where a mission that did not finish stood, from its events: the last epoch in the model,
/// whom the server said it waited for and why, and what it refused or found lost (so a run
/// that hangs on a machine nobody watches says why in its failure).
fn where_it_stood(seen: &[ServerEvent]) -> String {
    use ServerEvent as E;
    let last_epoch = seen.iter().rev().find_map(|e| match e {
        E::Epoch { epoch, .. } => Some(*epoch),
        _ => None,
    });
    let last_wait = seen.iter().rev().find(|e| matches!(e, E::Waiting { .. }));
    let trouble: Vec<_> = seen
        .iter()
        .filter(|e| matches!(e, E::Refused { .. } | E::Lost { .. } | E::Link { alive: false, .. }))
        .rev()
        .take(8)
        .collect();
    format!(
        "last epoch in the model {last_epoch:?}; last wait {last_wait:?}; \
         latest refusals, losses and lost links {trouble:?}"
    )
}

/// Start a vehicle node: `prefix` runs it under another command (e.g. `ip netns exec ns`).
/// Returns its place in `procs`. The log is appended to (restarts follow on).
pub fn start_vehicle(procs: &mut Procs, prefix: &[&str], args: &[&str], log: &std::path::Path) -> usize {
    let mut cmd = match prefix.split_first() {
        Some((p, rest)) => {
            let mut c = Command::new(p);
            c.args(rest).arg(bin("vehicle"));
            c
        }
        None => Command::new(bin("vehicle")),
    };
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(log)
        .expect("vehicle log");
    let child = cmd
        .args(args)
        .current_dir(root())
        .stderr(log)
        .spawn()
        .expect("starting a vehicle");
    procs.0.push(child);
    procs.0.len() - 1
}

impl Procs {
    /// `kill -9` one of them.
    pub fn kill(&mut self, i: usize) {
        self.0[i].kill().expect("SIGKILL");
        self.0[i].wait().expect("reaped");
    }

    /// Wait for every process to exit successfully (killed ones are already reaped).
    pub fn wait_all(&mut self, secs: u64) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        for c in &mut self.0 {
            loop {
                match c.try_wait().expect("try_wait") {
                    Some(s) => {
                        // Killed on purpose (SIGKILL) or finished: only a failure is an error.
                        use std::os::unix::process::ExitStatusExt;
                        assert!(s.success() || s.signal() == Some(9), "a node failed: {s}");
                        break;
                    }
                    None if std::time::Instant::now() > deadline => panic!("a node did not exit in {secs} s"),
                    None => std::thread::sleep(std::time::Duration::from_millis(50)),
                }
            }
        }
    }
}

/// Replace `from` by `to` in a text file (tests adjust a mission).
pub fn edit(path: &std::path::Path, from: &str, to: &str) {
    let text = std::fs::read_to_string(path).expect("reading");
    assert!(text.contains(from), "{from:?} not in {}", path.display());
    std::fs::write(path, text.replace(from, to)).expect("writing");
}

/// The number of batches a mission's vehicles send (one per epoch each takes part in).
pub fn expected_batches(m: &fleet_mission::config::MissionConfig, frames: usize) -> u64 {
    let s = m.schedule(frames);
    m.vehicles()
        .iter()
        .map(|v| (0..s.epochs()).filter(|&e| s.seq_of(v.kind, e).is_some()).count() as u64)
        .sum()
}

/// Whether this process may make network namespaces (root with iproute2).
pub fn is_root_with_ip() -> bool {
    let root = std::process::Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false);
    root && std::process::Command::new("ip").arg("-V").output().is_ok()
}

/// Run a command, panicking with its output if it fails.
pub fn sh(args: &[&str]) {
    let o = std::process::Command::new(args[0])
        .args(&args[1..])
        .output()
        .unwrap_or_else(|e| panic!("{args:?}: {e}"));
    assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
}

/// Another host: a network namespace behind a veth link, removed when dropped.
pub struct Host {
    pub ns: String,
    /// This host's address on the link, and the other host's.
    pub here: String,
    pub there: String,
}

impl Host {
    pub fn new(tag: u32) -> Self {
        let x = (std::process::id() + tag) % 200 + 20;
        let h = Host {
            ns: format!("hft{x}"),
            here: format!("10.78.{x}.1"),
            there: format!("10.78.{x}.2"),
        };
        let (va, vb) = (h.veth(), format!("{}b", h.ns));
        sh(&["ip", "netns", "add", &h.ns]);
        sh(&["ip", "link", "add", &va, "type", "veth", "peer", "name", &vb]);
        sh(&["ip", "link", "set", &vb, "netns", &h.ns]);
        sh(&["ip", "addr", "add", &format!("{}/24", h.here), "dev", &va]);
        sh(&["ip", "link", "set", &va, "up"]);
        sh(&[
            "ip",
            "netns",
            "exec",
            &h.ns,
            "ip",
            "addr",
            "add",
            &format!("{}/24", h.there),
            "dev",
            &vb,
        ]);
        sh(&["ip", "netns", "exec", &h.ns, "ip", "link", "set", &vb, "up"]);
        sh(&["ip", "netns", "exec", &h.ns, "ip", "link", "set", "lo", "up"]);
        h
    }

    /// This side of the link.
    pub fn veth(&self) -> String {
        format!("{}a", self.ns)
    }

    /// The link made a radio: `kbit` kbit/s each way (1000 bit/s a kbit, as radios count) (`tc tbf`: a token bucket of one frame, a
    /// queue of 500 ms, as a SiK radio's small buffer) and `loss_pct`% of the packets dropped
    /// each way at random (nftables' `numgen random` on each end's ingress: this kernel has no
    /// `netem`).
    pub fn shape(&self, kbit: f64, loss_pct: u32) {
        let rate = format!("{}bit", (kbit * 1000.0).round() as u64);
        let tbf = ["root", "tbf", "rate", &rate, "burst", "1600", "latency", "500ms"];
        let va = self.veth();
        let vb = format!("{}b", self.ns);
        let mut here = vec!["tc", "qdisc", "replace", "dev", &va];
        here.extend(tbf);
        sh(&here);
        let mut there = vec!["ip", "netns", "exec", &self.ns, "tc", "qdisc", "replace", "dev", &vb];
        there.extend(tbf);
        sh(&there);
        let loss = |prefix: &[&str], dev: &str| {
            let table = format!("radio_{dev}");
            let chain = format!("{{ type filter hook ingress device \"{dev}\" priority 0; }}");
            let rule = format!("numgen random mod 100 < {loss_pct} counter drop");
            for cmd in [
                vec!["add", "table", "netdev", &table],
                vec!["add", "chain", "netdev", &table, "loss", &chain],
                vec!["add", "rule", "netdev", &table, "loss", &rule],
            ] {
                let mut args: Vec<&str> = prefix.to_vec();
                args.push("nft");
                args.extend(cmd);
                sh(&args);
            }
        };
        loss(&[], &va);
        loss(&["ip", "netns", "exec", &self.ns], &vb);
    }

    /// Bytes this side of the link sent and received so far.
    pub fn bytes(&self) -> (u64, u64) {
        let read = |what: &str| -> u64 {
            let p = format!("/sys/class/net/{}/statistics/{what}_bytes", self.veth());
            std::fs::read_to_string(&p)
                .unwrap_or_else(|e| panic!("{p}: {e}"))
                .trim()
                .parse()
                .unwrap()
        };
        (read("tx"), read("rx"))
    }
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = std::process::Command::new("nft")
            .args(["delete", "table", "netdev", &format!("radio_{}", self.veth())])
            .output();
        let _ = std::process::Command::new("ip")
            .args(["netns", "del", &self.ns])
            .output();
        let _ = std::process::Command::new("ip")
            .args(["link", "del", &self.veth()])
            .output();
    }
}

/// Start every vehicle of `mission` with its outbox under `state` and its log in `dir`; the
/// vehicle `away` (if any) runs on another host (`ip netns exec <ns>`) and connects to
/// `endpoint` there. `away` lists such vehicles as (id, namespace, endpoint).
pub fn start_vehicles(
    procs: &mut Procs,
    mission: &std::path::Path,
    state: &str,
    dir: &std::path::Path,
    away: &[(&str, &str, &str)],
) {
    let m = mission.to_str().expect("utf-8 path");
    for v in fleet_mission::config::MissionConfig::load(Some(mission))
        .expect("mission")
        .vehicles()
    {
        let log = dir.join(format!("{}.log", v.id));
        match away.iter().find(|(id, _, _)| *id == v.id) {
            Some((_, ns, endpoint)) => start_vehicle(
                procs,
                &["ip", "netns", "exec", ns],
                &[
                    "--mission",
                    m,
                    "--id",
                    &v.id,
                    "--connect",
                    endpoint,
                    "--state-dir",
                    state,
                ],
                &log,
            ),
            None => start_vehicle(procs, &[], &["--mission", m, "--id", &v.id, "--state-dir", state], &log),
        };
    }
}

/// Start the server (until the mission is done) and every vehicle, those in `away` (id,
/// namespace, endpoint) on their hosts. Returns the processes, the server, and its out and
/// state directories under `dir`.
pub fn start_mission(
    dir: &std::path::Path,
    mission: &std::path::Path,
    away: &[(&str, &str, &str)],
) -> (Procs, Server, std::path::PathBuf, std::path::PathBuf) {
    let (out, state) = (dir.join("out"), dir.join("state"));
    let (m, st) = (mission.to_str().unwrap(), state.to_str().unwrap());
    let mut procs = Procs::default();
    let server = start_server(
        &mut procs,
        &[
            "--mission",
            m,
            "--out",
            out.to_str().unwrap(),
            "--state-dir",
            st,
            "--exit-when-done",
        ],
        &dir.join("server.log"),
    );
    start_vehicles(&mut procs, mission, st, dir, away);
    (procs, server, out, state)
}

/// The journal holds every batch of the mission once; fed to a fresh core in step order it
/// gives the model the server published (to 1e-9 relative).
pub fn check_exactly_once_and_same_model(mission: &std::path::Path, state: &std::path::Path, out: &std::path::Path) {
    let m = fleet_mission::config::MissionConfig::load(Some(mission)).unwrap();
    let truth = m.truth(|_| {}).unwrap().expect("a truth");
    let (grid, frames) = m.workspace(Some(truth.shape())).unwrap();
    let journal = fleet_net::store::Store::open(&state.join(format!("{}.redb", m.mission))).unwrap();
    let mut ctx = fleet_mission::protocol::Context::new(grid);
    ctx.vehicles = m.vehicles().into_iter().map(|v| v.id).collect();
    let mut batches: Vec<_> = journal
        .messages()
        .unwrap()
        .into_iter()
        .map(
            |(_, bytes)| match fleet_mission::protocol::decode(&bytes, &ctx).unwrap() {
                fleet_mission::protocol::Body::Batch(b) => b,
                other => panic!("not a batch: {other:?}"),
            },
        )
        .collect();
    assert_eq!(
        batches.len() as u64,
        expected_batches(&m, frames),
        "every batch in the journal exactly once"
    );
    let order = |id: &str| ctx.vehicles.iter().position(|v| v == id).unwrap();
    batches.sort_by_key(|b| {
        (
            fleet_mission::schedule::Schedule::epoch_of(b.kind, b.seq),
            order(&b.vehicle),
        )
    });
    let mut core = fleet_mission::server::ServerCore::new(&m.team, grid, frames)
        .unwrap()
        .with_boat_speed(m.motion.boat_speed);
    for b in batches {
        core.ingest(b).unwrap();
    }
    assert!(core.finished());
    let offline = core.model_update().unwrap();
    let fleet_mission::protocol::Body::Model(served) =
        fleet_mission::protocol::decode(&std::fs::read(out.join("model.cbor")).unwrap(), &ctx).unwrap()
    else {
        panic!("model.cbor")
    };
    let close = |what: &str, a: &[f64], b: &[f64], tolerance: f64| {
        let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let diff = a.iter().zip(b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        assert!(
            a.len() == b.len() && diff <= tolerance * scale,
            "{what}: differs by {diff:e} (scale {scale:e})"
        );
    };
    close(
        "eigenvalues",
        served.eigenvalues.as_flattened(),
        offline.eigenvalues.as_flattened(),
        1e-9,
    );
    // Each mode times its amplitude: an eigenvector is only defined up to a complex factor
    // (rounding 1e-19 apart can pick another phase), the model it makes is not.
    let scaled = |u: &fleet_mission::protocol::ModelUpdate| -> Vec<f64> {
        let r = u.amplitudes.len();
        let each = |k: usize| {
            let (mr, mi) = (f64::from(u.modes_re[k]), f64::from(u.modes_im[k]));
            let [ar, ai] = u.amplitudes[k % r];
            [mr * ar - mi * ai, mr * ai + mi * ar]
        };
        (0..u.modes_re.len()).flat_map(each).collect()
    };
    // The modes travel as f32: two runs' modes 1e-9 apart may round to neighbouring f32s, one
    // ulp (2^-23 of the value) apart; each product then differs by at most twice that.
    close("modes times amplitudes", &scaled(&served), &scaled(&offline), 2.5e-7);
}

/// A ground station on a UDP port that the gateway sends the fleet to (`gcs =
/// "udpout:127.0.0.1:<port>"`): it reads the stream and answers the gateway.
pub struct GroundStation {
    conn: Box<dyn mavlink::MavConnection<mavlink::dialects::ardupilotmega::MavMessage> + Send + Sync>,
}

impl GroundStation {
    pub fn listen(port: u16) -> Self {
        Self {
            conn: Box::new(
                mavlink::connect::<mavlink::dialects::ardupilotmega::MavMessage>(&format!("udpin:127.0.0.1:{port}"))
                    .expect("a ground-station socket"),
            ),
        }
    }

    /// The next frame (blocks until the gateway sends one).
    pub fn recv(&self) -> (mavlink::MavHeader, mavlink::dialects::ardupilotmega::MavMessage) {
        loop {
            if let Ok(f) = self.conn.recv() {
                return f;
            }
        }
    }

    /// Wait for a HEARTBEAT of `sysid` (so the gateway is the one answered), then set its
    /// mode, as QGroundControl's mode menu does (SET_MODE, sent three times: UDP).
    #[allow(deprecated)]
    pub fn set_mode(&self, sysid: u8, custom_mode: u32) {
        use mavlink::dialects::ardupilotmega::*;
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        loop {
            assert!(std::time::Instant::now() < deadline, "no HEARTBEAT from system {sysid}");
            if let (h, MavMessage::HEARTBEAT(_)) = self.recv() {
                if h.system_id == sysid as u32 {
                    break;
                }
            }
        }
        let m = MavMessage::SET_MODE(SET_MODE_DATA {
            target_system: sysid,
            custom_mode,
            ..Default::default()
        });
        for _ in 0..3 {
            self.conn
                .send(
                    &mavlink::MavHeader {
                        system_id: 255,
                        component_id: 190,
                        sequence: 0,
                    },
                    &m,
                )
                .expect("sending SET_MODE");
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    }
}

/// Processes (other than this one) whose command line contains `needle`.
pub fn pids_with(needle: &str) -> Vec<u32> {
    let me = std::process::id();
    std::fs::read_dir("/proc")
        .expect("/proc")
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&pid| pid != me)
        .filter(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline"))
                .is_ok_and(|c| String::from_utf8_lossy(&c).replace('\0', " ").contains(needle))
        })
        .collect()
}

/// A process's command line, arguments separated by spaces.
pub fn cmdline(pid: u32) -> String {
    std::fs::read(format!("/proc/{pid}/cmdline"))
        .map(|c| String::from_utf8_lossy(&c).replace('\0', " "))
        .unwrap_or_default()
}

/// Wait for `what` to hold, polling (panics after `secs`).
pub fn eventually(secs: u64, what: &str, mut f: impl FnMut() -> bool) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
    while !f() {
        assert!(std::time::Instant::now() < deadline, "{what}: not within {secs} s");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

impl Server {
    /// Wait for the first event `pick` accepts (panics after `secs`).
    pub fn wait_for<T>(&self, secs: u64, what: &str, mut pick: impl FnMut(&ServerEvent) -> Option<T>) -> T {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.events.recv_timeout(left) {
                Ok(e) => {
                    if let Some(t) = pick(&e) {
                        return t;
                    }
                }
                Err(err) => panic!("{what}: not within {secs} s ({err})"),
            }
        }
    }
}

/// `(status, body)` of one plain HTTP/1.0 request to 127.0.0.1 (the live view's tests).
pub fn http(port: u16, method: &str, path: &str) -> Option<(u16, String)> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(std::time::Duration::from_secs(5))).ok()?;
    write!(s, "{method} {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").ok()?;
    let mut bytes = vec![];
    s.read_to_end(&mut bytes).ok()?;
    let text = String::from_utf8_lossy(&bytes);
    let status = text.split_whitespace().nth(1)?.parse().ok()?;
    Some((
        status,
        text.split_once("\r\n\r\n")
            .map_or(String::new(), |(_, b)| b.to_string()),
    ))
}

/// The live view's `/api/state`, once it answers.
pub fn web_state(port: u16) -> Option<serde_json::Value> {
    let (status, body) = http(port, "GET", "/api/state")?;
    (status == 200).then(|| serde_json::from_str(&body).expect("/api/state is JSON"))
}

#[cfg(test)]
mod port_tests {
    use super::free_port;

    /// Ports handed out are distinct, bindable over UDP as over TCP, and below the range the
    /// kernel numbers sockets from, so no socket bound to port 0 can take one meanwhile.
    #[test]
    fn free_ports_are_distinct_and_outside_the_ephemeral_range() {
        let low: u16 = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
            .map(|s| s.split_whitespace().next().unwrap().parse().unwrap())
            .unwrap_or(32768);
        let ports: Vec<u16> = (0..64).map(|_| free_port()).collect();
        let distinct: std::collections::BTreeSet<_> = ports.iter().collect();
        assert_eq!(distinct.len(), ports.len(), "{ports:?}");
        assert!(
            ports.iter().all(|&p| p < low),
            "{ports:?} reach the ephemeral range from {low}"
        );
        assert!(ports
            .iter()
            .all(|&p| std::net::UdpSocket::bind(("127.0.0.1", p)).is_ok()));
    }
}
