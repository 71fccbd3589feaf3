//! The fleet over a radio (issue 35): the boats on another host (a network namespace) behind a
//! veth link made a radio (`tc tbf` for the rate each way, nftables for random loss each way:
//! this kernel has no `netem`), the model server, the aerials and the ground-station gateway on
//! this side. The mission completes with every batch assimilated once, the estimate is the one
//! the same mission makes over loopback, and what crossed the link (measured on it: payloads,
//! Zenoh's and TCP/IP's headers, keep-alives and resends) per boat per epoch is within budget.

use fleet::mission::report::ServerEvent;
use fleet_mission::config::MissionConfig;
use hetfleet_tests::*;
use std::path::Path;
use std::time::Instant;

/// `mission` with the server listening on loopback and on this side of `host`'s link, the
/// vehicles here connecting on loopback (the boats are given the link's address), and its
/// `[link]` the radio's rate.
fn over_the_link(dir: &Path, mission: &Path, host: &Host, port: u16, kbit: f64) -> std::path::PathBuf {
    let m = dir.join("mission.toml");
    let text: Vec<String> = std::fs::read_to_string(mission)
        .unwrap()
        .lines()
        .map(|line| match line.split_once(" = ").map(|(k, _)| k.trim()) {
            Some("listen") => format!(r#"listen = ["tcp/127.0.0.1:{port}", "tcp/{}:{port}"]"#, host.here),
            Some("connect") => format!(r#"connect = ["tcp/127.0.0.1:{port}"]"#),
            Some("rate_kbps") => format!("rate_kbps = {kbit:?}"),
            _ => line.to_string(),
        })
        .collect();
    let mut text = text.join("\n");
    if !text.contains("[link]") {
        text.push_str(&format!("\n[link]\nrate_kbps = {kbit:?}\n"));
    }
    assert!(text.contains(&host.here), "the mission's endpoints were replaced");
    std::fs::write(&m, text).unwrap();
    m
}

/// What a run behind the radio gave.
struct Radio {
    out: std::path::PathBuf,
    /// Bytes that crossed the link (both ways) per boat per epoch the boats sense.
    per_boat_epoch: f64,
    /// The server's `waiting` events: the vehicles an epoch waited for, each with why.
    waiting: Vec<(
        u64,
        std::collections::BTreeMap<fleet_mission::protocol::VehicleId, String>,
    )>,
}

/// `mission` run with its boats behind `kbit` kbit/s and `loss`% loss each way (the server,
/// the aerials and the ground-station gateway on this side); every batch in the journal
/// exactly once, the model the one of those batches fed in step order.
fn run_behind_radio(dir: &Path, mission: &Path, host: &Host, kbit: f64, loss: u32) -> Radio {
    let port = free_port();
    let m = over_the_link(dir, mission, host, port, kbit);
    host.shape(kbit, loss);
    let config = MissionConfig::load(Some(&m)).unwrap();
    let endpoint = format!("tcp/{}:{port}", host.here);
    let boats: Vec<String> = (1..=config.team.boats).map(|i| format!("boat-{i}")).collect();
    let away: Vec<(&str, &str, &str)> = boats
        .iter()
        .map(|b| (b.as_str(), host.ns.as_str(), endpoint.as_str()))
        .collect();
    let (t0, before) = (Instant::now(), host.bytes());
    let (mut procs, server, out, state) = start_mission(dir, &m, &away);
    let gateway = std::process::Command::new(bin("gcs-gateway"))
        .args([
            "--mission",
            m.to_str().unwrap(),
            "--gcs",
            &format!("udpout:127.0.0.1:{}", free_port()),
        ])
        .stderr(std::fs::File::create(dir.join("gateway.log")).unwrap())
        .spawn()
        .expect("the gateway");
    procs.0.push(gateway);
    let gateway_index = procs.0.len() - 1;
    let (_, events) = server
        .try_finished_with_events(1500)
        .unwrap_or_else(|why| panic!("{why}\n{}", log_tails(dir, 6)));
    let wall_s = t0.elapsed().as_secs_f64();
    let after = host.bytes();
    let bytes = (after.0 - before.0) + (after.1 - before.1);
    let schedule = config.schedule(config.frames_hint());
    let boat_epochs = (0..schedule.epochs())
        .filter(|&e| schedule.seq_of(fleet_mission::protocol::VehicleKind::Boat, e).is_some())
        .count() as f64;
    let waiting = events
        .into_iter()
        .filter_map(|e| match e {
            ServerEvent::Waiting { epoch, behind, .. } => Some((epoch, behind)),
            _ => None,
        })
        .collect();
    println!(
        "{kbit} kbit/s, {loss}% loss each way: {wall_s:.0} s ({:.1} s per epoch), {:.1} kB per boat per epoch on the link",
        wall_s / schedule.epochs() as f64,
        bytes as f64 / (boats.len() as f64 * boat_epochs) / 1e3
    );
    // Every node ends by itself once the mission is done (the gateway serves until stopped);
    // the journal is read once the server has let go of it.
    procs.kill(gateway_index);
    procs.wait_all(120);
    check_exactly_once_and_same_model(&m, &state, &out);
    Radio {
        out,
        per_boat_epoch: bytes as f64 / (boats.len() as f64 * boat_epochs),
        waiting,
    }
}

/// The last `n` lines of each node's log in `dir`: what a run that hung on a machine nobody
/// watches leaves to read.
fn log_tails(dir: &Path, n: usize) -> String {
    let mut logs: Vec<_> = std::fs::read_dir(dir)
        .map(|d| d.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    logs.retain(|p| p.extension().is_some_and(|x| x == "log"));
    logs.sort();
    logs.iter()
        .map(|p| {
            let text = std::fs::read_to_string(p).unwrap_or_default();
            let lines: Vec<&str> = text.lines().collect();
            let tail = lines[lines.len().saturating_sub(n)..].join("\n");
            format!("== {}\n{tail}", p.display())
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn the_bundled_mission_completes_with_its_boats_behind_a_64_kbit_radio_with_5_percent_loss() {
    if !is_root_with_ip() {
        println!("SKIPPED: needs root, iproute2, tc and nft for a shaped link (CI runs it as root)");
        return;
    }
    let dir = scratch("radio");
    let host = Host::new(35);
    let radio = run_behind_radio(&dir, &root().join("config/mission.toml"), &host, 64.0, 5);
    assert!(
        radio.per_boat_epoch <= 16_000.0,
        "{:.0} bytes per boat per epoch crossed the link (budget 16 kB)",
        radio.per_boat_epoch
    );
    // The same mission over loopback, for its estimate.
    let loopback = dir.join("loopback");
    let o = run("fleet", &["up", "--out", loopback.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let over_radio = fleet_math::process::dataset::load(radio.out.join("estimate.npy"), 1.0).unwrap();
    let local = fleet_math::process::dataset::load(loopback.join("estimate.npy"), 1.0).unwrap();
    let (n, steps) = (local.snapshots.nrows(), local.snapshots.ncols());
    assert_eq!((over_radio.snapshots.nrows(), over_radio.snapshots.ncols()), (n, steps));
    let (mut scale, mut diff) = (0.0f64, 0.0f64);
    for k in 0..steps {
        for c in 0..n {
            let (a, b) = (over_radio.snapshots[(c, k)], local.snapshots[(c, k)]);
            scale = scale.max(b.abs());
            diff = diff.max((a - b).abs());
        }
    }
    assert!(
        diff <= 1e-9 * scale,
        "the estimate over the radio differs from loopback's by {diff:e}"
    );
}

/// A long-range radio (9.6 kbit/s, 5% loss each way) under the tiny mission's three boats: the
/// link is the bottleneck (each epoch waits on the boats' batches for tens of seconds), the
/// mission still completes with nothing lost, and the server says which boats it waits for and
/// why (a `waiting` event naming each, and the reason a person can act on).
#[test]
fn a_long_range_radio_is_slow_not_down_and_the_operator_is_told_who_is_behind() {
    if !is_root_with_ip() {
        println!("SKIPPED: needs root, iproute2, tc and nft for a shaped link (CI runs it as root)");
        return;
    }
    let dir = scratch("radio-9k6");
    let host = Host::new(36);
    let radio = run_behind_radio(&dir, &root().join("config/mission-tiny.toml"), &host, 9.6, 5);
    assert!(!radio.waiting.is_empty(), "no epoch said whom it waited for");
    for (epoch, behind) in &radio.waiting {
        assert!(!behind.is_empty(), "epoch {epoch}: a waiting event names no vehicle");
        for (v, why) in behind {
            assert!(
                v.as_str().starts_with("boat-"),
                "epoch {epoch}: waited for {v}, which is here"
            );
            assert!(!why.is_empty(), "epoch {epoch}: no reason given for {v}");
        }
    }
}
