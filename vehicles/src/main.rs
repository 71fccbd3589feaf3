//! The vehicle node, aerial or boat: one process per vehicle of the mission file. In mixed
//! reality it senses the truth field at its own position with its own noise model and random
//! stream, follows the plans the model server gives it, and publishes its batches until they
//! are acknowledged.

#[global_allocator]
static ALLOCATOR: fleet_math::Allocator = fleet_math::Allocator;

mod node;

use clap::Parser;

#[derive(Parser, Debug)]
#[command(name = "vehicle", version, about = "hetfleet's vehicle node (aerial or boat)")]
pub struct Args {
    /// This vehicle's id in the mission (`av-1`, `boat-3`, ...).
    #[arg(long)]
    pub id: fleet_mission::roster::VehicleId,
    #[command(flatten)]
    pub node: fleet_net::NodeArgs,
    /// Where the durable outbox lives (`<state-dir>/<id>.redb`); a restart resumes from it.
    #[arg(long, default_value = "vehicle-state")]
    pub state_dir: std::path::PathBuf,
    /// Bound of the outbox on disk (MiB); when full the vehicle holds until acks make room.
    #[arg(long, default_value_t = 256)]
    pub outbox_limit_mb: u64,
    /// The autopilot: `sim`, `none`, or a MAVLink connection string (`udpin:0.0.0.0:14551`,
    /// `udpout:192.168.1.20:14550`, `tcpout:127.0.0.1:5760`, `serial:/dev/ttyACM0:57600`).
    /// Default: the mission's `[mavlink] autopilot`.
    #[arg(long)]
    pub autopilot: Option<String>,
    /// A `sim` autopilot's charge at start (mAh; default: full), as a boat launched with a
    /// pack that was not charged: a bench test of the low-battery failsafe on one vehicle.
    #[arg(long)]
    pub sim_battery_start_mah: Option<f64>,
    /// Where this vehicle's readings come from: `sim` (the mission's truth at the vehicle's
    /// fix), `stdin` or `udp:ADDR:PORT` (newline-delimited JSON from an instrument driver).
    /// Default: the mission's `[sensors]`.
    #[arg(long)]
    pub sensor: Option<String>,
    /// Give up waiting for the final acknowledgement after this long without one that moves
    /// the outbox (ms): a slow link still delivering is waited for, a silent one is not.
    #[arg(long, default_value_t = 60_000)]
    pub final_ack_ms: u64,
}

fn main() {
    fleet_net::init_node();
    let args = Args::parse();
    fleet_net::run_node("vehicle", 1, node::run(args));
}
