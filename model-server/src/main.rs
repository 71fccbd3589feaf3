//! The model server node. Its Zenoh transport comes with the fleet issue; until then it only
//! states what it will do, and exits non-zero so no script mistakes it for a running server.

fn main() {
    eprintln!(
        "model-server {}: the Zenoh node is not built yet; use `fleet dmd` for the model itself",
        env!("CARGO_PKG_VERSION")
    );
    std::process::exit(2);
}
