//! `fleet replay <recording.mcap> --out DIR`: the model server's core run again on a mission's
//! recorded operations, offline; the final model must equal the recorded one bit for bit.

use anyhow::{bail, Result};
use fleet::protocol::{self, Body};
use fleet_mission::recording::{CoreOp, Recording, RecordingError};
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// A recording `fleet up` (or `model-server --record`) wrote.
    pub recording: PathBuf,
    /// Write the replayed model, estimate, variance and plans here (as a run directory has them).
    #[arg(long, default_value = "fleet-replay")]
    pub out: PathBuf,
    /// Replay in time: the recorded pace times this factor (2: twice as fast); default: at once.
    #[arg(long)]
    pub speed: Option<f64>,
}

fn classify(e: RecordingError) -> anyhow::Error {
    if e.is_bad_file() {
        fleet::exit::bad_input(e)
    } else {
        e.into()
    }
}

pub fn run(args: Args) -> Result<()> {
    if let Some(s) = args.speed {
        if !(s.is_finite() && s > 0.0) {
            return Err(fleet::exit::bad_input(anyhow::anyhow!("--speed {s}: give a positive factor (1: the recorded pace)")));
        }
    }
    let rec = Recording::read(&args.recording).map_err(classify)?;
    let ops = rec.messages.iter().filter(|m| m.topic == fleet_mission::recording::CORE_TOPIC).count();
    let pb = super::progress_bar(ops as u64, "replay");
    let (mut first, start) = (None, Instant::now());
    let mut ingested = 0u64;
    let core = rec
        .replay(&args.recording, |log_ns, op| {
            if let Some(speed) = args.speed {
                let t0 = *first.get_or_insert(log_ns);
                let due = Duration::from_nanos(((log_ns.saturating_sub(t0)) as f64 / speed) as u64);
                if let Some(wait) = due.checked_sub(start.elapsed()) {
                    std::thread::sleep(wait);
                }
            }
            ingested += matches!(op, CoreOp::Ingest { .. }) as u64;
            pb.inc(1);
        })
        .map_err(classify)?;
    pb.finish_and_clear();
    fleet_mission::outputs::write(&args.out, &core, rec.mission.pace.horizon)?;
    let replayed = core.model_update().map(|m| protocol::encode(&Body::Model(m)));
    let recorded = rec.final_model().map(|m| m.data.clone());
    println!(
        "replayed {} operations of mission {} ({ingested} batches in, {} accepted, {} duplicates) into {}",
        ops,
        rec.mission.mission,
        core.counters.batches - core.counters.duplicates,
        core.counters.duplicates,
        args.out.display()
    );
    match (replayed, recorded) {
        (Some(a), Some(b)) if a == b => {
            println!("final model v{}: identical to the recorded one, bit for bit ({} bytes)", core.version, a.len());
            Ok(())
        }
        (Some(_), Some(_)) => bail!("the replayed final model (v{}) differs from the recorded one: the core is not deterministic, or the recording is not this build's", core.version),
        (None, None) => {
            println!("no model: the recording ends before the first epoch was assimilated");
            Ok(())
        }
        (Some(_), None) => bail!("the recording holds no published model, but its operations make one (v{})", core.version),
        (None, Some(_)) => bail!("the recording holds a published model, but its operations make none"),
    }
}
