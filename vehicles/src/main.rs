//! The vehicle node (aerial or boat). Its Zenoh and MAVLink sides come with their issues; until
//! then it exits non-zero so no script mistakes it for a running vehicle.

fn main() {
    eprintln!("vehicle {}: the vehicle node is not built yet", env!("CARGO_PKG_VERSION"));
    std::process::exit(2);
}
