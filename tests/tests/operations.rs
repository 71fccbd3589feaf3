//! The fleet as an operator runs it, with processes killed, state files damaged, identities
//! claimed and no terminal: a held vehicle survives a server restart; damaged journals and
//! outboxes are refused and left as they are; the ground-station gateway pins system ids from
//! the mission; `fleet up` keeps every notice without a terminal and owns its nodes.

use fleet::mission::report::ServerEvent;
use fleet_mission::config::MissionConfig;
use hetfleet_tests::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("a free UDP port")
        .port()
}

/// ArduRover's HOLD mode number.
const HOLD: u32 = 4;

/// A paced tiny mission (150 ms a step, 80 steps: about 12 s) with its ground stations on
/// `gcs_port`, autopilots declared lost after 1.5 s without a HEARTBEAT.
fn slow_mission(dir: &Path, gcs_port: u16) -> (PathBuf, String) {
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let m = tiny_mission(dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    edit(&m, "plan_timeout_ms = 20000", "plan_timeout_ms = 1500\nstep_ms = 150");
    edit(&m, "frames = 40", "frames = 80");
    edit(&m, "listen = [", "lease_ms = 1000\nlisten = [");
    edit(
        &m,
        r#"autopilot = "sim""#,
        &format!("autopilot = \"sim\"\ngcs = \"udpout:127.0.0.1:{gcs_port}\"\nheartbeat_timeout_ms = 1500"),
    );
    (m, ep)
}

#[test]
fn a_server_that_held_vehicles_restarts_after_kill_9_and_the_mission_completes() {
    let dir = scratch("hold-restart");
    let gcs_port = free_udp_port();
    let (mission, _) = slow_mission(&dir, gcs_port);
    let m = MissionConfig::load(Some(&mission)).unwrap();
    let (mp, out, state) = (
        mission.to_str().unwrap().to_string(),
        dir.join("out"),
        dir.join("state"),
    );
    let st = state.to_str().unwrap().to_string();
    let server_args = [
        "--mission",
        &mp,
        "--out",
        out.to_str().unwrap(),
        "--state-dir",
        &st,
        "--exit-when-done",
    ];
    let mut procs = Procs::default();
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    let gs = GroundStation::listen(gcs_port);
    procs.0.push(
        Command::new(bin("gcs-gateway"))
            .args(["--mission", &mp])
            .stderr(std::fs::File::create(dir.join("gateway.log")).unwrap())
            .spawn()
            .unwrap(),
    );
    // boat-3 drives an autopilot of its own process, so the test can make it go silent. It is
    // switched on at boat-3's launch point (inside the fence by its margin, as the fleet keeps
    // every launch point; the site's corner is on the fence).
    let ap_port = free_udp_port();
    let grid = fleet_math::grid::Grid::new(24, 48, 1.0).unwrap();
    let at = fleet_mission::launch::launch_points(&m, &grid).unwrap()[m.vehicle("boat-3").unwrap().0];
    let home = [at[0].to_string(), at[1].to_string()];
    let autopilot = procs.0.len();
    procs.0.push(
        Command::new(bin("sim-autopilot"))
            .args([
                "--mission",
                &mp,
                "--frame",
                "boat",
                "--sysid",
                &m.sysid("boat-3").unwrap().to_string(),
                "--listen",
                &format!("udpin:127.0.0.1:{ap_port}"),
                "--grid",
                "24",
                "48",
                "--home",
                &home[0],
                &home[1],
            ])
            .stderr(std::fs::File::create(dir.join("autopilot.log")).unwrap())
            .spawn()
            .unwrap(),
    );
    for v in m.vehicles() {
        let mut args = vec!["--mission", &mp, "--id", &v.id, "--state-dir", &st];
        let remote = format!("udpout:127.0.0.1:{ap_port}");
        if v.id == "boat-3" {
            args.extend(["--autopilot", &remote]);
        }
        start_vehicle(&mut procs, &[], &args, &dir.join(format!("{}.log", v.id)));
    }
    let held = |who: &'static str| {
        move |e: &ServerEvent| {
            matches!(e, ServerEvent::Hold { vehicle, held: true, .. } if vehicle == who).then_some(())
        }
    };
    let epoch_at_least = |n: u64| {
        move |e: &ServerEvent| match e {
            ServerEvent::Epoch { epoch, .. } if *epoch >= n => Some(*epoch),
            _ => None,
        }
    };

    // An operator puts boat-1 on HOLD; its empty batches are journalled; the server dies.
    server.epoch(1, 60);
    gs.set_mode(m.sysid("boat-1").unwrap(), HOLD);
    server.wait_for(30, "boat-1 held", held("boat-1"));
    let e = server.wait_for(30, "an epoch", epoch_at_least(0));
    server.wait_for(30, "two epochs on", epoch_at_least(e + 2));
    procs.kill(server.index);
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    // boat-3's autopilot goes silent (lost); the server dies again.
    let e = server.wait_for(60, "the restarted server goes on", epoch_at_least(0));
    procs.kill(autopilot);
    server.wait_for(30, "boat-3 held (autopilot lost)", held("boat-3"));
    server.wait_for(30, "two epochs on", epoch_at_least(e + 2));
    procs.kill(server.index);
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    let summary = server.finished(120);
    assert_eq!(
        summary.counters.rejected.values().sum::<u64>(),
        0,
        "every batch accepted, before and after the restarts: {:?}",
        summary.counters.rejected
    );
    assert!(summary.counters.restored > 0);
    let log = std::fs::read_to_string(dir.join("server.log")).unwrap();
    assert_eq!(
        log.matches("journal: resuming").count(),
        2,
        "both restarts resumed: {log}"
    );
    // Every batch once in the journal, and the served model is the model of those batches.
    check_exactly_once_and_same_model(&mission, &state, &out);
}

/// Run a node until it exits (or `secs` pass: then it is killed and `None` returned).
fn exit_of(mut cmd: Command, secs: u64) -> Option<(i32, String)> {
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("a node");
    let deadline = std::time::Instant::now() + Duration::from_secs(secs);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
            return Some((status.code().unwrap_or(-1), err));
        }
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The offset in `bytes` of `needle`'s first occurrence.
/// Every place `needle` occurs: redb writes copy-on-write, so a file may also hold stale
/// copies of a record in freed pages, and only damage to the live one must be refused.
fn find_all(bytes: &[u8], needle: &[u8]) -> Vec<usize> {
    let at: Vec<usize> = bytes
        .windows(needle.len())
        .enumerate()
        .filter(|(_, w)| *w == needle)
        .map(|(i, _)| i)
        .collect();
    assert!(!at.is_empty(), "present");
    at
}

#[test]
fn damaged_journals_and_outboxes_are_refused_by_the_nodes_and_left_as_they_are() {
    let dir = scratch("damaged");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    // A finished run's journal, and a vehicle's outbox holding unacknowledged batches.
    let run_dir = dir.join("run");
    let o = run(
        "fleet",
        &["up", mission.to_str().unwrap(), "--out", run_dir.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let journal = std::fs::read(run_dir.join("state/tiny.redb")).unwrap();
    let outbox = {
        let mut s = fleet_net::store::Store::open(&dir.join("made/boat-1.redb")).unwrap();
        let j = fleet_net::store::Store::open(&run_dir.join("state/tiny.redb")).unwrap();
        let batches: Vec<_> = j
            .messages()
            .unwrap()
            .into_iter()
            .filter(|((v, _), _)| v == "boat-1")
            .collect();
        for ((v, seq), b) in &batches {
            s.commit(&[((v, *seq), b)], &[]).unwrap();
        }
        drop(s);
        std::fs::read(dir.join("made/boat-1.redb")).unwrap()
    };
    let record = {
        let j = fleet_net::store::Store::open(&run_dir.join("state/tiny.redb")).unwrap();
        j.messages().unwrap()[3].1.clone()
    };
    // One bit of the record flipped, in every copy of it the file holds (the live one among them).
    let flip = |b: &[u8]| {
        let mut out = b.to_vec();
        for at in find_all(b, &record[40..80]) {
            out[at + 20] ^= 0x10;
        }
        out
    };
    let truth = run_dir.join("truth.npy");
    let m = mission.to_str().unwrap();
    let cases: Vec<(&str, &str, Vec<u8>)> = vec![
        (
            "model-server",
            "journal truncated to a third",
            journal[..journal.len() / 3].to_vec(),
        ),
        ("model-server", "a measurement's bit flipped", flip(&journal)),
        ("model-server", "0 bytes", vec![]),
        (
            "vehicle",
            "outbox truncated to a third",
            outbox[..outbox.len() / 3].to_vec(),
        ),
        ("vehicle", "a batch's bit flipped", flip(&outbox)),
    ];
    for (node, what, bytes) in cases {
        let state = dir.join(format!("state-{}", what.replace(' ', "-")));
        std::fs::create_dir_all(&state).unwrap();
        let file = state.join(if node == "vehicle" { "boat-1.redb" } else { "tiny.redb" });
        std::fs::write(&file, &bytes).unwrap();
        let mut cmd = Command::new(bin(node));
        cmd.args([
            "--mission",
            m,
            "--truth",
            truth.to_str().unwrap(),
            "--state-dir",
            state.to_str().unwrap(),
        ]);
        if node == "vehicle" {
            cmd.args(["--id", "boat-1"]);
        }
        let (code, err) = exit_of(cmd, 30).unwrap_or_else(|| panic!("{what}: the node did not stop"));
        let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
        println!("{what}: exit {code}: {}", lines.last().unwrap_or(&""));
        assert_eq!(code, 2, "{what}: bad input is exit 2: {err}");
        assert_eq!(lines.len(), 1, "{what}: one line: {err}");
        assert!(
            lines[0].starts_with(&format!("{node}: ")) && lines[0].contains(&file.display().to_string()),
            "{what}: names the file: {err}"
        );
        assert!(
            lines[0].contains("move the file aside"),
            "{what}: says how to recover: {err}"
        );
        assert!(!err.contains("panicked"), "{what}: {err}");
        assert_eq!(
            std::fs::read(&file).unwrap(),
            bytes,
            "{what}: the refusal changed the file"
        );
        assert_eq!(
            std::fs::read_dir(&state).unwrap().count(),
            1,
            "{what}: nothing left beside it"
        );
    }
}

#[test]
#[allow(deprecated)]
fn the_gateway_pins_system_ids_from_the_mission_whatever_arrives_first() {
    use mavlink::dialects::ardupilotmega::*;
    let dir = scratch("impostor");
    let gcs_port = free_udp_port();
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    edit(
        &mission,
        r#"autopilot = "sim""#,
        &format!("autopilot = \"sim\"\ngcs = \"udpout:127.0.0.1:{gcs_port}\""),
    );
    let m = MissionConfig::load(Some(&mission)).unwrap();
    let mp = mission.to_str().unwrap();
    let mut procs = Procs::default();
    let st = dir.join("state");
    let _server = start_server(
        &mut procs,
        &["--mission", mp, "--state-dir", st.to_str().unwrap()],
        &dir.join("server.log"),
    );
    procs.0.push(
        Command::new(bin("gcs-gateway"))
            .args(["--mission", mp])
            .stderr(std::fs::File::create(dir.join("gateway.log")).unwrap())
            .spawn()
            .unwrap(),
    );
    let gs = GroundStation::listen(gcs_port);
    let (boat1, boat2) = (m.sysid("boat-1").unwrap(), m.sysid("boat-2").unwrap());
    let keys = fleet_mission::protocol::keys::Keys::new("tiny").unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let session = rt.block_on(async {
        let cfg = fleet_net::config(
            fleet_net::Role::Vehicle,
            &m.network,
            &m.link,
            None,
            &fleet_net::Endpoints::default(),
        )
        .unwrap();
        fleet_net::open(cfg).await.unwrap()
    });
    let hb = |sysid: u8, mode: u32| {
        vehicles::link::frame_bytes(
            mavlink::MavHeader {
                system_id: sysid as u32,
                component_id: 1,
                sequence: 0,
            },
            &MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: mode,
                mavtype: MavType::MAV_TYPE_SURFACE_BOAT,
                ..Default::default()
            }),
        )
    };
    let put = |key: String, bytes: Vec<u8>| rt.block_on(async { session.put(&key, bytes).await.unwrap() });
    let gcs_in = |id: &str| rt.block_on(async { session.declare_subscriber(keys.gcs(id)).await.unwrap() });
    let (to1, to2) = (gcs_in("boat-1"), gcs_in("boat-2"));
    // boat-1, on its own key, claims boat-2's system id first (mode 99 marks its frames) and
    // keeps at it; then the real boat-2 comes up (mode 15).
    std::thread::sleep(Duration::from_millis(1500));
    for _ in 0..50 {
        put(keys.mavlink("boat-1"), hb(boat2, 99));
    }
    let mut seen: Vec<(u32, u32)> = vec![];
    let stop = std::sync::atomic::AtomicBool::new(false);
    std::thread::scope(|s| {
        s.spawn(|| {
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                put(keys.mavlink("boat-1"), hb(boat2, 99));
                put(keys.mavlink("boat-2"), hb(boat2, 15));
                put(keys.mavlink("boat-1"), hb(boat1, 15));
                std::thread::sleep(Duration::from_millis(100));
            }
        });
        let until = std::time::Instant::now() + Duration::from_secs(3);
        while std::time::Instant::now() < until {
            if let (h, MavMessage::HEARTBEAT(d)) = gs.recv() {
                seen.push((h.system_id, d.custom_mode));
            }
        }
        // An operator's HOLD for boat-2's system id (sent once boat-2's HEARTBEAT is seen).
        gs.set_mode(boat2, HOLD);
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
    });
    assert!(
        seen.contains(&(boat2 as u32, 15)),
        "the real boat-2 reaches the ground station: {seen:?}"
    );
    assert!(!seen.contains(&(boat2 as u32, 99)), "boat-1's claim never does");
    // The HOLD went to boat-2, not to the impostor.
    let got = rt.block_on(async { tokio::time::timeout(Duration::from_secs(5), to2.recv_async()).await });
    assert!(matches!(got, Ok(Ok(_))), "the HOLD reached boat-2");
    assert!(
        to1.try_recv().ok().flatten().is_none_or(|s| {
            let (_, msg) = vehicles::link::parse_frame(&s.payload().to_bytes()).unwrap();
            !matches!(msg, MavMessage::SET_MODE(_))
        }),
        "nothing for boat-2 went to boat-1"
    );
    drop(procs);
    let log = std::fs::read_to_string(dir.join("gateway.log")).unwrap();
    let lines = log.lines().filter(|l| l.contains("impostor")).count();
    assert!(
        (1..=3).contains(&lines),
        "impostor frames logged once, then counted ({lines} lines): {log}"
    );
}

/// `fleet up` as a child, its output not a terminal.
fn fleet_up(mission: &Path, out: &Path) -> Command {
    let mut c = Command::new(bin("fleet"));
    c.args(["up", mission.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .current_dir(root())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

#[test]
fn fleet_up_without_a_terminal_keeps_every_notice_and_the_report_says_why_it_differs() {
    let dir = scratch("notty");
    let gcs_port = free_udp_port();
    let (mission, ep) = slow_mission(&dir, gcs_port);
    let m = MissionConfig::load(Some(&mission)).unwrap();
    let out = dir.join("run");
    let child = fleet_up(&mission, &out).spawn().unwrap();
    // An observer of the server's status, and a ground station holding boat-2 mid-mission.
    let statuses = std::sync::Arc::new(std::sync::Mutex::new(vec![]));
    let seen = statuses.clone();
    let net = m.network.clone();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Runtime::new().unwrap();
        rt.block_on(async move {
            let cfg = fleet_net::config(
                fleet_net::Role::Vehicle,
                &net,
                &fleet_mission::config::Link::default(),
                None,
                &fleet_net::Endpoints {
                    listen: vec![],
                    connect: vec![ep],
                },
            )
            .unwrap();
            let session = fleet_net::open(cfg).await.unwrap();
            let sub = session.declare_subscriber("fleet/tiny/server/status").await.unwrap();
            while let Ok(s) = sub.recv_async().await {
                if let Ok(fleet_mission::protocol::Body::Status(st)) = fleet_mission::protocol::decode(
                    &s.payload().to_bytes(),
                    &fleet_mission::protocol::Context::new(fleet_math::grid::Grid::new(24, 48, 1.0).unwrap()),
                ) {
                    seen.lock().unwrap().push(st);
                }
            }
        });
    });
    let gs = GroundStation::listen(gcs_port);
    eventually(60, "the mission under way", || {
        std::fs::read_to_string(out.join("events.jsonl")).is_ok_and(|t| t.contains(r#""epoch":2"#))
    });
    gs.set_mode(m.sysid("boat-2").unwrap(), HOLD);
    let o = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        stdout.contains("boat-2: left out of the allocation (HOLD"),
        "the notice is printed without a terminal: {stdout}"
    );
    let notices = std::fs::read_to_string(out.join("logs/fleet-up.log")).unwrap();
    assert!(
        notices.contains("boat-2: left out of the allocation"),
        "and kept in the log: {notices}"
    );
    let events = std::fs::read_to_string(out.join("events.jsonl")).unwrap();
    assert!(events.lines().all(|l| serde_json::from_str::<ServerEvent>(l).is_ok()));
    assert!(
        events.contains(r#""event":"hold","vehicle":"boat-2","held":true"#)
            && events.lines().any(|l| l.contains(r#""event":"finished""#)),
        "{events}"
    );
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("Network equals offline: **no**")
            && report.contains("boat-2 was left out of the allocation (mode HOLD once)"),
        "the report says why: {report}"
    );
    for log in std::fs::read_dir(out.join("logs")).unwrap() {
        let path = log.unwrap().path();
        assert!(
            !std::fs::read(&path).unwrap().contains(&0x1b),
            "{}: no colour escapes in a log file",
            path.display()
        );
    }
    eventually(10, "the finished status", || {
        statuses.lock().unwrap().iter().any(|s| s.finished)
    });
    let last = statuses.lock().unwrap().last().cloned().unwrap();
    assert!(
        last.finished,
        "the last status an observer sees says finished: {last:?}"
    );
    // The status says what the model was worth at the last epoch (issue 37).
    let skill = last.skill.expect("the status carries the model's skill");
    assert!(
        skill.forecast.is_some_and(|f| f <= 1.0) && (0.0..=1.0).contains(&skill.between),
        "{skill:?}"
    );
}

/// The endpoint's port is free again (nothing holds it).
fn port_free(ep: &str) -> bool {
    std::net::TcpListener::bind(ep.trim_start_matches("tcp/")).is_ok()
}

#[test]
fn fleet_up_owns_its_nodes_a_signal_stops_them_all() {
    for (sig, name) in [(libc::SIGTERM, "SIGTERM"), (libc::SIGKILL, "SIGKILL")] {
        let dir = scratch(&format!("own-{name}"));
        let gcs_port = free_udp_port();
        let (mission, ep) = slow_mission(&dir, gcs_port);
        let out = dir.join("run");
        // In a session of its own, as a service manager or nohup would start it.
        let mut child = Command::new("setsid")
            .arg(bin("fleet"))
            .args(["up", mission.to_str().unwrap(), "--out", out.to_str().unwrap()])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        eventually(60, "the mission under way", || {
            std::fs::read_to_string(out.join("events.jsonl")).is_ok_and(|t| t.contains(r#""epoch":1"#))
        });
        let needle = dir.to_str().unwrap().to_string();
        assert!(
            pids_with(&needle).len() >= 8,
            "fleet up, the server, the gateway and five vehicles run"
        );
        // SAFETY: a signal to our own child.
        unsafe { libc::kill(child.id() as i32, sig) };
        let status = child.wait().unwrap();
        eventually(15, &format!("{name}: every node gone"), || {
            pids_with(&needle).is_empty()
        });
        assert!(port_free(&ep), "{name}: the server's port is free again");
        assert!(
            std::net::UdpSocket::bind(("127.0.0.1", gcs_port)).is_ok(),
            "{name}: nothing holds the ground stations' port"
        );
        use std::os::unix::process::ExitStatusExt;
        if sig == libc::SIGTERM {
            assert_eq!(
                status.code(),
                Some(128 + libc::SIGTERM),
                "stopped by a signal: 128 + its number"
            );
        } else {
            assert_eq!(status.signal(), Some(libc::SIGKILL));
        }
    }
}

#[test]
fn a_failed_start_leaves_the_previous_run_and_a_dead_node_is_reported_in_its_own_words() {
    let dir = scratch("failed-start");
    let gcs_port = free_udp_port();
    let (mission, ep) = slow_mission(&dir, gcs_port);
    let out = dir.join("run");
    std::fs::create_dir_all(out.join("state")).unwrap();
    std::fs::write(out.join("report.md"), "the previous run").unwrap();
    std::fs::write(out.join("state/tiny.redb"), "the previous journal").unwrap();
    // Another program holds the server's port.
    let holder = std::net::TcpListener::bind(ep.trim_start_matches("tcp/")).unwrap();
    let o = fleet_up(&mission, &out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.trim().lines().count() == 1
            && err.contains(&format!("listen {ep}"))
            && err.to_lowercase().contains("in use"),
        "one line naming the endpoint: {err}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("report.md")).unwrap(),
        "the previous run"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("state/tiny.redb")).unwrap(),
        "the previous journal"
    );
    drop(holder);
    // A node killed mid-mission: `up` stops and says which, and what it last said.
    let child = fleet_up(&mission, &out).spawn().unwrap();
    eventually(60, "the mission under way", || {
        std::fs::read_to_string(out.join("events.jsonl")).is_ok_and(|t| t.contains(r#""epoch":1"#))
    });
    let boat: Vec<u32> = pids_with(dir.to_str().unwrap())
        .into_iter()
        .filter(|p| cmdline(*p).contains("--id boat-2"))
        .collect();
    assert_eq!(boat.len(), 1, "one boat-2");
    // SAFETY: a signal to a node this test started.
    unsafe { libc::kill(boat[0] as i32, libc::SIGKILL) };
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("boat-2 exited (killed by signal 9)") && err.contains("it said:"),
        "{err}"
    );
    eventually(15, "every node gone", || pids_with(dir.to_str().unwrap()).is_empty());
}

#[test]
fn a_batch_that_decodes_but_is_invalid_is_counted_once_in_the_status() {
    use fleet_mission::protocol::{Body, MeasurementBatch, Noise, Sample, VehicleKind};
    let dir = scratch("counted-once");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    let m = MissionConfig::load(Some(&mission)).unwrap();
    let mut procs = Procs::default();
    let server = start_server(
        &mut procs,
        &[
            "--mission",
            mission.to_str().unwrap(),
            "--state-dir",
            dir.join("state").to_str().unwrap(),
        ],
        &dir.join("server.log"),
    );
    server.wait_for(30, "the server up", |e| {
        matches!(e, ServerEvent::Ready { .. }).then_some(())
    });
    let rt = tokio::runtime::Runtime::new().unwrap();
    let keys = fleet_mission::protocol::keys::Keys::new("tiny").unwrap();
    let status = rt.block_on(async {
        let cfg = fleet_net::config(
            fleet_net::Role::Vehicle,
            &m.network,
            &m.link,
            None,
            &fleet_net::Endpoints::default(),
        )
        .unwrap();
        let session = fleet_net::open(cfg).await.unwrap();
        let statuses = session.declare_subscriber(keys.server_status()).await.unwrap();
        let batch = |kind, steps: Vec<u64>| MeasurementBatch {
            vehicle: "boat-1".parse().unwrap(),
            kind,
            seq: 0,
            noise: Noise {
                sigma0: 0.05,
                growth_per_m: 0.0,
            },
            samples: steps
                .into_iter()
                .map(|s| Sample {
                    step: s,
                    position: [1.0, 1.0],
                    cells: vec![0],
                    values: vec![0.5],
                    sigma: None,
                })
                .collect(),
        };
        // Wrong kind (boat-1 declares itself an aerial), then wrong steps: two invalid batches.
        for b in [
            batch(VehicleKind::Aerial, vec![0]),
            batch(VehicleKind::Boat, vec![3, 4]),
        ] {
            fleet_net::put(&session, &keys.measurements("boat-1"), &Body::Batch(b))
                .await
                .unwrap();
        }
        let ctx = fleet_mission::protocol::Context::new(fleet_math::grid::Grid::new(24, 48, 1.0).unwrap());
        loop {
            let s = tokio::time::timeout(Duration::from_secs(10), statuses.recv_async())
                .await
                .expect("a status")
                .unwrap();
            if let Ok(Body::Status(st)) = fleet_net::decode(&s, &ctx) {
                if st.batches >= 2 {
                    break st;
                }
            }
        }
    });
    assert_eq!(
        status.rejected,
        std::collections::BTreeMap::from([("invalid_batch".to_string(), 2)]),
        "each invalid batch counted exactly once"
    );
    assert_eq!(status.batches, 2);
    let log = std::fs::read_to_string(dir.join("server.log")).unwrap();
    assert!(
        log.contains("declared Aerial, registered Boat"),
        "the refusal is logged with its reason: {log}"
    );
}
