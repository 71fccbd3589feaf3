#![no_main]
//! Zenoh payloads: decode and validate against a small grid with known vehicles.
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut ctx = fleet_mission::protocol::Context::new(fleet_math::grid::Grid::new(6, 8, 1.0).unwrap());
    ctx.vehicles = vec!["boat-1".into(), "av-1".into()];
    let _ = fleet_mission::protocol::decode(data, &ctx);
});
