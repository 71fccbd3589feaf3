//! What comes off a radio link is not trusted: garbage bytes, bad CRCs, unknown message ids,
//! truncated frames and a silent autopilot must leave the bridge and the simulated autopilot
//! working, with the loss shown on the bridge's status.

use fleet_math::grid::Grid;
use fleet_mission::config::MavlinkConfig;
use fleet_mission::protocol::AutopilotLink;
use fleet_mission::site::Site;
use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use nalgebra::Vector3;
use rand::{Rng, RngExt, SeedableRng};
use std::net::UdpSocket;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};
use vehicles::autopilot::modes::{Control, Frame};
use vehicles::autopilot::serve;
use vehicles::autopilot::sim::{SimAutopilot, SimSpec};
use vehicles::bridge::{Bridge, BridgeSpec};
use vehicles::link::{frame_bytes, parse_frame};

/// The scripted autopilot's frames: system 7, the autopilot's component.
const AP_HEADER: MavHeader = MavHeader {
    system_id: 7,
    component_id: 1,
    sequence: 0,
};

fn site() -> Site {
    MavlinkConfig::default().site(&Grid::new(24, 48, 1.0).unwrap())
}

/// Hostile datagrams: random bytes, frames with a flipped CRC byte, unknown message ids,
/// truncations, and a MAVLink 2 start byte with a huge length.
fn garbage(rng: &mut impl Rng, n: usize) -> Vec<Vec<u8>> {
    let good = frame_bytes(
        MavHeader {
            system_id: 7,
            component_id: 1,
            sequence: 0,
        },
        &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
    );
    (0..n)
        .map(|i| match i % 5 {
            0 => (0..rng.random_range(1..300)).map(|_| rng.random()).collect(),
            1 => {
                let mut f = good.clone();
                let k = f.len() - 1;
                f[k] ^= 0x5a;
                f
            }
            2 => {
                // Valid framing, message id 0xfffffe (no dialect has it), random CRC.
                let mut f = vec![0xfd, 4, 0, 0, 9, 7, 1, 0xfe, 0xff, 0xff, 1, 2, 3, 4];
                f.extend([rng.random::<u8>(), rng.random::<u8>()]);
                f
            }
            3 => good[..rng.random_range(1..good.len())].to_vec(),
            _ => vec![0xfd, 255, 0, 0, 0, 1, 1, 0, 0, 0],
        })
        .collect()
}

fn heartbeat(mode: u32) -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: mode,
        mavtype: MavType::MAV_TYPE_SURFACE_BOAT,
        autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED,
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// A boat's bridge (system 7) that drives as soon as the autopilot shows GUIDED and armed.
fn boat_spec() -> BridgeSpec {
    BridgeSpec {
        heartbeat_timeout: Duration::from_millis(400),
        ..BridgeSpec::plain(SimSpec {
            frame: Frame::Boat,
            sysid: 7,
            site: site(),
            max_speed: 2.0,
            turn_rate: 1.0,
            cruise_alt: 0.0,
            turn_radius: 0.0,
            wp_radius: 0.0,
            gps_delay_s: 0.0,
            disarm_delay_s: 10.0,
            speedup: 1.0,
            safety: Default::default(),
            wind: Default::default(),
        })
    }
}

/// The autopilot's HEARTBEAT (system 7) at 10 Hz to `peer`, in the mode stored in the returned
/// cell (0: silent; `u32::MAX`: stop).
fn heartbeats(ap: &UdpSocket, peer: std::net::SocketAddr, first: u32) -> Arc<std::sync::atomic::AtomicU32> {
    let mode = Arc::new(std::sync::atomic::AtomicU32::new(first));
    let (ap, cell) = (ap.try_clone().unwrap(), mode.clone());
    std::thread::spawn(move || loop {
        let m = cell.load(std::sync::atomic::Ordering::Relaxed);
        if m == u32::MAX {
            return;
        }
        if m != 0 {
            let _ = ap.send_to(&frame_bytes(AP_HEADER, &heartbeat(m)), peer);
        }
        std::thread::sleep(Duration::from_millis(100));
    });
    mode
}

fn wait_for(what: &str, secs: f64, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    while !cond() {
        assert!(Instant::now() < deadline, "{what}: not within {secs} s");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn garbage_and_a_silent_autopilot_never_break_the_bridge() {
    // A fake autopilot we script by hand on a UDP socket.
    let ap = UdpSocket::bind("127.0.0.1:0").unwrap();
    ap.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
    let spec = boat_spec();
    let mut bridge = Bridge::connect(&format!("udpout:{}", ap.local_addr().unwrap()), spec, None).unwrap();
    // The bridge's companion heartbeat tells us where it is.
    let mut buf = [0u8; 512];
    let (_, peer) = ap.recv_from(&mut buf).expect("the bridge's heartbeat");
    let send = |bytes: &[u8]| {
        ap.send_to(bytes, peer).unwrap();
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    for g in garbage(&mut rng, 2_000) {
        send(&g);
    }
    assert_eq!(
        bridge.status().link,
        AutopilotLink::Connecting,
        "garbage is not an autopilot"
    );
    assert!(bridge.position().is_none());

    // The autopilot's HEARTBEAT at 10 Hz in the mode set here (0: silent).
    let mode = heartbeats(&ap, peer, 15);
    let alive = |m| mode.store(m, std::sync::atomic::Ordering::Relaxed);
    wait_for("link up in GUIDED", 3.0, || {
        bridge.status().link == AutopilotLink::Up && bridge.drivable()
    });
    // Positions on the Earth (the autopilot's local frame has its own origin).
    let (lat, lon, _) = site().global_of(&Vector3::new(3.0, 4.0, 0.0));
    let pos = MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
        lat: (lat * 1e7).round() as i32,
        lon: (lon * 1e7).round() as i32,
        hdg: u16::MAX,
        ..Default::default()
    });
    send(&frame_bytes(AP_HEADER, &pos));
    // A position off the Earth is refused, not believed.
    send(&frame_bytes(
        AP_HEADER,
        &MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            lat: i32::MAX,
            lon: 5,
            ..Default::default()
        }),
    ));
    for g in garbage(&mut rng, 500) {
        send(&g);
    }
    wait_for("position read", 2.0, || {
        bridge
            .position()
            .is_some_and(|(x, y)| (x - 4.0).abs() < 0.01 && (y - 3.0).abs() < 0.01)
    });
    assert!(bridge.goto((10.0, 10.0)), "a guided target goes out");

    // Silence: lost, not drivable, no targets sent; then it is back.
    alive(0);
    wait_for("autopilot lost", 2.0, || bridge.status().link == AutopilotLink::Lost);
    assert!(!bridge.drivable() && !bridge.goto((1.0, 1.0)));
    alive(15);
    wait_for("autopilot back", 2.0, || bridge.status().link == AutopilotLink::Up);
    // An operator's HOLD: no longer the planner's.
    alive(4);
    wait_for("on hold", 2.0, || !bridge.status().guided);
    assert!(!bridge.goto((1.0, 1.0)));

    // Ground-station frames: garbage and other systems' commands are refused and counted.
    for g in garbage(&mut rng, 500) {
        assert!(bridge.from_gcs(&g).is_err());
    }
    let gcs = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    };
    let arm = |target| {
        frame_bytes(
            gcs,
            &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                target_system: target,
                ..Default::default()
            }),
        )
    };
    assert!(bridge.from_gcs(&arm(9)).is_err(), "not ours");
    assert!(bridge.from_gcs(&arm(7)).is_ok());
    assert!(bridge.from_gcs(&vec![0xfd; 4096]).is_err(), "oversized");
    let c = bridge.counters();
    assert_eq!((c.from_gcs, c.refused_from_gcs), (1, 502));
    assert_eq!(bridge.status().refused_from_gcs, 502, "telemetry carries the refusals");
    alive(u32::MAX);
}

#[test]
fn the_simulated_autopilot_answers_through_garbage() {
    let port = UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let spec = SimSpec {
        frame: Frame::Multirotor,
        sysid: 5,
        site: site(),
        max_speed: 10.0,
        turn_rate: 1.0,
        cruise_alt: 20.0,
        turn_radius: 0.0,
        wp_radius: 0.0,
        gps_delay_s: 0.0,
        disarm_delay_s: 10.0,
        speedup: 1.0,
        safety: Default::default(),
        wind: Default::default(),
    };
    let stop = Arc::new(AtomicBool::new(false));
    serve::spawn(
        &format!("udpin:127.0.0.1:{port}"),
        SimAutopilot::new(spec, Vector3::zeros()),
        None,
        stop.clone(),
    )
    .unwrap();
    let gcs = UdpSocket::bind("127.0.0.1:0").unwrap();
    gcs.set_read_timeout(Some(Duration::from_millis(100))).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
    for g in garbage(&mut rng, 2_000) {
        gcs.send_to(&g, ("127.0.0.1", port)).unwrap();
    }
    let h = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    };
    let arm = frame_bytes(
        h,
        &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            param1: 1.0,
            target_system: 5,
            ..Default::default()
        }),
    );
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut acked = false;
    while !acked && Instant::now() < deadline {
        gcs.send_to(&arm, ("127.0.0.1", port)).unwrap();
        let mut buf = [0u8; 512];
        while let Ok(n) = gcs.recv(&mut buf) {
            if let Ok((hdr, MavMessage::COMMAND_ACK(a))) = parse_frame(&buf[..n]) {
                assert_eq!(hdr.system_id, 5);
                acked = a.command == MavCmd::MAV_CMD_COMPONENT_ARM_DISARM && a.result == MavResult::MAV_RESULT_ACCEPTED;
                break;
            }
        }
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    assert!(acked, "no COMMAND_ACK after the garbage");
}

/// The DO_SET_MODE commands for `want` the bridge sends within `secs` (the scripted autopilot
/// applies none of them; a refusal, `ack`, answers the first).
fn mode_requests(ap: &UdpSocket, want: u32, secs: f64, ack: Option<MavResult>) -> usize {
    let (mut buf, mut n) = ([0u8; 512], 0);
    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    while Instant::now() < deadline {
        let Ok((len, peer)) = ap.recv_from(&mut buf) else {
            continue;
        };
        let Ok((_, MavMessage::COMMAND_LONG(c))) = parse_frame(&buf[..len]) else {
            continue;
        };
        if c.command != MavCmd::MAV_CMD_DO_SET_MODE || c.param2 as u32 != want {
            continue;
        }
        n += 1;
        if let (1, Some(result)) = (n, ack) {
            let a = COMMAND_ACK_DATA {
                command: c.command,
                result,
                ..Default::default()
            };
            ap.send_to(&frame_bytes(AP_HEADER, &MavMessage::COMMAND_ACK(a)), peer)
                .unwrap();
        }
    }
    n
}

/// The vehicle's own mode change (a link-loss failsafe's RTL) lost on the link is asked for
/// again until the autopilot's heartbeat shows it, and its reason stays in telemetry through
/// the heartbeats sent before it took; a mode change the autopilot refuses is said, not retried.
#[test]
fn a_lost_mode_change_is_asked_again_until_the_autopilot_shows_it() {
    const GUIDED: u32 = 15;
    const RTL: u32 = 11;
    let ap = UdpSocket::bind("127.0.0.1:0").unwrap();
    ap.set_read_timeout(Some(Duration::from_millis(100))).unwrap();
    let bridge = Bridge::connect(&format!("udpout:{}", ap.local_addr().unwrap()), boat_spec(), None).unwrap();
    let mut buf = [0u8; 512];
    let (_, peer) = ap.recv_from(&mut buf).expect("the bridge's heartbeat");
    let mode = heartbeats(&ap, peer, GUIDED);
    wait_for("link up in GUIDED", 3.0, || bridge.drivable());

    assert!(bridge.failsafe(Control::Return, "ground link lost"));
    // The autopilot never hears it (a lost datagram): still GUIDED, asked again.
    let asked = mode_requests(&ap, RTL, 4.5, None);
    assert!(
        asked >= 2,
        "RTL asked for {asked} time(s) while the autopilot stayed in GUIDED"
    );
    let status = bridge.status();
    assert_eq!(status.failsafe.as_deref(), Some("ground link lost"), "{status:?}");
    // Now it takes: no more requests once the heartbeat shows RTL.
    mode.store(RTL, std::sync::atomic::Ordering::Relaxed);
    wait_for("RTL shown", 2.0, || bridge.status().mode == "RTL");
    assert_eq!(
        mode_requests(&ap, RTL, 2.5, None),
        0,
        "asked again after the autopilot showed RTL"
    );
    assert_eq!(bridge.status().failsafe.as_deref(), Some("ground link lost"));

    // GUIDED again on rejoining, refused by the autopilot: said, and not asked again.
    bridge.rejoin();
    assert_eq!(mode_requests(&ap, GUIDED, 3.0, Some(MavResult::MAV_RESULT_DENIED)), 1);
    let failsafe = bridge.status().failsafe.unwrap_or_default();
    assert!(failsafe.contains("refused GUIDED"), "{failsafe}");
    mode.store(u32::MAX, std::sync::atomic::Ordering::Relaxed);
}
