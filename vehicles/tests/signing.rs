//! MAVLink 2 signing on the autopilot link, over real UDP sockets: a signed simulated
//! autopilot obeys only frames signed with its key (unsigned, wrongly signed and replayed ones
//! are refused, each counted by reason) and signs what it sends; a bridge with the key drives
//! it; a bridge with another key gets nothing from it; an autopilot that cannot sign is taken
//! only when the mission says so.

use fleet_math::grid::Grid;
use fleet_mission::config::MavlinkConfig;
use fleet_mission::protocol::AutopilotLink;
use fleet_mission::signing_key::SigningKey;

use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use nalgebra::Vector3;
use std::net::UdpSocket;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use vehicles::autopilot::modes::Frame;
use vehicles::autopilot::serve::{self, ServeStats};
use vehicles::autopilot::sim::{SimAutopilot, SimSpec};
use vehicles::bridge::{Bridge, BridgeSpec};
use vehicles::link::{frame_bytes, parse_frame};
use vehicles::signing::{LinkSigning, Refused};

fn spec(sysid: u8) -> SimSpec {
    SimSpec {
        frame: Frame::Boat,
        sysid,
        site: MavlinkConfig::default().site(&Grid::new(24, 48, 1.0).unwrap()),
        max_speed: 20.0,
        turn_rate: 6.0,
        cruise_alt: 0.0,
        turn_radius: 0.0,
        wp_radius: 0.0,
        gps_delay_s: 0.0,
        disarm_delay_s: 10.0,
        speedup: 1.0,
        safety: Default::default(),
        wind: Default::default(),
    }
}

/// A simulated autopilot on a loopback port, signed with `key` if given.
fn autopilot(sysid: u8, key: Option<&SigningKey>, stop: &Arc<AtomicBool>) -> (u16, Arc<ServeStats>) {
    let port = UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let signing = key.map(|k| LinkSigning::new(k.clone(), vehicles::signing::LINK_AUTOPILOT, false));
    let stats = serve::spawn(
        &format!("udpin:127.0.0.1:{port}"),
        // Switched on 5 m inside the fence, clear of its margin as the fleet's launch points are.
        SimAutopilot::new(spec(sysid), Vector3::new(5.0, 10.0, 0.0)),
        signing,
        stop.clone(),
    )
    .unwrap();
    (port, stats)
}

fn wait_for(what: &str, secs: f64, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    while !cond() {
        assert!(Instant::now() < deadline, "{what}: not within {secs} s");
        std::thread::sleep(Duration::from_millis(10));
    }
}

const GCS: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

fn arm(sysid: u8) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        param1: 1.0,
        target_system: sysid,
        ..Default::default()
    })
}

/// Send `frame` and collect what comes back for `ms` milliseconds.
fn exchange(sock: &UdpSocket, port: u16, frame: &[u8], ms: u64) -> Vec<Vec<u8>> {
    sock.send_to(frame, ("127.0.0.1", port)).unwrap();
    let deadline = Instant::now() + Duration::from_millis(ms);
    let mut got = vec![];
    let mut buf = [0u8; 512];
    while Instant::now() < deadline {
        if let Ok(n) = sock.recv(&mut buf) {
            got.push(buf[..n].to_vec());
        }
    }
    got
}

fn acks(frames: &[Vec<u8>]) -> usize {
    let arm = MavCmd::MAV_CMD_COMPONENT_ARM_DISARM;
    let acked = |f: &&Vec<u8>| matches!(parse_frame(f), Ok((_, MavMessage::COMMAND_ACK(a))) if a.command == arm);
    frames.iter().filter(acked).count()
}

#[test]
fn a_signed_autopilot_obeys_only_signed_frames_and_counts_every_refusal() {
    let key = SigningKey::from_passphrase("autopilot-5");
    let stop = Arc::new(AtomicBool::new(false));
    let (port, stats) = autopilot(5, Some(&key), &stop);
    let gcs = UdpSocket::bind("127.0.0.1:0").unwrap();
    gcs.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
    let n = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);

    // Unsigned, and signed with another key: no answer, each counted.
    assert_eq!(
        acks(&exchange(&gcs, port, &frame_bytes(GCS, &arm(5)), 300)),
        0,
        "unsigned obeyed"
    );
    let stranger = LinkSigning::new(SigningKey::from_passphrase("guess"), 0, false);
    assert_eq!(
        acks(&exchange(&gcs, port, stranger.frame(GCS, &arm(5)).raw_bytes(), 300)),
        0,
        "wrong key obeyed"
    );
    wait_for("counted", 2.0, || {
        n(&stats.unsigned) == 1 && n(&stats.bad_signature) == 1
    });

    // Signed with the key: acked, and everything the autopilot sends is signed with it.
    let ours = LinkSigning::new(key.clone(), 0, false);
    let signed = ours.frame(GCS, &arm(5)).raw_bytes().to_vec();
    let back = exchange(&gcs, port, &signed, 400);
    assert_eq!(acks(&back), 1, "a signed command is obeyed");
    let check = LinkSigning::new(key, 9, false);
    assert!(
        !back.is_empty() && back.iter().all(|f| check.check(f).is_ok()),
        "every frame it sends is signed with the key"
    );

    // The same signed frame again (a recording played back): refused as a replay.
    assert_eq!(acks(&exchange(&gcs, port, &signed, 300)), 0, "a replay obeyed");
    wait_for("replay counted", 2.0, || n(&stats.replay) == 1);
    assert_eq!((n(&stats.unsigned), n(&stats.bad_signature)), (1, 1));
    stop.store(true, Ordering::Relaxed);
    assert_eq!(Refused::Replay.reason(), "replay");
}

fn bridge_to(port: u16, key: Option<SigningKey>, accept_unsigned: bool) -> Bridge {
    let spec = BridgeSpec {
        heartbeat_timeout: Duration::from_millis(1500),
        signing: key.map(|k| (k, accept_unsigned)),
        // The site's extent as the fence, and two rally points: uploaded over the signed link.
        fence_m: vec![[0.0, 0.0], [48.0, 0.0], [48.0, 24.0], [0.0, 24.0]],
        rally: vec![Vector3::new(1.0, 1.0, 0.0), Vector3::new(1.0, 40.0, 0.0)],
        ..BridgeSpec::plain(spec(5))
    };
    Bridge::connect(&format!("udpout:127.0.0.1:{port}"), spec, None).unwrap()
}

#[test]
fn a_bridge_with_the_key_drives_its_autopilot_and_one_without_gets_nothing() {
    let key = SigningKey::from_passphrase("boat-5");
    let stop = Arc::new(AtomicBool::new(false));

    // The right key: armed, GUIDED, driven to a place, its position read.
    let (port, stats) = autopilot(5, Some(&key), &stop);
    let b = bridge_to(port, Some(key.clone()), false);
    wait_for("link up and drivable", 10.0, || {
        b.status().link == AutopilotLink::Up && b.drivable()
    });
    assert!(
        b.fence_enabled(),
        "the fence and rally points went up and the fence is enforced"
    );
    assert!(b.goto((6.0, 4.0)));
    wait_for("arrived", 10.0, || b.arrived((6.0, 4.0)));
    assert_eq!(
        (
            b.counters().refused_signing,
            stats.unsigned.load(Ordering::Relaxed),
            stats.bad_signature.load(Ordering::Relaxed)
        ),
        (0, 0, 0)
    );

    // Another key: the autopilot refuses the bridge, the bridge refuses the autopilot.
    let (port, stats) = autopilot(5, Some(&key), &stop);
    let wrong = bridge_to(port, Some(SigningKey::from_passphrase("boat-6")), false);
    std::thread::sleep(Duration::from_millis(2500));
    assert_eq!(
        wrong.status().link,
        AutopilotLink::Connecting,
        "an autopilot that signs with another key is not ours"
    );
    assert!(wrong.counters().refused_signing > 0 && stats.bad_signature.load(Ordering::Relaxed) > 0);

    // An autopilot that cannot sign: refused, unless the mission accepts unsigned telemetry
    // (what the bridge sends it is signed all the same).
    let (port, _) = autopilot(5, None, &stop);
    let strict = bridge_to(port, Some(key.clone()), false);
    std::thread::sleep(Duration::from_millis(2500));
    assert_eq!(strict.status().link, AutopilotLink::Connecting);
    assert!(strict.counters().refused_signing > 0);
    let (port, _) = autopilot(5, None, &stop);
    let lenient = bridge_to(port, Some(key), true);
    wait_for("unsigned telemetry taken", 10.0, || {
        lenient.status().link == AutopilotLink::Up && lenient.drivable()
    });
    assert_eq!(lenient.counters().refused_signing, 0);
    stop.store(true, Ordering::Relaxed);
}
