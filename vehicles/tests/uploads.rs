//! The fence and rally uploads as a real link carries them: the bridge's side of the mission
//! protocol (`vehicles::upload`) against the simulated autopilot playing ArduPilot's upload
//! rules, over a slow link that loses messages; and a bridge whose fence upload fails never
//! arms its vehicle.

use fleet_math::grid::Grid;
use fleet_mission::config::MavlinkConfig;
use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use nalgebra::Vector3;
use std::collections::VecDeque;
use std::net::UdpSocket;
use std::time::{Duration, Instant};
use vehicles::autopilot::modes::Frame;
use vehicles::autopilot::sim::{SimAutopilot, SimSpec};
use vehicles::bridge::{Bridge, BridgeSpec, COMPANION_COMPONENT};
use vehicles::link::{frame_bytes, parse_frame};
use vehicles::upload::{self, Upload};

const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;
const RALLY: MavMissionType = MavMissionType::MAV_MISSION_TYPE_RALLY;
/// The bridge as the autopilot sees it.
const BRIDGE: MavHeader = MavHeader {
    system_id: 255,
    component_id: COMPANION_COMPONENT,
    sequence: 0,
};

/// One way of a radio: each message delivered `latency_s` after it is sent, or lost with
/// probability `loss` (a deterministic generator: the same losses on every run).
struct Way {
    queue: VecDeque<(f64, MavMessage)>,
    latency_s: f64,
    loss: f64,
    state: u64,
    lost: usize,
}

impl Way {
    fn new(latency_s: f64, loss: f64, seed: u64) -> Self {
        let state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        Self {
            queue: VecDeque::new(),
            latency_s,
            loss,
            state,
            lost: 0,
        }
    }

    fn send(&mut self, now: f64, m: MavMessage) {
        self.state ^= self.state << 13;
        self.state ^= self.state >> 7;
        self.state ^= self.state << 17;
        let uniform = (self.state >> 11) as f64 / (1u64 << 53) as f64;
        if uniform < self.loss {
            self.lost += 1;
        } else {
            self.queue.push_back((now + self.latency_s, m));
        }
    }

    fn due(&mut self, now: f64) -> Vec<MavMessage> {
        let n = self.queue.iter().take_while(|(t, _)| *t <= now).count();
        self.queue.drain(..n).map(|(_, m)| m).collect()
    }
}

/// The bridge's upload's answer to one of the autopilot's messages.
fn answer(u: &mut Upload, m: &MavMessage) -> Vec<MavMessage> {
    match m {
        MavMessage::MISSION_REQUEST_INT(r) => u.on_request(r.mission_type, r.seq, 3).into_iter().collect(),
        MavMessage::MISSION_ACK(a) => u.on_ack(a.mission_type, a.mavtype, 3),
        MavMessage::MISSION_COUNT(c) => u.on_count(c.mission_type, c.count, 3),
        MavMessage::MISSION_ITEM_INT(i) => u.on_item(i, 3),
        _ => vec![],
    }
}

/// 200 uploads, fence and rally in turn, each over a link that takes 0.3 s each way (a
/// 64 kbit/s radio behind the fleet's own traffic: an upload lasts longer than the bridge's
/// 1 s tick) and loses 5% each way. Every one ends confirmed by reading it back, the autopilot
/// holding exactly the items sent.
#[test]
fn two_hundred_uploads_over_a_lossy_slow_link_are_all_confirmed() {
    let m = MavlinkConfig::default();
    let site = m.site(&Grid::new(48, 96, 1.0).unwrap());
    let spec = SimSpec::from_config(Frame::Boat, 3, site, &m);
    let corners = [[0.0, 0.0], [0.0, 80.0], [40.0, 80.0], [40.0, 0.0]];
    let global: Vec<[f64; 2]> = corners
        .iter()
        .map(|&[n, e]| {
            let (lat, lon, _) = site.global_of(&Vector3::new(n, e, 0.0));
            [lat, lon]
        })
        .collect();
    let (mut starts, mut lost) = (0, 0);
    for n in 0..200u64 {
        let (kind, items) = if n % 2 == 0 {
            (FENCE, upload::fence_items(&global))
        } else {
            (RALLY, upload::rally_items(&global[..3]))
        };
        let mut sim = SimAutopilot::new(spec.clone(), Vector3::new(10.0, 10.0, 0.0));
        let mut up = Upload::new(kind, items.clone());
        let (mut to_ap, mut to_bridge) = (Way::new(0.3, 0.05, 2 * n + 1), Way::new(0.3, 0.05, 2 * n + 2));
        let (dt, mut now, mut tick) = (0.05, 0.0, 0.0);
        up.start(3).into_iter().for_each(|m| to_ap.send(now, m));
        while !up.finished() && now < 300.0 {
            now += dt;
            sim.step(dt);
            for m in to_ap.due(now) {
                sim.handle(&BRIDGE, &m);
            }
            for m in sim.take() {
                to_bridge.send(now, m);
            }
            let mut out: Vec<MavMessage> = to_bridge.due(now).iter().flat_map(|m| answer(&mut up, m)).collect();
            // The bridge's 1 Hz tick, the first at once (as tokio's interval ticks).
            if now >= tick {
                out.extend(up.tick(3));
                tick += 1.0;
            }
            out.into_iter().for_each(|m| to_ap.send(now, m));
        }
        assert!(up.confirmed(), "upload {n} ({kind:?}): {:?} after {now:.1} s", up.state);
        let held = if kind == FENCE { &sim.fence_items } else { &sim.rally };
        let as_sent = |v: &[MISSION_ITEM_INT_DATA]| v.iter().map(|i| (i.command, i.x, i.y)).collect::<Vec<_>>();
        assert_eq!(as_sent(held), as_sent(&items), "upload {n}");
        (starts, lost) = (starts + up.starts(), lost + to_ap.lost + to_bridge.lost);
    }
    assert!(
        lost > 100,
        "the link lost only {lost} messages: the test would not test loss"
    );
    println!("200 uploads confirmed: {starts} starts, {lost} messages lost");
}

/// A disarmed boat in HOLD (system 7).
fn hold_heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 4,
        mavtype: MavType::MAV_TYPE_SURFACE_BOAT,
        autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        system_status: MavState::MAV_STATE_STANDBY,
        mavlink_version: 3,
    })
}

/// An autopilot that refuses every fence upload (MISSION_ACK ERROR to each count): the bridge
/// starts it [`upload::TRIES`] times, then never asks to arm, and says why on the status.
#[test]
fn a_vehicle_whose_fence_is_refused_is_never_armed() {
    let ap = UdpSocket::bind("127.0.0.1:0").unwrap();
    ap.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    let mut spec = test_spec();
    spec.fence_m = vec![[0.0, 0.0], [0.0, 40.0], [80.0, 40.0], [80.0, 0.0]];
    let bridge = Bridge::connect(&format!("udpout:{}", ap.local_addr().unwrap()), spec, None).unwrap();
    let header = MavHeader {
        system_id: 7,
        component_id: 1,
        sequence: 0,
    };
    let (mut counts, mut arms, mut buf) = (0, 0, [0u8; 512]);
    let (mut peer, mut last_hb) = (None, Instant::now() - Duration::from_secs(1));
    // Well past ready_timeout (1 s), when the bridge would otherwise ask to arm anyway.
    let deadline = Instant::now() + Duration::from_secs(6);
    while Instant::now() < deadline {
        if let (Some(p), true) = (peer, last_hb.elapsed() >= Duration::from_millis(200)) {
            ap.send_to(&frame_bytes(header, &hold_heartbeat()), p).unwrap();
            last_hb = Instant::now();
        }
        let Ok((len, from)) = ap.recv_from(&mut buf) else {
            continue;
        };
        peer = Some(from);
        match parse_frame(&buf[..len]) {
            Ok((_, MavMessage::MISSION_COUNT(c))) => {
                counts += 1;
                let ack = MISSION_ACK_DATA {
                    target_system: 255,
                    target_component: COMPANION_COMPONENT,
                    mavtype: MavMissionResult::MAV_MISSION_ERROR,
                    mission_type: c.mission_type,
                    ..Default::default()
                };
                ap.send_to(&frame_bytes(header, &MavMessage::MISSION_ACK(ack)), from)
                    .unwrap();
            }
            Ok((_, MavMessage::COMMAND_LONG(c))) if c.command == MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => arms += 1,
            _ => {}
        }
    }
    let waiting = bridge.status().waiting.unwrap_or_default();
    assert_eq!((counts, arms), (upload::TRIES, 0), "waiting: {waiting}");
    assert!(
        waiting.contains("a confirmed fence") && waiting.contains("MAV_MISSION_ERROR"),
        "{waiting}"
    );
}

/// A boat's bridge (system 7) that asks to arm 1 s after it finds the autopilot.
fn test_spec() -> BridgeSpec {
    let site = MavlinkConfig::default().site(&Grid::new(24, 48, 1.0).unwrap());
    BridgeSpec {
        heartbeat_timeout: Duration::from_millis(1500),
        ready_timeout: Duration::from_secs(1),
        ..BridgeSpec::plain(SimSpec::from_config(Frame::Boat, 7, site, &MavlinkConfig::default()))
    }
}
