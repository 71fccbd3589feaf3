#![no_main]
//! `.npy` files (datasets, truth fields).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = fleet_math::npy::from_bytes(data, "fuzz.npy");
});
