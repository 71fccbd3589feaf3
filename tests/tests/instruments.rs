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

use fleet::protocol::{Body, Context};
use fleet_mission::recording::Recording;
use hetfleet_tests::*;
use std::collections::BTreeMap;
use std::net::UdpSocket;
use std::path::{Path, PathBuf};

/// The tiny mission on the clock (steps of 1 s from `start`), boat-1 and boat-2 on UDP ports,
/// boat-3 on its standard input, the aerials on frame directories `<dir>/av-N`, the
/// ground-station stream on `gcs`.
fn timed_mission(dir: &Path, start: f64, ports: &[u16], gcs: u16) -> std::path::PathBuf {
    let ep = vec![format!("tcp/127.0.0.1:{}", free_port())];
    let m = tiny_mission(dir, &ep, &ep);
    edit(
        &m,
        "[mavlink]\n",
        &format!("[mavlink]\ngcs = \"udpout:127.0.0.1:{gcs}\"\n"),
    );
    let start = fleet_mission::instrument::MissionClock::rfc3339(start);
    let mut text = std::fs::read_to_string(&m).unwrap();
    text.push_str(&format!("\n[time]\nstart = \"{start}\"\nstep_s = 1.0\n\n[sensors]\n"));
    for (i, p) in ports.iter().enumerate() {
        text.push_str(&format!("boat-{} = \"udp:127.0.0.1:{p}\"\n", i + 1));
    }
    text.push_str("boat-3 = \"stdin\"\n");
    for id in ["av-1", "av-2"] {
        let frames = dir.join(id);
        std::fs::create_dir_all(&frames).unwrap();
        text.push_str(&format!("{id} = \"geotiff:{}\"\n", frames.display()));
    }
    std::fs::write(&m, text).unwrap();
    m
}

fn udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
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

/// The instrument emulator for the mission at `m` (`--truth`: the world, when the mission has
/// none), boat-3's readings on its standard output; its process, the log of what it sent and
/// that output.
fn start_emulator(
    dir: &Path,
    m: &Path,
    ports: &[u16],
    gcs: u16,
    truth: Option<&Path>,
) -> (Procs, PathBuf, std::process::ChildStdout) {
    let mut emulator = std::process::Command::new(bin("instrument_emulator"));
    let (gcs, log) = (gcs.to_string(), dir.join("sent.ndjson"));
    emulator.args(["--mission", m.to_str().unwrap(), "--gcs-port", &gcs, "--seed", "3"]);
    emulator.arg("--log").arg(&log).args(["--send", "boat-3=-"]);
    for (i, p) in ports.iter().enumerate() {
        emulator.args(["--send", &format!("boat-{}=127.0.0.1:{p}", i + 1)]);
    }
    for id in ["av-1", "av-2"] {
        emulator.args(["--frames", &format!("{id}={}", dir.join(id).display())]);
    }
    if let Some(t) = truth {
        emulator.arg("--truth").arg(t);
    }
    let mut child = emulator
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("the emulator");
    let stdout = child.stdout.take().expect("piped");
    (Procs(vec![child]), log, stdout)
}

/// `fleet up` on `m` into `out`, in a thread, its standard input (which its nodes inherit:
/// boat-3 reads it) from `stdin`.
fn fleet_up(m: &Path, out: &Path, stdin: std::process::ChildStdout) -> std::thread::JoinHandle<std::process::Output> {
    let mut c = std::process::Command::new(bin("fleet"));
    c.args(["up", m.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .current_dir(root())
        .stdin(stdin);
    std::thread::spawn(move || c.output().expect("running fleet up"))
}

#[test]
fn an_outside_instrument_feeds_the_boats_and_hostile_lines_are_counted_not_used() {
    let dir = scratch("instruments");
    let ports = [udp_port(), udp_port()];
    let gcs = udp_port();
    let m = timed_mission(
        &dir,
        fleet_mission::instrument::MissionClock::now().ceil() + 12.0,
        &ports,
        gcs,
    );
    let (mut procs, log, stdout) = start_emulator(&dir, &m, &ports, gcs, None);
    let out = dir.join("run");
    let fleet = fleet_up(&m, &out, stdout);
    // Hostile lines to boat-1 while the mission runs (once the first boat epoch is open).
    let mission = fleet_mission::config::MissionConfig::load(Some(&m)).unwrap();
    let clock = mission.clock().unwrap();
    while fleet_mission::instrument::MissionClock::now() < clock.time_of(11) {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let grid = fleet::grid::Grid::new(24, 48, 1.0).unwrap();
    let lines = hostile(
        fleet_mission::instrument::MissionClock::now(),
        &mission.mavlink.site(&grid),
    );
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut want: BTreeMap<String, u64> = BTreeMap::new();
    for (line, kind) in &lines {
        socket
            .send_to(format!("{line}\n").as_bytes(), ("127.0.0.1", ports[0]))
            .unwrap();
        *want.entry(kind.to_string()).or_default() += 1;
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
    let o = fleet.join().unwrap();
    assert!(o.status.success(), "fleet up: {}", String::from_utf8_lossy(&o.stderr));
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
    assert!(sent.len() >= 3 * 5 * 20, "the emulator sent {} readings", sent.len());
    let rec = Recording::read(&out.join("recording.mcap")).unwrap();
    let mut ctx = Context::new(rec.grid);
    ctx.vehicles = rec.mission.vehicles().into_iter().map(|v| v.id).collect();
    let (mut received, mut last_counts, mut av1_counts) = (BTreeMap::new(), None, None);
    let (mut aerial_values, mut status) = (0, None);
    for msg in &rec.messages {
        match fleet::protocol::decode(&msg.data, &ctx) {
            Ok(Body::Batch(b)) if b.kind == fleet::protocol::VehicleKind::Boat => {
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
    let good = sent.keys().filter(|(id, _, _)| id == "boat-1").count() as u64;
    assert_eq!(counts.accepted, good);
    assert_eq!(counts.received, good + lines.len() as u64);
}

/// The frame the emulator wrote for `step` in `dir`, on the model grid.
fn frame_at(
    dir: &Path,
    step: u64,
    mission: &fleet_mission::config::MissionConfig,
    grid: &fleet::grid::Grid,
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

/// A mission without a truth (`[field]` sizes the grid): every node runs without a truth file,
/// the world is a field the test keeps aside (given only to the emulator), and the run is
/// scored by the boats' held-out readings. Their mean squared difference less the readings'
/// noise estimates the estimate's true MSE at those cells without bias; it is checked against
/// the true one (from the field kept aside) within 4 standard deviations of that estimator,
/// `sqrt((4 mse noise + 2 noise^2) / n)` for Gaussian noise.
#[test]
fn a_mission_without_a_truth_runs_on_instruments_and_is_scored_by_held_out_readings() {
    let dir = scratch("no-truth");
    let tiny = fleet_mission::config::MissionConfig::load(Some(&root().join("config/mission-tiny.toml"))).unwrap();
    let world = tiny.truth(|_| {}).unwrap().expect("a truth");
    let world_path = dir.join("world.npy");
    fleet::process::dataset::save(&world_path, &world, None).unwrap();
    let ports = [udp_port(), udp_port()];
    let gcs = udp_port();
    let m = timed_mission(
        &dir,
        fleet_mission::instrument::MissionClock::now().ceil() + 12.0,
        &ports,
        gcs,
    );
    let text = std::fs::read_to_string(&m).unwrap();
    let (a, b) = (text.find("[truth]").unwrap(), text.find("[team]").unwrap());
    let field = format!(
        "[field]\ngrid = [{}, {}]\nframes = {}\n\n",
        world.rows,
        world.cols,
        world.frames()
    );
    std::fs::write(&m, format!("{}{field}{}", &text[..a], &text[b..])).unwrap();
    let (mut procs, log, stdout) = start_emulator(&dir, &m, &ports, gcs, Some(&world_path));
    let out = dir.join("run");
    let o = fleet_up(&m, &out, stdout).join().unwrap();
    assert!(o.status.success(), "fleet up: {}", String::from_utf8_lossy(&o.stderr));
    procs.wait_all(30);
    assert!(!out.join("truth.npy").exists(), "no truth is made or written");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("## Held-out readings") && !report.contains("offline loop"),
        "{report}"
    );
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert!(
        summary["mse"].as_array().unwrap().is_empty(),
        "nothing is scored against a truth"
    );
    let h = &summary["holdout"];
    let (n, mse, noise) = (
        h["readings"].as_u64().unwrap(),
        h["mse"].as_f64().unwrap(),
        h["noise_var"].as_f64().unwrap(),
    );

    // The true error at the held-out cells, from the field kept aside.
    let est = fleet::process::dataset::load(out.join("estimate.npy"), 1.0).unwrap();
    let held: Vec<(usize, usize)> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| (v["step"].as_u64().unwrap(), v["cell"].as_u64().unwrap()))
        .filter(|&(k, c)| fleet_mission::holdout::is_held(k, c as u32, fleet_mission::holdout::DEFAULT_SHARE))
        .map(|(k, c)| (k as usize, c as usize))
        .collect();
    assert_eq!(
        held.len() as u64,
        n,
        "every held-out reading the emulator sent was scored"
    );
    assert!(n >= 20, "{n} readings held out");
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
