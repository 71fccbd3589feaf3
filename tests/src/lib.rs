//! Helpers for the cross-process tests: where the workspace's binaries and reference data are.

use std::path::PathBuf;
use std::process::{Command, Output};

/// The workspace root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
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
        .unwrap_or_else(|e| panic!("cannot start {}: {e} (build it with `cargo build --release --workspace`)", path.display()))
}

/// A scratch directory for one test (removed and made afresh).
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("hetfleet-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch dir");
    d
}

/// A TCP port nobody listens on now.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).expect("a free port").port()
}

/// `config/mission-tiny.toml` with its endpoints replaced, written into `dir`.
pub fn tiny_mission(dir: &std::path::Path, listen: &[String], connect: &[String]) -> PathBuf {
    let text = std::fs::read_to_string(root().join("config/mission-tiny.toml")).expect("the tiny mission");
    let list = |v: &[String]| format!("[{}]", v.iter().map(|e| format!("{e:?}")).collect::<Vec<_>>().join(", "));
    let text = text
        .replace(r#"listen = ["tcp/127.0.0.1:7461"]"#, &format!("listen = {}", list(listen)))
        .replace(r#"connect = ["tcp/127.0.0.1:7461"]"#, &format!("connect = {}", list(connect)));
    let path = dir.join("mission.toml");
    std::fs::write(&path, text).expect("writing the mission");
    path
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
    pub events: std::sync::mpsc::Receiver<fleet::mission::report::ServerEvent>,
}

/// Start `model-server` with `args` (plus `--events`), stderr to `log`.
pub fn start_server(procs: &mut Procs, args: &[&str], log: &std::path::Path) -> Server {
    use std::io::BufRead;
    let mut child = Command::new(bin("model-server"))
        .args(args)
        .arg("--events")
        .current_dir(root())
        .stdout(std::process::Stdio::piped())
        .stderr(std::fs::File::create(log).expect("server log"))
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
    Server { events: rx }
}

impl Server {
    /// Wait for the mission's summary (panics after `secs`).
    pub fn finished(&self, secs: u64) -> fleet::mission::report::ServerSummary {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.events.recv_timeout(left) {
                Ok(fleet::mission::report::ServerEvent::Finished { summary }) => return *summary,
                Ok(_) => {}
                Err(e) => panic!("the mission did not finish in {secs} s: {e}"),
            }
        }
    }
}

/// Start a vehicle node: `prefix` runs it under another command (e.g. `ip netns exec ns`).
pub fn start_vehicle(procs: &mut Procs, prefix: &[&str], args: &[&str], log: &std::path::Path) {
    let mut cmd = match prefix.split_first() {
        Some((p, rest)) => {
            let mut c = Command::new(p);
            c.args(rest).arg(bin("vehicle"));
            c
        }
        None => Command::new(bin("vehicle")),
    };
    let child = cmd.args(args).current_dir(root()).stderr(std::fs::File::create(log).expect("vehicle log")).spawn().expect("starting a vehicle");
    procs.0.push(child);
}
