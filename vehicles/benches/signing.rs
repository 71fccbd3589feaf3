//! What MAVLink 2 signing costs per frame: a GLOBAL_POSITION_INT (the most frequent message,
//! 10 Hz per vehicle) framed unsigned, framed and signed, and a signed frame checked (a fresh
//! frame each time, as the replay check needs a newer timestamp).

use criterion::{criterion_group, criterion_main, Criterion};
use fleet_mission::signing_key::SigningKey;
use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use std::hint::black_box;
use vehicles::link::frame_bytes;
use vehicles::signing::{LinkSigning, LINK_AUTOPILOT, LINK_BRIDGE};

fn signing(c: &mut Criterion) {
    let msg = MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
        lat: 556_761_000,
        lon: 125_683_000,
        hdg: 9000,
        ..Default::default()
    });
    let h = MavHeader {
        system_id: 3,
        component_id: 1,
        sequence: 0,
    };
    let key = SigningKey::from_passphrase("bench");
    let (autopilot, bridge) = (
        LinkSigning::new(key.clone(), LINK_AUTOPILOT, false),
        LinkSigning::new(key, LINK_BRIDGE, false),
    );
    c.bench_function("frame unsigned", |b| {
        b.iter(|| frame_bytes(black_box(h), black_box(&msg)))
    });
    c.bench_function("frame signed", |b| {
        b.iter(|| autopilot.frame(black_box(h), black_box(&msg)))
    });
    c.bench_function("frame signed, then checked", |b| {
        b.iter(|| {
            let f = autopilot.frame(h, &msg);
            bridge
                .check(black_box(f.raw_bytes()))
                .expect("a fresh signed frame passes")
        })
    });
}

criterion_group!(benches, signing);
criterion_main!(benches);
