//! How big a boat's outbox grows on disk while it is cut off from the server.
//!
//! Takes the real sizes from a finished run (`fleet up --out DIR`: the server's journal and a
//! boat's outbox under `DIR/state/`): the mean encoded boat batch, and the vehicle state the
//! boat commits with each batch. Then commits one such batch (and state) per boat epoch to a
//! fresh store, as a disconnected boat does, and prints the file's size as the hours go by.
//!
//! `cargo run --release -p fleet-net --example outbox_growth -- DIR/state/default.redb
//! DIR/state/boat-1.redb --epoch-s 5 --hours 1`

use clap::Parser;
use fleet_net::store::Store;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    /// The server's journal of a finished run.
    journal: PathBuf,
    /// A boat's outbox of the same run (for the size of its committed state).
    outbox: PathBuf,
    /// Seconds between a boat's batches in the field.
    #[arg(long, default_value_t = 5.0)]
    epoch_s: f64,
    #[arg(long, default_value_t = 1.0)]
    hours: f64,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let journal = Store::open(&args.journal)?;
    let boats: Vec<Vec<u8>> = journal
        .messages()?
        .into_iter()
        .filter(|((v, _), _)| v.starts_with("boat"))
        .map(|(_, b)| b)
        .collect();
    anyhow::ensure!(!boats.is_empty(), "no boat batches in {}", args.journal.display());
    let mean = boats.iter().map(Vec::len).sum::<usize>() / boats.len();
    let batch = boats
        .iter()
        .min_by_key(|b| b.len().abs_diff(mean))
        .expect("not empty")
        .clone();
    let state = Store::open(&args.outbox)?.meta("state")?.unwrap_or_default();
    let n = (args.hours * 3600.0 / args.epoch_s).round() as u64;
    println!(
        "boat batch {} bytes (mean of {}), state {} bytes; {n} batches in {} h at one per {} s",
        batch.len(),
        boats.len(),
        state.len(),
        args.hours,
        args.epoch_s
    );
    let dir = std::env::temp_dir().join(format!("outbox-growth-{}", std::process::id()));
    let mut store = Store::open(&dir.join("boat.redb"))?;
    for seq in 1..=n {
        store.commit(&[(("boat-1", seq), &batch)], &[("state", &state)])?;
        if seq == n || seq % (n / 4).max(1) == 0 {
            let file = std::fs::metadata(store.path())?.len();
            println!(
                "{seq:>6} batches held: file {:>10} bytes ({:.0} bytes per batch; payload {} bytes)",
                file,
                file as f64 / seq as f64,
                store.size().0
            );
        }
    }
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}
