//! `fleet experiment [config.toml] --out <dir>`: the paper's evaluation as a report.

use anyhow::Context;
use fleet::experiment::claims;
use fleet::experiment::comparison;
use fleet::experiment::paper::{self, ExperimentConfig};
use fleet_exit::bad_input;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Experiment file (TOML).
    #[arg(default_value = "config/experiment-paper.toml")]
    config: PathBuf,
    /// Directory for report.md, the figures, results.json and timings.json.
    #[arg(long, default_value = "report")]
    out: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(&args.config)
        .map_err(|e| bad_input(anyhow::anyhow!("{}: {e}", args.config.display())))?;
    let cfg = ExperimentConfig::from_toml(&text)
        .map_err(bad_input)
        .with_context(|| args.config.display().to_string())?;
    let pb = super::progress_bar(paper::units(&cfg) as u64, "experiment");
    let t0 = std::time::Instant::now();
    let (res, truths) = paper::run(&cfg, |msg| {
        pb.set_message(msg.to_string());
        pb.inc(1);
    })?;
    pb.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    let command = format!(
        "fleet experiment {} --out {}",
        args.config.display(),
        args.out.display()
    );
    let figures = paper::write_report(&args.out, &res, &truths, &command)?;
    std::fs::write(
        args.out.join("timings.json"),
        serde_json::to_string_pretty(&serde_json::json!({ "seconds": secs }))?,
    )?;
    for r in &res.rows {
        let m = |t: &str| r.teams[t].mean;
        println!(
            "{} AV {}/{} MV {}/{} noise {}: mean MSE over {} seeds from step {}: heterogeneous {:.4e} (random disks \
                {:.4e}), aerial-only {:.4e}, boat-only {:.4e}; {}",
            r.row.name(),
            r.row.av_time,
            r.row.av_space,
            r.row.mv_time,
            r.row.mv_space,
            r.row.noise,
            r.seeds.len(),
            r.scored_from,
            m(comparison::HETEROGENEOUS),
            m(comparison::RANDOM),
            m(comparison::AERIAL_ONLY),
            m(comparison::BOAT_ONLY),
            r.comparisons
                .iter()
                .map(|c| format!("{} vs {}: {}", c.first, c.second, c.verdict.words()))
                .collect::<Vec<_>>()
                .join(", ")
        );
        let (held, checked) = claims::tally(&r.claims);
        let not_held: Vec<&str> = r
            .claims
            .iter()
            .filter(|c| c.holds == Some(false))
            .map(|c| c.claim.as_str())
            .collect();
        println!(
            "  claims held {held} of {checked} (the report's \"The claims, row by row\"){}",
            match not_held.is_empty() {
                true => String::new(),
                false => format!("; not held: {}", not_held.join("; ")),
            }
        );
    }
    println!(
        "wrote {}/report.md with {} figures ({secs:.1} s)",
        args.out.display(),
        figures.len()
    );
    Ok(())
}
