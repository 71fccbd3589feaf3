#![no_main]
//! MAVLink frames as the bridge and the ground-station gateway read them.
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = vehicles::link::parse_frame(data);
});
