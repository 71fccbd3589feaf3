//! The model server node: a Zenoh router that takes every vehicle's measurement batches,
//! assimilates complete epochs with the same `fleet_mission::server::ServerCore` the offline
//! experiment is tested against, and publishes models, acks, plans and its own status.

mod departure;
mod node;
mod publisher;
mod replay;

#[global_allocator]
static ALLOCATOR: fleet_math::Allocator = fleet_math::Allocator;

use clap::Parser;

#[derive(Parser, Debug)]
#[command(
    name = "model-server",
    version,
    about = "hetfleet's model server: assimilates measurement batches over Zenoh and publishes models and plans"
)]
pub struct Args {
    #[command(flatten)]
    pub node: fleet_net::NodeArgs,
    /// Write one JSON event per line on stdout (for `fleet up` and scripts).
    #[arg(long)]
    pub events: bool,
    /// Write the summary (summary.json), the final model (model.cbor), the estimate and variance
    /// per step (estimate.npy, variance.npy: written as the steps are made, as .npy.part files
    /// named at the end) and the plans published (plans.json) here.
    #[arg(long)]
    pub out: Option<std::path::PathBuf>,
    /// Record the mission here (MCAP: the traffic the server saw and sent, with receive times,
    /// and its core's operations, so `fleet replay` reproduces the model). An existing file
    /// is kept: the recording goes beside it (`recording.1.mcap`, ...).
    #[arg(long)]
    pub record: Option<std::path::PathBuf>,
    /// What the recording keeps: `lean` (what `fleet replay` needs to rebuild the model bit for
    /// bit, the Foxglove channels, one model in ten and the last, compressed) or `full`
    /// (every model as published, uncompressed).
    #[arg(long, default_value = "lean")]
    pub record_mode: fleet_records::recording::RecordMode,
    /// Where the journal of accepted batches lives (`<state-dir>/<mission>.redb`); a restart
    /// replays it and carries on.
    #[arg(long, default_value = "server-state")]
    pub state_dir: std::path::PathBuf,
    /// Exit once the mission is finished and every vehicle has left, or once no batch has come
    /// for `--linger-ms` from those still here (a vehicle re-sends until its last ack arrives).
    #[arg(long)]
    pub exit_when_done: bool,
    /// With --exit-when-done: how long to wait for a vehicle still here that sends nothing
    /// (the default outlasts a vehicle's longest wait before it re-sends, 60 s).
    #[arg(long, default_value_t = departure::DEFAULT_LINGER_MS)]
    pub linger_ms: u64,
    /// Instead of serving a mission, play this recording back onto Zenoh at its recorded pace
    /// (times --speed), for a live view to follow (`fleet replay --web` starts it).
    #[arg(long)]
    pub replay: Option<std::path::PathBuf>,
    /// With --replay: the recorded pace times this factor.
    #[arg(long, default_value_t = 1.0, requires = "replay")]
    pub speed: f64,
}

fn main() {
    fleet_net::init_node();
    // Before the mission's matrices are allocated: a 2 MB page found by compaction at the
    // fault stalled the first epochs (fleet_mission::memory::small_pages_only).
    if fleet_mission::memory::small_pages_only() == fleet_mission::memory::HugePages::Refused {
        tracing::warn!("the kernel refused to turn transparent huge pages off: the first epochs may stall");
    }
    let args = Args::parse();
    match args.replay.clone() {
        Some(file) => fleet_net::run_node(
            "model-server",
            2,
            async move { replay::run(&args, &file, args.speed).await },
        ),
        None => fleet_net::run_node("model-server", 2, node::run(args)),
    }
}
