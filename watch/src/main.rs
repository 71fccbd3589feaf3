//! `fleet-watch`: the live operations view (see the crate's documentation).

#[global_allocator]
static ALLOCATOR: fleet_math::Allocator = fleet_math::Allocator;

use clap::Parser;

fn main() {
    fleet_net::init_node();
    let args = watch::node::Args::parse();
    fleet_net::run_node("fleet-watch", 2, watch::node::run(args));
}
