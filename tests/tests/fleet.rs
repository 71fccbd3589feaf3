//! The fleet over real Zenoh sockets between separate processes: `fleet up`, a Python
//! eclipse-zenoh client, and a vehicle on another network namespace.

use fleet::experiment::team;
use fleet::mission::report::ServerSummary;
use fleet_mission::config::MissionConfig;
use hetfleet_tests::*;
use std::path::Path;

/// Every batch assimilated exactly once, and the networked model's error equal, step for
/// step, to the offline loop's on the same truth and seed.
fn check_against_offline(mission: &Path, summary: &ServerSummary) {
    let m = MissionConfig::load(Some(mission)).unwrap();
    let truth = m.truth(|_| {}).unwrap().expect("a truth");
    let offline = team::run(&m.team, &truth, |_, _| {}).unwrap();
    let c = &summary.counters;
    assert_eq!(c.rejected.values().sum::<u64>(), 0, "{:?}", c.rejected);
    assert_eq!(
        c.batches - c.duplicates,
        expected_batches(&m, truth.frames()),
        "each batch assimilated once"
    );
    assert_eq!(summary.epochs, m.schedule(truth.frames()).epochs());
    assert_eq!(summary.mse.len(), offline.heterogeneous.len());
    for (k, (a, b)) in summary.mse.iter().zip(&offline.heterogeneous).enumerate() {
        assert!((a - b).abs() <= 1e-9 * b.abs(), "step {k}: network {a} vs offline {b}");
    }
    assert_eq!(summary.rank, offline.rank);
}

#[test]
fn fleet_up_runs_a_mission_that_equals_the_offline_loop() {
    let dir = scratch("up");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    let out = dir.join("run");
    let o = run(
        "fleet",
        &["up", mission.to_str().unwrap(), "--out", out.to_str().unwrap()],
    );
    assert!(
        o.status.success(),
        "fleet up failed: {}\n{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    let summary: ServerSummary =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    check_against_offline(&mission, &summary);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("Network equals offline: **yes"), "{report}");
    assert!(out.join("mse.png").exists() && out.join("model.cbor").exists());
    // The model's skill at every epoch after the aerial-only start, in the summary and the report.
    assert_eq!(summary.skill.len() as u64, summary.epochs - 1, "{:?}", summary.skill);
    assert!(summary
        .skill
        .iter()
        .all(|s| s.forecast.is_some_and(|f| f <= 1.0) && (0.0..=1.0).contains(&s.between)));
    assert!(report.contains("## Forecast skill"), "{report}");
    // The server's own peak memory (an operator sizes the base station's machine by it).
    assert!(
        summary.peak_resident_mib.is_some_and(|m| m > 1.0),
        "{:?}",
        summary.peak_resident_mib
    );
    assert!(report.contains("| server peak resident memory |"), "{report}");
    assert_eq!(
        summary.link_ups.len(),
        summary.vehicles.len(),
        "every vehicle was seen alive"
    );
}

#[test]
fn a_python_eclipse_zenoh_client_decodes_model_latest() {
    let dir = scratch("py");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    let m = mission.to_str().unwrap();
    let out = dir.join("out");
    let mut procs = Procs::default();
    let state = dir.join("state");
    let st = state.to_str().unwrap();
    let server = start_server(
        &mut procs,
        &["--mission", m, "--out", out.to_str().unwrap(), "--state-dir", st],
        &dir.join("server.log"),
    );
    start_vehicles(&mut procs, &mission, st, &dir, &[]);
    server.finished(120);
    let o = std::process::Command::new("python3")
        .arg(root().join("tests/py/model_latest.py"))
        .args([&ep, "tiny", out.join("summary.json").to_str().unwrap()])
        .output()
        .expect("python3");
    assert!(
        o.status.success(),
        "the Python client failed (scripts/test.sh installs eclipse-zenoh and cbor2):\n{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    println!("{}", String::from_utf8_lossy(&o.stdout));
}

#[test]
fn a_vehicle_on_another_host_reaches_the_server_through_its_router() {
    if !is_root_with_ip() {
        println!("SKIPPED: needs root and iproute2 for a network namespace (CI runs it as root)");
        return;
    }
    // Host "boat" in its own namespace, linked to this host by a veth pair.
    let host = Host::new(0);
    let here = host.here.clone();
    let dir = scratch("netns");
    let port = free_port();
    let (local, remote) = (format!("tcp/127.0.0.1:{port}"), format!("tcp/{here}:{port}"));
    // The server routes on both: loopback for the vehicles here, the veth for the other host.
    let mission = tiny_mission(&dir, &[local.clone(), remote.clone()], &[local]);
    let m = mission.to_str().unwrap();
    let mut procs = Procs::default();
    let st = dir.join("state");
    let st = st.to_str().unwrap();
    let server = start_server(
        &mut procs,
        &["--mission", m, "--state-dir", st],
        &dir.join("server.log"),
    );
    start_vehicles(&mut procs, &mission, st, &dir, &[("boat-1", &host.ns, &remote)]);
    let summary = server.finished(120);
    assert!(
        summary.link_ups.contains_key("boat-1"),
        "boat-1's liveliness crossed the link"
    );
    // Its own namespace cannot reach this host's loopback: the data came over the veth.
    check_against_offline(&mission, &summary);
}
