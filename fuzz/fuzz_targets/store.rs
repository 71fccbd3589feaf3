#![no_main]
//! The nodes' state files (a server's journal, a vehicle's outbox): opened and read whole.
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::env::temp_dir().join(format!("hetfleet-fuzz-store-{}.redb", std::process::id()));
    std::fs::write(&path, data).unwrap();
    if let Ok(s) = fleet_net::store::Store::open(&path) {
        let _ = s.messages();
        let _ = s.meta_with_prefix("");
    }
    let _ = std::fs::remove_file(&path);
});
