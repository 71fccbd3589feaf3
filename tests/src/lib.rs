//! Helpers for the cross-process tests: where the workspace's binaries and reference data are.

use std::path::PathBuf;
use std::process::{Command, Output};

/// The workspace root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// Path of a workspace binary built in the same profile as this test (`cargo test --release`
/// builds it into the same target directory).
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe.parent().and_then(|d| d.parent()).expect("target dir");
    dir.join(name)
}

/// Run a workspace binary with arguments, from the workspace root.
pub fn run(name: &str, args: &[&str]) -> Output {
    let path = bin(name);
    Command::new(&path)
        .args(args)
        .current_dir(root())
        .output()
        .unwrap_or_else(|e| panic!("cannot start {}: {e} (build it with `cargo build --release --workspace`)", path.display()))
}
