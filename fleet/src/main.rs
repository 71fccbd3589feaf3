//! `fleet`: the hetfleet command line. Each subcommand lives in its own module under `cli/`.

mod cli;

#[global_allocator]
static ALLOCATOR: fleet_math::Allocator = fleet_math::Allocator;

use clap::Parser;

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .init();
    fleet_math::configure_linalg_threads();
    let args = cli::Cli::parse();
    if let Err(e) = cli::run(args) {
        fleet_exit::fail("fleet", &e);
    }
}
