//! Faults on real processes and real links: `kill -9` of the server and of a boat mid-mission,
//! a boat's radio link going down and up on a seeded schedule (its own network namespace,
//! `ip link set down/up`), and every link degraded (loss, delay, reordering: TUN links with a lossy
//! relay, as these kernels have no `tc netem`).
//! In every case: each batch is assimilated exactly once, and the server's final model equals
//! the model computed offline from the same batches fed in step order.

use fleet::mission::config::MissionConfig;
use fleet::mission::schedule::Schedule;
use fleet::mission::server::ServerCore;
use fleet::protocol::{self, Body, Context};
use fleet_net::store::Store;
use hetfleet_tests::*;
use std::path::Path;
use std::time::Duration;

/// The journal holds every batch of the mission once; fed to a fresh core in step order it
/// gives the model the server published (to 1e-9 relative).
fn check_exactly_once_and_same_model(mission: &Path, state: &Path, out: &Path) {
    let m = MissionConfig::load(Some(mission)).unwrap();
    let truth = m.truth(|_| {}).unwrap();
    let (grid, frames) = m.workspace(&truth).unwrap();
    let journal = Store::open(&state.join(format!("{}.redb", m.mission))).unwrap();
    let mut ctx = Context::new(grid);
    ctx.vehicles = m.vehicles().into_iter().map(|v| v.id).collect();
    let mut batches: Vec<_> = journal
        .messages()
        .unwrap()
        .into_iter()
        .map(|(_, bytes)| match protocol::decode(&bytes, &ctx).unwrap() {
            Body::Batch(b) => b,
            other => panic!("not a batch: {other:?}"),
        })
        .collect();
    assert_eq!(batches.len() as u64, expected_batches(&m, frames), "every batch in the journal exactly once");
    let order = |id: &str| ctx.vehicles.iter().position(|v| v == id).unwrap();
    batches.sort_by_key(|b| (Schedule::epoch_of(b.kind, b.seq), order(&b.vehicle)));
    let mut core = ServerCore::new(&m.team, grid, frames).unwrap();
    for b in batches {
        core.ingest(b).unwrap();
    }
    assert!(core.finished());
    let offline = core.model_update().unwrap();
    let Body::Model(served) = protocol::decode(&std::fs::read(out.join("model.cbor")).unwrap(), &ctx).unwrap() else { panic!("model.cbor") };
    let close = |what: &str, a: &[f64], b: &[f64]| {
        let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let diff = a.iter().zip(b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        assert!(a.len() == b.len() && diff <= 1e-9 * scale, "{what}: differs by {diff:e} (scale {scale:e})");
    };
    close("eigenvalues", served.eigenvalues.as_flattened(), offline.eigenvalues.as_flattened());
    close("amplitudes", served.amplitudes.as_flattened(), offline.amplitudes.as_flattened());
    close("modes", &served.modes_re, &offline.modes_re);
}

/// A paced tiny mission (so there is time to break things mid-way) on a fresh port.
fn paced_mission(dir: &Path, listen: &[String], connect: &[String], step_ms: u64) -> std::path::PathBuf {
    let m = tiny_mission(dir, listen, connect);
    edit(&m, "plan_timeout_ms = 20000", &format!("plan_timeout_ms = 1500\nstep_ms = {step_ms}"));
    edit(&m, "listen = [", "lease_ms = 1000\nlisten = [");
    m
}

#[test]
fn kill_9_of_the_server_and_of_a_boat_loses_nothing_and_counts_nothing_twice() {
    let dir = scratch("kill");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = paced_mission(&dir, &[ep.clone()], &[ep], 60);
    let (m, out, state) = (mission.to_str().unwrap().to_string(), dir.join("out"), dir.join("state"));
    let server_args = ["--mission", &m, "--out", out.to_str().unwrap(), "--state-dir", state.to_str().unwrap(), "--exit-when-done"];
    let mut procs = Procs::default();
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    let vehicle_args = |id: &str| vec!["--mission".to_string(), m.clone(), "--id".into(), id.into(), "--state-dir".into(), state.to_str().unwrap().into()];
    let mut boat2 = 0;
    for v in MissionConfig::load(Some(&mission)).unwrap().vehicles() {
        let args = vehicle_args(&v.id);
        let i = start_vehicle(&mut procs, &[], &args.iter().map(String::as_str).collect::<Vec<_>>(), &dir.join(format!("{}.log", v.id)));
        if v.id == "boat-2" {
            boat2 = i;
        }
    }
    // A boat dies after the first boat epoch and comes back from its outbox.
    server.epoch(1, 60);
    procs.kill(boat2);
    let args = vehicle_args("boat-2");
    start_vehicle(&mut procs, &[], &args.iter().map(String::as_str).collect::<Vec<_>>(), &dir.join("boat-2.log"));
    // The server dies mid-mission and comes back from its journal.
    server.epoch(3, 60);
    procs.kill(server.index);
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    let summary = server.finished(120);
    procs.wait_all(60);
    assert!(summary.counters.restored >= 4 * 3, "the restarted server replayed its journal ({})", summary.counters.restored);
    assert_eq!(summary.counters.batches - summary.counters.duplicates, expected_batches(&MissionConfig::load(Some(&mission)).unwrap(), 40));
    check_exactly_once_and_same_model(&mission, &state, &out);
    println!("kill -9: restored {} batches, {} duplicates re-sent and dropped", summary.counters.restored, summary.counters.duplicates);
}

#[test]
fn a_boat_whose_link_drops_on_a_schedule_loses_nothing() {
    if !is_root_with_ip() {
        println!("SKIPPED: needs root and iproute2 (CI runs it as root)");
        return;
    }
    use rand::{RngExt, SeedableRng};
    let host = Host::new(1);
    let dir = scratch("flap");
    let port = free_port();
    let (local, remote) = (format!("tcp/127.0.0.1:{port}"), format!("tcp/{}:{port}", host.here));
    let mission = paced_mission(&dir, &[local.clone(), remote.clone()], &[local], 60);
    // The server waits 0.8 s for a late boat, then goes on without it and re-fits later.
    edit(&mission, "resend_ms", "epoch_timeout_ms = 800\nresend_ms");
    let (m, out, state) = (mission.to_str().unwrap(), dir.join("out"), dir.join("state"));
    let st = state.to_str().unwrap();
    let mut procs = Procs::default();
    let server = start_server(&mut procs, &["--mission", m, "--out", out.to_str().unwrap(), "--state-dir", st, "--exit-when-done"], &dir.join("server.log"));
    start_vehicles(&mut procs, &mission, st, &dir, &[("boat-1", &host.ns, &remote)]);
    // Seeded outages of the boat's link while the mission runs: down 0.5-2.5 s, up 0.3-1 s.
    server.epoch(0, 60);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let (mut down_s, mut back) = (0.0, vec![]);
    for _ in 0..3 {
        let (down, up) = (rng.random_range(500..2500u64), rng.random_range(300..1000u64));
        sh(&["ip", "link", "set", &host.veth(), "down"]);
        std::thread::sleep(Duration::from_millis(down));
        // From the link coming back to the next model (the boat's backlog in it).
        while server.events.try_recv().is_ok() {}
        let t = std::time::Instant::now();
        sh(&["ip", "link", "set", &host.veth(), "up"]);
        if server.next_epoch(Duration::from_millis(up + 5000)) {
            back.push(t.elapsed().as_secs_f64() * 1e3);
        }
        std::thread::sleep(Duration::from_millis(up).saturating_sub(t.elapsed()));
        down_s += down as f64 / 1e3;
    }
    // (The events were drained above: the summary comes from the server's file.)
    procs.wait_all(180);
    let summary: fleet::mission::report::ServerSummary = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    check_exactly_once_and_same_model(&mission, &state, &out);
    assert!(summary.counters.forced >= 1 && summary.counters.refits >= 1, "the outages made the server go on without the boat and re-fit: {:?}", summary.counters);
    println!(
        "link flaps: boat-1 down {down_s:.1} s in 3 outages of a {:.1} s mission; {} epochs assimilated without it, {} re-fits; link up to the next model {back:.0?} ms; its token appeared {} times; {} duplicates",
        summary.wall_s,
        summary.counters.forced,
        summary.counters.refits,
        summary.link_ups["boat-1"],
        summary.counters.duplicates
    );
}

/// Every vehicle on its own host behind a link that drops 30% of the packets each way and
/// delays the rest by 2-22 ms, so they also arrive out of order. These kernels have no `netem`,
/// so the links are TUN pairs with a relay (`lossy_link`); the nodes' kernels see real loss and
/// reordering. Zenoh runs over TCP, which retransmits: to the fleet, loss is delay.
#[test]
fn thirty_percent_loss_with_reordering_on_every_link() {
    if !is_root_with_ip() {
        println!("SKIPPED: needs root and iproute2 (CI runs it as root)");
        return;
    }
    use hetfleet_tests::lossy_link::{Degradation, LossyHost};
    let dir = scratch("lossy");
    let port = free_port();
    let local = format!("tcp/127.0.0.1:{port}");
    let ids: Vec<String> = MissionConfig::load(Some(&root().join("config/mission-tiny.toml"))).unwrap().vehicles().into_iter().map(|v| v.id).collect();
    let hosts: Vec<LossyHost> = (0..ids.len())
        .map(|i| LossyHost::new(10 + i as u32, Degradation { loss: 0.3, delay_ms: 2, jitter_ms: 20, seed: 7 + i as u64 }).expect("a TUN link (needs /dev/net/tun)"))
        .collect();
    let remote: Vec<String> = hosts.iter().map(|h| format!("tcp/{}:{port}", h.here)).collect();
    let mission = tiny_mission(&dir, &[vec![local.clone()], remote.clone()].concat(), &[local]);
    let (m, out, state) = (mission.to_str().unwrap(), dir.join("out"), dir.join("state"));
    let st = state.to_str().unwrap();
    let mut procs = Procs::default();
    let server = start_server(&mut procs, &["--mission", m, "--out", out.to_str().unwrap(), "--state-dir", st, "--exit-when-done"], &dir.join("server.log"));
    let away: Vec<(&str, &str, &str)> = ids.iter().zip(&hosts).zip(&remote).map(|((id, h), e)| (id.as_str(), h.ns.as_str(), e.as_str())).collect();
    start_vehicles(&mut procs, &mission, st, &dir, &away);
    let summary = server.finished(600);
    procs.wait_all(120);
    check_exactly_once_and_same_model(&mission, &state, &out);
    let (passed, dropped, overtaken) = hosts.iter().map(LossyHost::totals).fold((0, 0, 0), |a, t| (a.0 + t.0, a.1 + t.1, a.2 + t.2));
    let lost = dropped as f64 / (passed + dropped) as f64;
    assert!((0.25..0.35).contains(&lost), "the links dropped {dropped} of {} packets", passed + dropped);
    assert!(overtaken > 0, "no packet was reordered");
    println!(
        "30% loss on {} links: {dropped} of {} packets dropped ({:.1}%), {overtaken} reordered; mission in {:.1} s, last batch to model p50 {:.1} ms p99 {:.1} ms; {} duplicates re-sent and dropped",
        hosts.len(),
        passed + dropped,
        100.0 * lost,
        summary.wall_s,
        summary.latency_ms.p50,
        summary.latency_ms.p99,
        summary.counters.duplicates
    );
}
