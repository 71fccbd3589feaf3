//! Every decoder that reads what comes from outside, fed generated malformed input: the wire
//! protocol (Zenoh payloads), MAVLink frames, mission files, `.npy` files and the nodes' state
//! files (journal, outbox). Each input is a
//! valid one mutated (bytes flipped, replaced, inserted, deleted, truncated) or plain random
//! bytes. Properties: nothing panics, and whatever is accepted satisfies the decoder's own
//! checks (finite values, cells on the grid, shapes that match their data). The total count is
//! printed.

use fleet_math::grid::Grid;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::*;
use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};
use std::sync::atomic::{AtomicU64, Ordering};
use vehicles::link::{frame_bytes, parse_frame};

/// Inputs per decoder.
const CASES: u32 = 30_000;
/// Whole state files (each one written, checked on a copy, opened and read).
const STORE_CASES: u32 = 10_000;

static INPUTS: AtomicU64 = AtomicU64::new(0);

/// One edit of a byte string: (where, byte, what: flip bits / replace / insert / delete).
type Edit = (usize, u8, u8);

fn mutate(base: &[u8], edits: &[Edit], cut: Option<usize>, random: &[u8]) -> Vec<u8> {
    // One input in eight is plain random bytes.
    if edits.first().is_some_and(|e| e.2 % 8 == 7) {
        return random.to_vec();
    }
    let mut v = base.to_vec();
    for &(at, byte, op) in edits {
        if v.is_empty() {
            v.push(byte);
            continue;
        }
        let i = at % v.len();
        match op % 4 {
            0 => v[i] ^= byte.max(1),
            1 => v[i] = byte,
            2 => v.insert(i, byte),
            _ => {
                v.remove(i);
            }
        }
    }
    if let Some(c) = cut {
        v.truncate(c % (v.len() + 1));
    }
    v
}

fn malformed() -> impl Strategy<Value = (usize, Vec<Edit>, Option<usize>, Vec<u8>)> {
    (
        any::<usize>(),
        prop::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 1..8),
        prop::option::of(any::<usize>()),
        prop::collection::vec(any::<u8>(), 0..200),
    )
}

/// Run `check` on `CASES` mutations of the `seeds`.
fn fuzz(name: &str, seeds: &[Vec<u8>], check: impl Fn(&[u8]) -> Result<(), TestCaseError>) {
    fuzz_n(name, seeds, CASES, check)
}

fn fuzz_n(name: &str, seeds: &[Vec<u8>], cases: u32, check: impl Fn(&[u8]) -> Result<(), TestCaseError>) {
    let mut runner = TestRunner::new(Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    });
    runner
        .run(&malformed(), |(which, edits, cut, random)| {
            INPUTS.fetch_add(1, Ordering::Relaxed);
            check(&mutate(&seeds[which % seeds.len()], &edits, cut, &random))
        })
        .unwrap_or_else(|e| panic!("{name}: {e}"));
}

fn ctx() -> Context {
    let mut c = Context::new(Grid::new(6, 8, 1.0).unwrap());
    c.vehicles = vec!["boat-1".parse().unwrap(), "av-1".parse().unwrap()];
    c
}

fn wire_seeds() -> Vec<Vec<u8>> {
    let g = Grid::new(6, 8, 1.0).unwrap();
    let n = g.len();
    let bodies = [
        Body::Batch(MeasurementBatch {
            vehicle: "boat-1".parse().unwrap(),
            kind: VehicleKind::Boat,
            seq: 3,
            noise: Noise {
                sigma0: 0.1,
                growth_per_m: 0.0,
            },
            samples: vec![Sample {
                step: 10,
                position: [1.5, 2.5],
                cells: vec![0, 7, 19],
                values: vec![0.3, 0.4, 0.5],
                sigma: None,
            }],
        }),
        Body::Telemetry(Telemetry {
            vehicle: "av-1".parse().unwrap(),
            step: 2,
            position: [0.0, 4.0],
            heading: 1.0,
            battery: 0.5,
            link: LinkState::Up,
            outbox_depth: 7,
            autopilot: Some(AutopilotStatus {
                link: AutopilotLink::Up,
                sysid: 1,
                mode: "GUIDED".into(),
                armed: true,
                guided: true,
                unreadable: 0,
                refused_from_gcs: 2,
                failsafe: Some("Failsafe: battery low".into()),
                waiting: Some("GPS fix".into()),
            }),
            acked: Some(4),
            readings: Some(fleet_mission::protocol::ReadingCounts {
                received: 12,
                accepted: 10,
                refused: [("too_old".to_string(), 2)].into(),
                empty_frames: 1,
            }),
            traffic: Some(fleet_mission::protocol::LinkTraffic {
                sent: [("batch".to_string(), [3, 12_000])].into(),
                received: [("ack".to_string(), [3, 90])].into(),
            }),
            sensor: Some(fleet_mission::protocol::SensorHealth {
                state: fleet_mission::protocol::Health::Suspect,
                reason: "biased high (CUSUM 7.0)".into(),
            }),
        }),
        Body::Ack(Ack {
            vehicle: "boat-1".parse().unwrap(),
            seq: 9,
            sensor: None,
        }),
        Body::Model(ModelUpdate {
            version: 1,
            epoch: 2,
            step: 40,
            grid: g,
            dt: 0.25,
            eigenvalues: vec![[0.9, 0.1]],
            modes_re: vec![0.1; n],
            modes_im: vec![0.0; n],
            amplitudes: vec![[1.0, 0.0]],
            variance: vec![0.01; n],
            forecast_steps: 5,
            forecast_variance: vec![0.02; n],
            land: vec![],
            level: 0.0,
            estimate: vec![0.3; n],
        }),
        Body::Plan(Plan {
            vehicle: "boat-1".parse().unwrap(),
            model_version: 1,
            epoch: 3,
            targets: vec![Target {
                epoch: 3,
                step: 45,
                position: [2.0, 2.0],
                radius: 1.5,
                cells: vec![0, 1, 5],
            }],
        }),
    ];
    bodies.iter().map(encode).collect()
}

#[test]
fn malformed_inputs_never_panic_a_decoder() {
    let c = ctx();
    fuzz("wire protocol", &wire_seeds(), |bytes| {
        if let Ok(body) = decode(bytes, &c) {
            // What is accepted passed validation: ids known, cells on the grid, values finite.
            match &body {
                Body::Batch(b) => {
                    prop_assert!(c.vehicles.contains(&b.vehicle));
                    for s in &b.samples {
                        prop_assert!(
                            s.cells.iter().all(|&k| (k as usize) < c.grid.len())
                                && s.values.iter().all(|v| v.is_finite())
                        );
                    }
                }
                Body::Telemetry(t) => prop_assert!((0.0..=1.0).contains(&t.battery)),
                _ => {}
            }
            prop_assert_eq!(
                decode(&encode(&body), &c).ok(),
                Some(body),
                "accepted input re-encodes to itself"
            );
        }
        Ok(())
    });

    let h = MavHeader {
        system_id: 3,
        component_id: 1,
        sequence: 7,
    };
    let frames: Vec<Vec<u8>> = [
        MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_DO_SET_MODE,
            param2: 4.0,
            target_system: 3,
            ..Default::default()
        }),
        MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
            seq: 1,
            x: 556_761_000,
            y: 125_683_000,
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            ..Default::default()
        }),
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            x: 1.0,
            y: 2.0,
            ..Default::default()
        }),
    ]
    .iter()
    .map(|m| frame_bytes(h, m))
    .collect();
    fuzz("MAVLink frames", &frames, |bytes| {
        if let Ok((h, m)) = parse_frame(bytes) {
            // Accepted frames carry a CRC-checked message that serialises back to itself.
            prop_assert_eq!(parse_frame(&frame_bytes(h, &m)).map(|x| x.1).ok(), Some(m));
        }
        Ok(())
    });

    let missions: Vec<Vec<u8>> = [
        "config/mission.toml",
        "config/mission-tiny.toml",
        "config/mission-60.toml",
    ]
    .iter()
    .map(|p| std::fs::read(hetfleet_tests::root().join(p)).unwrap())
    .collect();
    fuzz("mission files", &missions, |bytes| {
        if let Ok(m) = MissionConfig::from_toml(&String::from_utf8_lossy(bytes)) {
            prop_assert!(m.frames_hint() >= 10 && m.pace.horizon >= 1 && m.mavlink.sim_speedup > 0.0);
        }
        Ok(())
    });

    let dir = hetfleet_tests::scratch("fuzz-npy");
    let mut npys = vec![];
    for (k, shape) in [vec![3usize, 4], vec![2, 3, 2], vec![5]].into_iter().enumerate() {
        let n: usize = shape.iter().product();
        let p = dir.join(format!("{k}.npy"));
        fleet_math::npy::write(&p, &shape, &(0..n).map(|i| i as f64 * 0.5).collect::<Vec<_>>()).unwrap();
        npys.push(std::fs::read(&p).unwrap());
    }
    fuzz(".npy files", &npys, |bytes| {
        if let Ok(a) = fleet_math::npy::from_bytes(bytes, "fuzz.npy") {
            prop_assert_eq!(a.data.len(), a.shape.iter().product::<usize>());
        }
        Ok(())
    });

    // The nodes' state files (a journal, an outbox): each input is a whole file, opened and
    // read as a node does, so fewer of them. Accepted means read back exactly as written.
    let dir = hetfleet_tests::scratch("fuzz-store");
    let mut stores = vec![];
    for (k, (vehicles, meta)) in [
        (&["av-1", "boat-1"][..], "epoch/0000000001"),
        (&["boat-1"][..], "state"),
    ]
    .into_iter()
    .enumerate()
    {
        let p = dir.join(format!("seed-{k}.redb"));
        let mut s = fleet_net::store::Store::open(&p).unwrap();
        for seq in 0..6u64 {
            for v in vehicles {
                s.commit(
                    &[((v, seq), &wire_seeds()[0])],
                    &[(meta, format!("{v} {seq}").as_bytes())],
                )
                .unwrap();
            }
        }
        s.remove_through(vehicles[0], 1, &[]).unwrap();
        let contents = (s.messages().unwrap(), s.meta_with_prefix("").unwrap());
        drop(s);
        stores.push((std::fs::read(&p).unwrap(), contents));
    }
    let seeds: Vec<Vec<u8>> = stores.iter().map(|(b, _)| b.clone()).collect();
    let case = dir.join("case.redb");
    fuzz_n("journal and outbox files", &seeds, STORE_CASES, |bytes| {
        std::fs::write(&case, bytes).unwrap();
        let read = fleet_net::store::Store::open(&case).and_then(|s| Ok((s.messages()?, s.meta_with_prefix("")?)));
        match read {
            Ok(contents) => prop_assert!(
                stores.iter().any(|(_, c)| *c == contents),
                "a damaged store opened with different data"
            ),
            Err(e) => {
                prop_assert!(e.is_bad_file(), "{}", e);
                prop_assert_eq!(
                    std::fs::read(&case).unwrap(),
                    bytes.to_vec(),
                    "the refusal changed the file"
                );
            }
        }
        Ok(())
    });

    let n = INPUTS.load(Ordering::Relaxed);
    println!(
        "fuzzed {n} generated malformed inputs across 5 decoders (wire protocol, MAVLink, mission TOML, .npy, \
        journal/outbox files): 0 panics"
    );
    assert!(n >= 100_000, "only {n} inputs");
}
