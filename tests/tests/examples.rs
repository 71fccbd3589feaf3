//! The programs of `examples/`, each as its README runs it, against a live `fleet up` of the
//! tiny mission on the clock (steps of half a second, boat-1's readings from the sonde driver
//! over UDP, the fleet's ground-station stream to the driver): the Rust and the Python clients
//! each print the models the server publishes; the driver's readings reach boat-1's vehicle
//! node, which logs them; and the server core runs offline on the same mission file.

use hetfleet_tests::{bin, edit, free_port, root, scratch, tiny_mission};
use std::process::{Command, Stdio};

/// The tiny mission on the clock, from `start` (UTC seconds), boat-1 fed over UDP on `sensor`,
/// the ground-station stream to `gcs`.
fn clocked_mission(dir: &std::path::Path, ep: &str, start: f64, sensor: u16, gcs: u16) -> std::path::PathBuf {
    let m = tiny_mission(dir, &[ep.to_string()], &[ep.to_string()]);
    let start = fleet_mission::instrument::MissionClock::rfc3339(start);
    let mut text = std::fs::read_to_string(&m).unwrap();
    text.push_str(&format!(
        "\n[time]\nstart = \"{start}\"\nstep_s = 0.5\n\n[sensors]\ndefault = \"sim\"\nboat-1 = \"udp:127.0.0.1:{sensor}\"\n"
    ));
    std::fs::write(&m, text).unwrap();
    edit(
        &m,
        "sim_speedup = 100.0",
        &format!("sim_speedup = 100.0\ngcs = \"udpout:127.0.0.1:{gcs}\""),
    );
    m
}

#[test]
fn every_example_runs_against_a_live_mission() {
    let dir = scratch("examples");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let (sensor, gcs) = (free_port(), free_port());
    let start = fleet_mission::instrument::MissionClock::now().ceil() + 8.0;
    let m = clocked_mission(&dir, &ep, start, sensor, gcs);
    let out = dir.join("run");
    let up = Command::new(bin("fleet"))
        .args(["up", m.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let rust = Command::new(bin("watch_fleet"))
        .args([m.to_str().unwrap(), &ep, "3"])
        .output_in_thread();
    let python = Command::new("python3")
        .args([
            root().join("examples/python/watch_fleet.py").to_str().unwrap(),
            "tiny",
            &ep,
            "3",
        ])
        .output_in_thread();
    let driver = Command::new("python3")
        .args([
            root().join("examples/python/sonde_driver.py").to_str().unwrap(),
            "--gcs",
            &format!("127.0.0.1:{gcs}"),
            "--sysid",
            "3",
            "--to",
            &format!("127.0.0.1:{sensor}"),
            "--period",
            "0.25",
            "--seconds",
            "25",
        ])
        .output_in_thread();
    let up = up.wait_with_output().unwrap();
    assert!(up.status.success(), "fleet up: {}", String::from_utf8_lossy(&up.stderr));
    for (name, o) in [
        ("watch_fleet (Rust)", rust),
        ("watch_fleet.py", python),
        ("sonde_driver.py", driver),
    ] {
        let o = o.join().unwrap();
        let said = format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(o.status.success(), "{name}: {said}");
        if name.starts_with("watch") {
            assert_eq!(said.matches("model v").count(), 3, "{name}: {said}");
        }
    }
    // The driver's readings reached boat-1's node: its log holds them, at the driver's value.
    let log = std::fs::read_to_string(out.join("readings.ndjson")).unwrap_or_default();
    let boat: Vec<serde_json::Value> = log
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["vehicle"] == "boat-1")
        .collect();
    assert!(
        boat.iter()
            .any(|v| v["value"].as_f64().is_some_and(|x| (x - 0.3).abs() < 0.1)),
        "boat-1's readings: {boat:?}"
    );

    let offline = Command::new(bin("offline_core"))
        .arg(root().join("config/mission-tiny.toml"))
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&offline.stdout);
    assert!(offline.status.success() && said.lines().count() >= 7, "{said}");
}

/// `Command::output` on a thread of its own.
trait InThread {
    fn output_in_thread(self) -> std::thread::JoinHandle<std::process::Output>;
}

impl InThread for &mut Command {
    fn output_in_thread(self) -> std::thread::JoinHandle<std::process::Output> {
        let child = self.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
        std::thread::spawn(move || child.wait_with_output().unwrap())
    }
}
