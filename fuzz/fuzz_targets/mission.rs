#![no_main]
//! Mission files.
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = fleet_mission::config::MissionConfig::from_toml(&String::from_utf8_lossy(data));
});
