//! Subcommands of the `fleet` binary.

mod assimilate;
mod bench;
mod dmd;
mod experiment;
mod export;
mod render;
mod replay;
mod schema;
mod secure;
mod simulate;
mod supervise;
mod up;

use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "fleet",
    version,
    about = "hetfleet: a heterogeneous robot team models, predicts and samples a changing field"
)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Fit a DMD model (batch, general or long-term online) to a field and report its spectrum.
    Dmd(dmd::Args),
    /// Measure the paper's timing and accuracy studies on this machine.
    Bench(bench::Args),
    /// Generate a truth field (plasma cloud, synthetic fields) as .npy plus a JSON sidecar.
    Simulate(simulate::Args),
    /// Draw a frame of a field (.npy) as a PNG, or the whole sequence as a GIF.
    Render(render::Args),
    /// The paper's evaluation end to end (Table 2, Figs. 7, 8, 10, 11) as a report.
    Experiment(experiment::Args),
    /// Run a mission: the model server and every vehicle as processes over Zenoh, with a report.
    Up(up::Args),
    /// A finished run as NetCDF, GeoTIFF or QGroundControl plans.
    Export(export::Args),
    /// Run the model server's core again on a mission's recording; the final model must match.
    Replay(replay::Args),
    /// A mission's logged readings assimilated after the fact: the model a live run makes of them.
    Assimilate(assimilate::Args),
    /// Zenoh configs of a secured mission: passwords, mutual TLS, access control per vehicle.
    Secure(secure::Args),
    /// The JSON Schema of the mission or experiment file (for editors that check TOML).
    Schema(schema::Args),
    /// A reference page made from the code, in Markdown (`files`: every key of both files).
    Reference(schema::ReferenceArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Dmd(a) => dmd::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Simulate(a) => simulate::run(a),
        Command::Render(a) => render::run(a),
        Command::Experiment(a) => experiment::run(a),
        Command::Up(a) => up::run(a),
        Command::Export(a) => export::run(a),
        Command::Replay(a) => replay::run(a),
        Command::Assimilate(a) => assimilate::run(a),
        Command::Secure(a) => secure::run(a),
        Command::Schema(a) => schema::run(a),
        Command::Reference(a) => schema::reference(a),
    }
}

/// A progress bar on stderr that stays quiet when stderr is not a terminal.
pub fn progress_bar(len: u64, what: &str) -> indicatif::ProgressBar {
    let pb = indicatif::ProgressBar::new(len);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({elapsed}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    pb
}
