//! Readings from instruments that are not the vehicle (issue 34): a whole `fleet up` mission on
//! the clock (`[time]`), boats reading UDP sensor ports or their standard input, aerials
//! reading directories of GeoTIFF frames, fed by a separate process (the instrument emulator)
//! that hears where each vehicle really is from the ground-station stream and sends what a
//! disk-sensing instrument there reads of the truth, or writes what a camera there sees of it.
//! Hostile lines and frames go to the same ports and directories meanwhile. Every reading the
//! emulator sent is in the server's batches, at its step and cell with its value, every aerial
//! value is its frame's, and nothing else is: the model is a function of the batches, so it is
//! the one the good readings alone give. Each hostile line and frame is counted by its kind in
//! the vehicle's telemetry.

use fleet_mission::protocol::{Body, Context};
use fleet_records::recording::Recording;
use hetfleet_tests::*;
use std::collections::BTreeMap;
use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Which vehicle reads which source in a test, and the ports and directories it reads.
struct Feeds {
    /// Boats on UDP sensor ports.
    udp: Vec<(&'static str, u16)>,
    /// A boat on its standard input (piped from the emulator through `fleet up`).
    stdin: Option<&'static str>,
    /// Boats whose sonde sends NAMED_VALUE_FLOAT `SONDE` on the autopilot's companion link.
    mavlink: Vec<&'static str>,
    /// The simulated autopilots' companion ports are this plus their system id.
    companion_base: u16,
    /// Aerials on frame directories `<dir>/av-N`.
    frames: Vec<&'static str>,
}

impl Feeds {
    /// The `[sensors]` table's entries, the frame directories made under `dir`.
    fn sensors(&self, dir: &Path) -> String {
        let mut text = String::new();
        for (id, p) in &self.udp {
            text.push_str(&format!("{id} = \"udp:127.0.0.1:{p}\"\n"));
        }
        if let Some(id) = self.stdin {
            text.push_str(&format!("{id} = \"stdin\"\n"));
        }
        for id in &self.mavlink {
            text.push_str(&format!("{id} = \"mavlink:SONDE\"\n"));
        }
        for id in &self.frames {
            std::fs::create_dir_all(dir.join(id)).unwrap();
            text.push_str(&format!("{id} = \"geotiff:{}\"\n", dir.join(id).display()));
        }
        text
    }
}

/// The tiny mission on the clock (steps of 1 s from `start`), each vehicle on its feed, the
/// ground-station stream on `gcs`.
fn timed_mission(dir: &Path, start: f64, feeds: &Feeds, gcs: u16) -> PathBuf {
    let ep = vec![format!("tcp/127.0.0.1:{}", free_port())];
    let m = tiny_mission(dir, &ep, &ep);
    let mavlink = format!(
        "[mavlink]\ngcs = \"udpout:127.0.0.1:{gcs}\"\nsim_companion_port = {}\n",
        feeds.companion_base
    );
    edit(&m, "[mavlink]\n", &mavlink);
    let start = fleet_mission::instrument::MissionClock::rfc3339(start);
    let mut text = std::fs::read_to_string(&m).unwrap();
    text.push_str(&format!("\n[time]\nstart = \"{start}\"\nstep_s = 1.0\n\n[sensors]\n"));
    text.push_str(&feeds.sensors(dir));
    std::fs::write(&m, text).unwrap();
    m
}

fn udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A base port whose next `n` UDP ports are free now (a simulated autopilot's companion link
/// is the base plus its system id), below the kernel's ephemeral range (32768 up), so no socket
/// bound to port 0 takes one before the autopilots bind them. Tests running at once give
/// different `salt`s (they share the process id the search starts from).
fn companion_base(n: u16, salt: u16) -> u16 {
    let mut candidate = 20_000 + ((std::process::id() as u16 % 5_000) + salt) % 12_000;
    loop {
        let free = (1..=n).all(|i| UdpSocket::bind(("127.0.0.1", candidate + i)).is_ok());
        if free {
            return candidate;
        }
        candidate = 20_000 + (candidate - 20_000 + n + 1) % 12_000;
    }
}

/// Lines of every refusal kind a JSON line can carry, with the kind each must be counted as.
fn hostile(now: f64, site: &fleet_mission::site::Site) -> Vec<(String, &'static str)> {
    let (lat, lon, _) = site.global_of(&site.ned_of((5.5, 5.5), 0.0));
    let r = |t: f64, lat: f64, lon: f64, extra: &str| {
        format!(r#"{{"t": {t}, "lat": {lat}, "lon": {lon}, "value": 0.5{extra}}}"#)
    };
    vec![
        ("{\"t\": 1, garbage".into(), "malformed"),
        ("\u{1}\u{2}\u{7f}binary".into(), "malformed"),
        (r#"{"t": 1, "lat": 0, "lon": 0, "value": "high"}"#.into(), "wrong_type"),
        (r(now, lat, lon, r#", "sigma": -1"#), "bad_sigma"),
        (format!(r#"{{"t": {now}, "value": 0.5}}"#), "no_fix"),
        (r(now, lat + 1.0, lon, ""), "outside_site"),
        (r(now + 3600.0, lat, lon, ""), "from_future"),
        (r(now - 3600.0, lat, lon, ""), "too_old"),
        (format!("{{\"pad\": \"{}\"}}", "x".repeat(60_000)), "oversized"),
    ]
}

/// The instrument emulator for the mission at `m`, feeding `feeds` (`--truth`: the world, when
/// the mission has none; `hostile`: bad MAVLink values too; `faults`: its fault flags, such as
/// `("--fault", "boat-3=bias@25")`); its process, the log of what it sent and its standard
/// output (a `stdin` boat's readings).
fn start_emulator(
    dir: &Path,
    m: &Path,
    feeds: &Feeds,
    gcs: u16,
    truth: Option<&Path>,
    hostile: bool,
    faults: &[(&str, &str)],
) -> (Procs, PathBuf, std::process::ChildStdout) {
    let mission = fleet_mission::config::MissionConfig::load(Some(m)).unwrap();
    let mut emulator = std::process::Command::new(bin("instrument_emulator"));
    let (gcs, log) = (gcs.to_string(), dir.join("sent.ndjson"));
    emulator.args(["--mission", m.to_str().unwrap(), "--gcs-port", &gcs, "--seed", "3"]);
    emulator.arg("--log").arg(&log);
    emulator.args(["--hostile-mavlink", &hostile.to_string()]);
    for (id, p) in &feeds.udp {
        emulator.args(["--send", &format!("{id}=127.0.0.1:{p}")]);
    }
    if let Some(id) = feeds.stdin {
        emulator.args(["--send", &format!("{id}=-")]);
    }
    for id in &feeds.mavlink {
        let port = feeds.companion_base + mission.sysid(id).unwrap() as u16;
        emulator.args(["--mavlink", &format!("{id}={port}")]);
    }
    for id in &feeds.frames {
        emulator.args(["--frames", &format!("{id}={}", dir.join(id).display())]);
    }
    if let Some(t) = truth {
        emulator.arg("--truth").arg(t);
    }
    for (flag, value) in faults {
        emulator.args([flag, value]);
    }
    let mut child = emulator
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("the emulator");
    let stdout = child.stdout.take().expect("piped");
    (Procs(vec![child]), log, stdout)
}

/// `fleet up` on `m` into `out`, in a thread, its standard input (which its nodes inherit:
/// a `stdin` boat reads it) from `stdin`.
fn fleet_up(m: &Path, out: &Path, stdin: std::process::ChildStdout) -> std::thread::JoinHandle<std::process::Output> {
    let mut c = std::process::Command::new(bin("fleet"));
    c.args(["up", m.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .current_dir(root())
        .stdin(stdin);
    std::thread::spawn(move || c.output().expect("running fleet up"))
}

/// Hostile lines to `port` at ten times the rate the emulator sends `normal_per_s` good ones,
/// for `seconds`, in a thread; the kinds it sent, counted.
fn flood(
    port: u16,
    site: fleet_mission::site::Site,
    normal_per_s: f64,
    seconds: f64,
) -> std::thread::JoinHandle<BTreeMap<String, u64>> {
    std::thread::spawn(move || {
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        let (mut sent, mut i) = (BTreeMap::new(), 0usize);
        let every = std::time::Duration::from_secs_f64(1.0 / (10.0 * normal_per_s));
        let until = std::time::Instant::now() + std::time::Duration::from_secs_f64(seconds);
        let mut next = std::time::Instant::now();
        while next < until {
            let lines = hostile(fleet_mission::instrument::MissionClock::now(), &site);
            let (line, kind) = &lines[i % lines.len()];
            socket
                .send_to(format!("{line}\n").as_bytes(), ("127.0.0.1", port))
                .unwrap();
            *sent.entry(kind.to_string()).or_default() += 1;
            i += 1;
            next += every;
            std::thread::sleep(next.saturating_duration_since(std::time::Instant::now()));
        }
        sent
    })
}

/// The highest resident memory (kB) of the vehicle node `id` of the run into `out`, sampled
/// every 200 ms until `stop` (0 if it was never found).
fn peak_rss(out: &Path, id: &'static str, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    let needle = out.to_string_lossy().to_string();
    std::thread::spawn(move || {
        let mut peak = 0;
        while !stop.load(Ordering::Relaxed) {
            for p in std::fs::read_dir("/proc").unwrap().flatten() {
                let cmd = std::fs::read(p.path().join("cmdline")).unwrap_or_default();
                let args: Vec<String> = cmd
                    .split(|&b| b == 0)
                    .map(|a| String::from_utf8_lossy(a).to_string())
                    .collect();
                let ours = args.first().is_some_and(|a| a.ends_with("/vehicle"))
                    && args.iter().any(|a| a.starts_with(&needle))
                    && args.windows(2).any(|w| w[0] == "--id" && w[1] == id);
                if !ours {
                    continue;
                }
                let status = std::fs::read_to_string(p.path().join("status")).unwrap_or_default();
                let rss = status
                    .lines()
                    .find_map(|l| l.strip_prefix("VmRSS:"))
                    .and_then(|v| v.split_whitespace().next()?.parse().ok())
                    .unwrap_or(0);
                peak = peak.max(rss);
            }
            std::thread::sleep(std::time::Duration::from_millis(200));
        }
        peak
    })
}

#[test]
fn an_outside_instrument_feeds_the_boats_and_hostile_lines_are_counted_not_used() {
    let dir = scratch("instruments");
    let feeds = Feeds {
        udp: vec![("boat-1", udp_port())],
        stdin: Some("boat-3"),
        mavlink: vec!["boat-2"],
        companion_base: companion_base(5, 0),
        frames: vec!["av-1", "av-2"],
    };
    let gcs = udp_port();
    let start = fleet_mission::instrument::MissionClock::now().ceil() + 12.0;
    let m = timed_mission(&dir, start, &feeds, gcs);
    // boat-1's probe sticks from step 25, and boat-3's (through its standard input) reads 3
    // noise standard deviations high from then on: the server's health tests must find both.
    // av-2's frame of step 20 is cloud throughout: a frame that saw nothing.
    let faults = [
        ("--stuck", "boat-1=25"),
        ("--fault", "boat-3=bias@25"),
        ("--cloudy", "av-2=20"),
    ];
    let (mut procs, log, stdout) = start_emulator(&dir, &m, &feeds, gcs, None, true, &faults);
    let out = dir.join("run");
    let stop = Arc::new(AtomicBool::new(false));
    let rss = [
        peak_rss(&out, "boat-1", stop.clone()),
        peak_rss(&out, "boat-3", stop.clone()),
    ];
    let fleet = fleet_up(&m, &out, stdout);
    // A flood of hostile lines to boat-1 at ten times its instrument's rate, for 30 s from step 2.
    let mission = fleet_mission::config::MissionConfig::load(Some(&m)).unwrap();
    let clock = mission.clock().unwrap();
    let grid = fleet_math::grid::Grid::new(24, 48, 1.0).unwrap();
    let disk = grid.disk(grid.cell(grid.len() / 2), mission.team.radius).len() as f64;
    let normal_per_s = disk / (mission.team.boat_period as f64 * clock.step_s);
    while fleet_mission::instrument::MissionClock::now() < clock.time_of(2) {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let flooding = flood(feeds.udp[0].1, mission.mavlink.site(&grid), normal_per_s, 30.0);
    while fleet_mission::instrument::MissionClock::now() < clock.time_of(11) {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    // And to av-1's camera directory: a file that is not a TIFF, one without a time, and
    // a frame from an hour ago (renamed in whole, as a camera pipeline does).
    let frames = dir.join("av-1");
    std::fs::write(dir.join("junk"), b"not a tiff at all").unwrap();
    std::fs::rename(dir.join("junk"), frames.join("junk.tif")).unwrap();
    let first = std::fs::read_dir(&frames)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.to_string_lossy().contains("frame_"))
        .expect("a frame written by the emulator");
    let bytes = std::fs::read(&first).unwrap();
    let frame = fleet_mission::instrument::raster::decode(&bytes).unwrap();
    let stale = fleet_mission::instrument::MissionClock::rfc3339(frame.time.unwrap() - 3600.0).replace(['-', ':'], "");
    let timeless = bytes_without_datetime(&bytes);
    std::fs::write(dir.join("a"), &timeless).unwrap();
    std::fs::rename(dir.join("a"), frames.join("no-time.tif")).unwrap();
    std::fs::write(dir.join("b"), &timeless).unwrap();
    std::fs::rename(dir.join("b"), frames.join(format!("old_{stale}.tif"))).unwrap();
    let want_av1: BTreeMap<String, u64> = [("malformed".to_string(), 2), ("too_old".to_string(), 1)].into();
    let want_boat2: BTreeMap<String, u64> = [("from_future".to_string(), 1), ("not_finite".to_string(), 1)].into();
    let want = flooding.join().unwrap();
    let flooded: u64 = want.values().sum();
    assert!(flooded as f64 >= 0.9 * 300.0 * normal_per_s, "{flooded} lines in 30 s");
    let o = fleet.join().unwrap();
    assert!(o.status.success(), "fleet up: {}", String::from_utf8_lossy(&o.stderr));
    stop.store(true, Ordering::Relaxed);
    let [flooded_kb, quiet_kb] = rss.map(|t| t.join().unwrap());
    // What a flood can make the node hold is its queue (1024 lines of at most 4 kB) and one
    // datagram: within 16 MB of the boat that was not flooded.
    assert!(
        quiet_kb > 0 && flooded_kb <= quiet_kb + 16 * 1024,
        "boat-1 peaked at {flooded_kb} kB, boat-3 at {quiet_kb} kB"
    );
    procs.wait_all(30);

    // What the emulator sent, by (vehicle, step, cell).
    let sent: BTreeMap<(String, u64, u32), f64> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let key = (
                v["vehicle"].as_str().unwrap().to_string(),
                v["step"].as_u64().unwrap(),
                v["cell"].as_u64().unwrap() as u32,
            );
            (key, v["value"].as_f64().unwrap())
        })
        .collect();
    assert!(sent.len() >= 2 * 5 * 20, "the emulator sent {} readings", sent.len());
    let rec = Recording::read(&out.join("recording.mcap")).unwrap();
    let mut ctx = Context::new(rec.grid);
    ctx.vehicles = rec.mission.vehicles().into_iter().map(|v| v.id).collect();
    let (mut received, mut last_counts, mut av1_counts, mut boat2_counts) = (BTreeMap::new(), None, None, None);
    let (mut aerial_values, mut status) = (0, None);
    for msg in &rec.messages {
        match fleet_mission::protocol::decode(&msg.data, &ctx) {
            Ok(Body::Batch(b)) if b.kind == fleet_mission::protocol::VehicleKind::Boat => {
                for s in &b.samples {
                    assert!(s.sigma.is_some(), "an instrument's sample carries its sigma");
                    for (&c, &v) in s.cells.iter().zip(&s.values) {
                        received.insert((b.vehicle.to_string(), s.step, c), v);
                    }
                }
            }
            Ok(Body::Batch(b)) => {
                for s in &b.samples {
                    let f = frame_at(&dir.join(b.vehicle.as_str()), s.step, &mission, &rec.grid);
                    for (&c, &v) in s.cells.iter().zip(&s.values) {
                        // The vehicle's cell mean is (w v) / w: the value to a rounding or two.
                        let want = f[c as usize].expect("a value where the frame has one");
                        assert!(
                            (v - want).abs() <= 1e-12 * want.abs().max(1.0),
                            "{} step {}: {v}",
                            b.vehicle,
                            s.step
                        );
                        aerial_values += 1;
                    }
                }
            }
            Ok(Body::Telemetry(t)) if t.vehicle.as_str() == "boat-1" => last_counts = t.readings.or(last_counts),
            Ok(Body::Telemetry(t)) if t.vehicle.as_str() == "av-1" => av1_counts = t.readings.or(av1_counts),
            Ok(Body::Telemetry(t)) if t.vehicle.as_str() == "boat-2" => boat2_counts = t.readings.or(boat2_counts),
            Ok(Body::Status(s)) => status = Some(s),
            _ => {}
        }
    }
    assert_eq!(
        received.keys().collect::<Vec<_>>(),
        sent.keys().collect::<Vec<_>>(),
        "every reading sent, and nothing else, is in the batches"
    );
    for (k, v) in &received {
        assert!(
            (v - sent[k]).abs() <= 1e-12 * v.abs().max(1.0),
            "{k:?}: {v} != {}",
            sent[k]
        );
    }
    let counts = last_counts.expect("boat-1's telemetry carries its reading counts");
    assert_eq!(counts.refused, want, "each hostile line counted by its kind");
    let status = status.expect("the server's status");
    assert_eq!(status.readings["boat-1"].refused, want, "and in the server's status");
    assert!(aerial_values >= 2 * 40 * 10, "aerial values checked: {aerial_values}");
    let av1 = av1_counts.expect("av-1's telemetry carries its reading counts");
    assert_eq!(av1.refused, want_av1, "each hostile frame counted by its kind");
    // av-2's cloudy frame: taken, counted as a frame with no value, said in the report.
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let empty = |id: &str| summary["readings"][id]["empty_frames"].as_u64().unwrap_or(0);
    assert_eq!((empty("av-1"), empty("av-2")), (0, 1), "{}", summary["readings"]);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("Frames with no value at any cell (no-data throughout, or off the site): av-2 1."),
        "{report}"
    );
    // To the server a frame that saw nothing is a camera that said nothing: suspect (silent) at
    // its step, ok again after clean steps, and never excluded.
    let av2: Vec<(u64, String)> = (verdicts(&out).iter())
        .filter(|v| v["vehicle"] == "av-2")
        .map(|v| (v["step"].as_u64().unwrap(), v["to"].as_str().unwrap().to_string()))
        .collect();
    assert!(
        matches!(&av2[..], [(20, a), (_, b)] if a == "suspect" && b == "ok"),
        "{av2:?}"
    );
    let boat2 = boat2_counts.expect("boat-2's telemetry carries its reading counts");
    assert_eq!(
        boat2.refused, want_boat2,
        "each hostile MAVLink value counted by its kind"
    );
    let good = |id: &str| sent.keys().filter(|(v, _, _)| v == id).count() as u64;
    assert_eq!(counts.accepted, good("boat-1"));
    assert_eq!(counts.received, good("boat-1") + flooded);
    assert_eq!(boat2.accepted, good("boat-2"));
    assert!(good("boat-2") >= 5, "boat-2's sonde sent {} values", good("boat-2"));
    stuck_probe_is_excluded(&out, "boat-1", 25, &["boat-3", "av-2"]);
    biased_probe_is_marked(&out, "boat-3", 25);
    // And the ground station heard it from the gateway, under boat-1's system id.
    let sysid = mission.sysid("boat-1").unwrap() as u64;
    let said = std::fs::read_to_string(log.with_extension("statustext")).unwrap();
    assert!(
        said.lines().any(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            v["system"] == sysid && v["text"].as_str().unwrap().starts_with("Sensor excluded: stuck")
        }),
        "no STATUSTEXT for boat-1 (system {sysid}): {said}"
    );
    same_model_offline(&out, &dir.join("offline"));
    eprintln!(
        "flood: {flooded} hostile lines in 30 s; peak memory boat-1 {flooded_kb} kB, boat-3 {quiet_kb} kB; boat-2's \
         sonde: {} values over MAVLink",
        good("boat-2")
    );
}

/// The sensor verdicts of the run in `out` (its summary's).
fn verdicts(out: &Path) -> Vec<serde_json::Value> {
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    summary["sensor_verdicts"]
        .as_array()
        .expect("sensor verdicts in the summary")
        .clone()
}

/// The biased probe of `id` (3 noise standard deviations high from step `from`, sent through
/// its instrument's interface) is marked for its bias, after the fault began. How soon depends
/// on how many aerial lattice cells its disk holds where the boat really went (the bias test
/// compares the two at the same cells), so the test asks only that it is found; the fault
/// study measures how soon, over seeds.
fn biased_probe_is_marked(out: &Path, id: &str, from: u64) {
    let verdicts = verdicts(out);
    let first = verdicts
        .iter()
        .find(|v| v["vehicle"] == id && v["to"] != "ok")
        .unwrap_or_else(|| panic!("{id}'s bias was never found: {verdicts:?}"));
    assert!(first["step"].as_u64().unwrap() >= from, "{first}");
    assert!(first["reason"].as_str().unwrap().starts_with("biased"), "{first}");
    eprintln!(
        "{id}'s bias from step {from} found at step {}: {}",
        first["step"], first["reason"]
    );
}

/// The stuck probe of `id` (from step `from`, sent through its instrument's interface) is
/// excluded at its first sampling step after, once, with the reason: in the summary, as a
/// `sensor` event, and in the mission report; no other sensor is marked but those `failing` too.
fn stuck_probe_is_excluded(out: &Path, id: &str, from: u64, failing: &[&str]) {
    let verdicts = verdicts(out);
    let others = |v: &serde_json::Value| failing.iter().any(|f| v["vehicle"] == *f);
    let excluded: Vec<&serde_json::Value> = verdicts
        .iter()
        .filter(|v| v["to"] == "excluded" && !others(v))
        .collect();
    assert_eq!(excluded.len(), 1, "{verdicts:?}");
    let v = excluded[0];
    assert_eq!(v["vehicle"], id, "{v}");
    assert!(
        v["step"].as_u64().unwrap() >= from && v["step"].as_u64().unwrap() < from + 10,
        "{v}"
    );
    assert!(v["reason"].as_str().unwrap().starts_with("stuck"), "{v}");
    assert!(
        verdicts.iter().all(|v| v["vehicle"] == id || others(v)),
        "a healthy sensor was marked: {verdicts:?}"
    );
    let events = std::fs::read_to_string(out.join("events.jsonl")).unwrap();
    assert!(
        events
            .lines()
            .any(|l| l.contains("\"event\":\"sensor\"") && l.contains(id) && l.contains("excluded")),
        "no sensor event for {id}"
    );
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("## Sensor health") && report.contains("stuck"),
        "the report says so"
    );
    // The vehicle hears it in its acks, logs it, and says it in its telemetry.
    let log = std::fs::read_to_string(out.join(format!("logs/{id}.log"))).unwrap();
    assert!(
        log.lines()
            .any(|l| l.contains("the server doubts this vehicle's sensor") && l.contains("excluded")),
        "{id}'s log does not say its sensor was excluded"
    );
}

/// `fleet assimilate` on the readings the live run into `out` logged makes its model again, byte
/// for byte (the final model, and the estimate and variance at every step).
fn same_model_offline(out: &Path, offline: &Path) {
    let o = run(
        "fleet",
        &[
            "assimilate",
            out.join("mission.toml").to_str().unwrap(),
            "--readings",
            out.join("readings.ndjson").to_str().unwrap(),
            "--out",
            offline.to_str().unwrap(),
        ],
    );
    assert!(
        o.status.success(),
        "fleet assimilate: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    for f in ["model.cbor", "estimate.npy", "variance.npy", "plans.json"] {
        let (live, again) = (
            std::fs::read(out.join(f)).unwrap(),
            std::fs::read(offline.join(f)).unwrap(),
        );
        assert!(live == again, "{f}: the offline run's differs from the live run's");
    }
    assert!(offline.join("estimate.nc").is_file());
}

/// The frame the emulator wrote for `step` in `dir`, on the model grid.
fn frame_at(
    dir: &Path,
    step: u64,
    mission: &fleet_mission::config::MissionConfig,
    grid: &fleet_math::grid::Grid,
) -> Vec<Option<f64>> {
    let clock = mission.clock().unwrap();
    let stamp = fleet_mission::instrument::MissionClock::rfc3339(clock.time_of(step)).replace(['-', ':'], "");
    let bytes = std::fs::read(dir.join(format!("frame_{stamp}.tif"))).unwrap();
    let f = fleet_mission::instrument::raster::decode(&bytes).unwrap();
    f.resample(&mission.mavlink.site(grid), grid)
}

/// A TIFF with its DateTime's digits blanked (same length, no longer a date).
fn bytes_without_datetime(bytes: &[u8]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    let at = out
        .windows(5)
        .position(|w| w.starts_with(b"20") && w[4] == b':')
        .expect("a DateTime");
    out[at..at + 19].copy_from_slice(b"not a date at all..");
    out
}

/// `config/mission-field.toml`, the real-site template (a QGroundControl plan's geofence, UTC
/// start, no truth), moved to this test's clock (steps of 1 s from `start`, `frames` long), ports
/// and directories, its autopilots simulated (`sim`, 100 times faster, with companion links).
fn field_mission(dir: &Path, start: f64, frames: usize, feeds: &Feeds, gcs: u16) -> PathBuf {
    std::fs::copy(root().join("config/field-site.plan"), dir.join("field-site.plan")).unwrap();
    let m = dir.join("mission.toml");
    std::fs::copy(root().join("config/mission-field.toml"), &m).unwrap();
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let start = fleet_mission::instrument::MissionClock::rfc3339(start);
    for (from, to) in [
        (
            "start = \"2026-12-01T08:00:00Z\"".to_string(),
            format!("start = \"{start}\""),
        ),
        ("step_s = 60.0".into(), "step_s = 1.0".into()),
        ("frames = 480".into(), format!("frames = {frames}")),
        ("tcp/0.0.0.0:7447".into(), ep.clone()),
        ("tcp/192.168.1.10:7447".into(), ep),
        (
            "autopilot = \"serial:/dev/ttyACM0:115200\"".into(),
            format!(
                "autopilot = \"sim\"\nsim_speedup = 100.0\nsim_companion_port = {}",
                feeds.companion_base
            ),
        ),
        ("udpout:127.0.0.1:14550".into(), format!("udpout:127.0.0.1:{gcs}")),
    ] {
        edit(&m, &from, &to);
    }
    let text = std::fs::read_to_string(&m).unwrap();
    let (a, b) = (text.find("[sensors]").unwrap(), text.find("[mavlink]").unwrap());
    let sensors = format!("[sensors]\n{}\n", feeds.sensors(dir));
    std::fs::write(&m, format!("{}{sensors}{}", &text[..a], &text[b..])).unwrap();
    m
}

/// The real-site mission (`config/mission-field.toml`: a QGroundControl plan's boundary, UTC
/// start, no truth), end to end on emulated instruments of every point kind (UDP, MAVLink) and
/// cameras: every node runs without a truth file, the world is a field the test keeps aside
/// (given only to the emulator), and the run is scored by the boats' held-out readings. Their
/// mean squared difference less the readings' noise estimates the estimate's true MSE at those
/// cells without bias; it is checked against the true one (from the field kept aside) within 4
/// standard deviations of that estimator, `sqrt((4 mse noise + 2 noise^2) / n)` for Gaussian
/// noise.
#[test]
fn the_real_site_mission_runs_without_a_truth_and_is_scored_by_held_out_readings() {
    let dir = scratch("field");
    let tiny = fleet_mission::config::MissionConfig::load(Some(&root().join("config/mission-tiny.toml"))).unwrap();
    let world = tiny.truth(|_| {}).unwrap().expect("a truth");
    let world_path = dir.join("world.npy");
    fleet_math::process::dataset::save(&world_path, &world, None).unwrap();
    let feeds = Feeds {
        udp: vec![("boat-1", udp_port()), ("boat-3", udp_port())],
        stdin: None,
        mavlink: vec!["boat-2"],
        companion_base: companion_base(5, 6_000),
        frames: vec!["av-1", "av-2"],
    };
    let gcs = udp_port();
    let start = fleet_mission::instrument::MissionClock::now().ceil() + 12.0;
    let m = field_mission(&dir, start, world.frames(), &feeds, gcs);
    let mission = fleet_mission::config::MissionConfig::load(Some(&m)).unwrap();
    assert!(
        mission.truth.is_none() && mission.team.fence.is_some(),
        "no truth, a fence from the plan"
    );
    let (mut procs, log, stdout) = start_emulator(&dir, &m, &feeds, gcs, Some(&world_path), false, &[]);
    let out = dir.join("run");
    let o = fleet_up(&m, &out, stdout).join().unwrap();
    assert!(o.status.success(), "fleet up: {}", String::from_utf8_lossy(&o.stderr));
    procs.wait_all(30);
    assert!(!out.join("truth.npy").exists(), "no truth is made or written");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("## Held-out readings")
            && report.contains("## Innovations")
            && !report.contains("offline loop"),
        "{report}"
    );
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert!(
        summary["mse"].as_array().unwrap().is_empty(),
        "nothing is scored against a truth"
    );
    let epochs = summary["innovations"]
        .as_array()
        .expect("the boats' innovations per epoch")
        .len();
    assert!(epochs >= 5, "{epochs} epochs with innovations");
    let h = &summary["holdout"];
    let (n, mse, noise) = (
        h["readings"].as_u64().unwrap(),
        h["mse"].as_f64().unwrap(),
        h["noise_var"].as_f64().unwrap(),
    );

    // The true error at the held-out cells, from the field kept aside.
    let est = fleet_math::process::dataset::load(out.join("estimate.npy"), 1.0).unwrap();
    // (A disk instrument's reading whose cell lies outside the fence is refused: not scored.)
    let grid = fleet_math::grid::Grid::new(world.rows, world.cols, 1.0).unwrap();
    let (site, fence) = (mission.mavlink.site(&grid), mission.team.fence.clone().unwrap());
    let fenced = |c: u64| {
        let ned = site.ned_of(grid.centre_m(grid.cell(c as usize)), 0.0);
        fleet_mission::fence::inside(&fence.polygon_m, [ned.y, ned.x])
    };
    let held: Vec<(usize, usize)> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| (v["step"].as_u64().unwrap(), v["cell"].as_u64().unwrap()))
        .filter(|&(_, c)| fenced(c))
        .filter(|&(k, c)| fleet_mission::holdout::is_held(k, c as u32, fleet_mission::holdout::DEFAULT_SHARE))
        .map(|(k, c)| (k as usize, c as usize))
        .collect();
    assert_eq!(
        held.len() as u64,
        n,
        "every held-out reading the emulator sent was scored"
    );
    assert!(n >= 20, "{n} readings held out");
    eprintln!("held out: {n} readings");
    // The truth-free check by place: every held-out reading in one decile of reported variance.
    let deciles = h["by_decile"].as_array().expect("the held-out readings by decile");
    let in_deciles: u64 = deciles.iter().map(|d| d["readings"].as_u64().unwrap()).sum();
    assert_eq!((deciles.len(), in_deciles), (10, n), "{h}");
    assert!(h["ence"].as_f64().is_some_and(f64::is_finite), "{h}");
    assert!(
        report.contains("By decile of the variance the estimate reported"),
        "{report}"
    );
    let truth_mse = held
        .iter()
        .map(|&(k, c)| (est.snapshots[(c, k)] - world.snapshots[(c, k)]).powi(2))
        .sum::<f64>()
        / n as f64;
    let sd = ((4.0 * truth_mse * noise + 2.0 * noise * noise) / n as f64).sqrt();
    assert!(
        (mse - noise - truth_mse).abs() <= 4.0 * sd,
        "held-out {:.3e} vs true {truth_mse:.3e} (sd {sd:.1e})",
        mse - noise
    );
}
