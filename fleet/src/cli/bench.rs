//! `fleet bench`: the paper's Table 1 timings, the Fig. 7 accuracy study, and the sensing
//! timings on this machine,
//! as Markdown tables (and JSON with `--out`). Timings live here, never in tests.

use anyhow::Context;
use clap::Subcommand;
use fleet::experiment::{eig_study, peers, sensing_timing, table1};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    what: What,
    /// Write the figures as JSON here.
    #[arg(long, global = true)]
    out: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
enum What {
    /// Table 1: whole online runs of batch, general and long-term DMD, four cases.
    Table1 {
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// Fig. 7: dominant eigenvalue estimates at three noise levels, with and without debiasing.
    EigStudy {
        #[arg(long, default_value_t = 10)]
        trials: usize,
        #[arg(long, default_value_t = 1234)]
        seed: u64,
    },
    /// One Table 2 row (cloud1 area-averaged to 48 x 96, 100 steps, 2 aerials, 5 boats, rank
    /// 10), excluding the simulation.
    Team {
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        /// Use this (frames, rows, cols) .npy as the truth instead of simulating cloud1.
        #[arg(long)]
        truth: Option<PathBuf>,
    },
    /// A late batch's re-fit: a long mission whose boat's backlog of its last epochs arrives at
    /// the end, re-fitted from a checkpoint and from epoch 0.
    Refit {
        #[arg(long, default_value_t = 200)]
        epochs: usize,
        #[arg(long, default_value_t = 5)]
        late: u64,
        #[arg(long, default_value = "48x96")]
        grid: String,
    },
    /// The model server's epoch at each grid size (the core without the network): from the
    /// batch that completes an epoch to the model handed out, and to every next plan answered.
    Epoch {
        /// Grid sizes, ROWSxCOLS (radius and aerial stride scale with the rows).
        #[arg(long, value_delimiter = ',', default_value = "48x96,96x192,192x384,384x768")]
        grid: Vec<String>,
        #[arg(long, default_value_t = 2)]
        aerials: usize,
        #[arg(long, default_value_t = 5)]
        boats: usize,
        /// The boats' sensing radius at 48 x 96 (cells), scaled with the rows.
        #[arg(long, default_value_t = 10.0)]
        radius: f64,
        /// Boat epochs timed at each size.
        #[arg(long, default_value_t = 10)]
        epochs: usize,
    },
    /// Our kernels beside the Python peers' on the same data in the same run, alternating:
    /// Table 1 against numpy's references, PyDMD and odmd, point QR against pysensors.
    Peers {
        /// Alternating pairs of runs per cell (after a warm-up of each side).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        /// Table 1 cases to run (1-4).
        #[arg(long, value_delimiter = ',', default_value = "1,2,3,4")]
        cases: Vec<usize>,
    },
    /// Sensor placement (point QR beside pysensors, block QR, D-optimal, horizon) and gappy timings.
    Sensing {
        #[arg(long, default_value_t = 20)]
        repeats: usize,
        /// Skip the pysensors comparison (no Python needed).
        #[arg(long)]
        no_peers: bool,
    },
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let json = match args.what {
        What::Table1 { repeats } => table1_bench(repeats)?,
        What::EigStudy { trials, seed } => eig_study_bench(trials, seed)?,
        What::Team { repeats, truth } => team_bench(repeats, truth)?,
        What::Refit { epochs, late, grid } => refit_bench(epochs, late, &grid)?,
        What::Epoch {
            grid,
            aerials,
            boats,
            radius,
            epochs,
        } => {
            let fleet = fleet::experiment::epoch_timing::Fleet { aerials, boats, radius };
            epoch_bench(&grid, fleet, epochs)?
        }
        What::Sensing { repeats, no_peers } => sensing_bench(repeats, no_peers)?,
        What::Peers { repeats, cases } => peers_bench(repeats, &cases)?,
    };
    if let Some(out) = args.out {
        std::fs::write(&out, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

/// The paper's Table 1: whole online runs with and without an eigendecomposition per update.
fn table1_bench(repeats: usize) -> anyhow::Result<serde_json::Value> {
    let total = table1::methods().len() * 2 * 4;
    let pb = super::progress_bar(total as u64, "table 1");
    let rows = table1::run(repeats, |msg| {
        pb.set_message(msg.to_string());
        pb.inc(1);
    })?;
    pb.finish_and_clear();
    println!("| case | method | eig | median s | min s | paper s | speed-up vs paper |");
    println!("|---|---|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {} | {} | {:.4} | {:.4} | {} | {:.0}x |",
            r.case,
            r.method,
            if r.with_eig { "yes" } else { "no" },
            r.median_s,
            r.min_s,
            r.paper_s,
            r.paper_s / r.median_s
        );
    }
    Ok(serde_json::to_value(rows)?)
}

/// The paper's Fig. 7 with the debiased variants.
fn eig_study_bench(trials: usize, seed: u64) -> anyhow::Result<serde_json::Value> {
    let variants = eig_study::default_variants();
    let vars = [0.01, 0.04, 0.1];
    let pb = super::progress_bar((variants.len() * vars.len() * trials) as u64, "eig study");
    let levels = eig_study::run(&variants, &vars, trials, seed, || pb.inc(1))?;
    pb.finish_and_clear();
    println!("| noise var | variant | median Re | median abs error |");
    println!("|---|---|---|---|");
    for l in &levels {
        for v in &l.variants {
            println!(
                "| {} | {} | {:.4} | {:.4} |",
                l.noise_var, v.label, v.median_real, v.median_abs_error
            );
        }
    }
    Ok(serde_json::to_value(levels)?)
}

/// One Table 2 row, timed.
fn team_bench(repeats: usize, truth: Option<PathBuf>) -> anyhow::Result<serde_json::Value> {
    use fleet::experiment::team::{self, TeamConfig};
    let full = match truth {
        Some(p) => fleet_math::process::dataset::load(&p, 1.0)?,
        None => {
            eprintln!("simulating cloud1 at 96 x 384, 100 frames (not timed)...");
            fleet_math::process::plasma::PlasmaCloud::new(fleet_math::process::plasma::Preset::Cloud1.params())?
                .run(100, |_| {})?
        }
    };
    let truth = full.area_averaged(48, 96)?;
    let cfg = TeamConfig {
        aerial_stride: 3,
        aerial_sigma0: 0.15,
        boat_sigma: 0.15,
        radius: 3.75,
        ..TeamConfig::default()
    };
    let mut ts = vec![];
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let t0 = std::time::Instant::now();
        last = Some(team::run(&cfg, &truth, |_, _| {})?);
        ts.push(t0.elapsed().as_secs_f64());
    }
    let median = eig_study::median(&mut ts);
    let o = last.expect("at least one run");
    println!(
        "one Table 2 row, {} x {} x {} steps, 2 aerials, 5 boats, general DMD rank 10: median {:.3} s over {} \
            runs (MSE heterogeneous {:.4e})",
        truth.rows,
        truth.cols,
        truth.frames(),
        median,
        ts.len(),
        o.mean_heterogeneous
    );
    Ok(serde_json::json!({ "median_s": median, "runs": ts }))
}

/// `ROWSxCOLS`.
fn grid_size(grid: &str) -> anyhow::Result<(usize, usize)> {
    grid.split_once('x')
        .and_then(|(r, c)| Some((r.parse().ok()?, c.parse().ok()?)))
        .ok_or_else(|| fleet_exit::bad_input(anyhow::anyhow!("--grid {grid}: expected ROWSxCOLS")))
}

/// The epoch's critical path at each size, as a Markdown table.
fn epoch_bench(
    grids: &[String],
    fleet: fleet::experiment::epoch_timing::Fleet,
    epochs: usize,
) -> anyhow::Result<serde_json::Value> {
    let sizes = grids.iter().map(|g| grid_size(g)).collect::<anyhow::Result<Vec<_>>>()?;
    // As the model server runs its epochs (fleet_mission::memory::small_pages_only).
    let pages = fleet_mission::memory::small_pages_only();
    eprintln!("transparent huge pages: {}", huge_pages_said(pages));
    println!(
        "| grid | vehicles | first fit (ms) | to the model out, p50 / p99 (ms) | to the plans too, p50 / p99 (ms) \
         | model put an epoch (bytes) | with its modes, on request (bytes) | batches an epoch (bytes) \
         | peak resident (MB) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut out = vec![];
    for (rows, cols) in sizes {
        eprintln!("{rows} x {cols}: {epochs} epochs...");
        let t = fleet::experiment::epoch_timing::run(rows, cols, fleet, epochs)?;
        println!(
            "| {rows} x {cols} | {} + {} | {:.0} | {:.1} / {:.1} | {:.1} / {:.1} | {} | {} | {:.0} | {} |",
            t.aerials,
            t.boats,
            t.first_fit_ms,
            t.model_p50_ms,
            t.model_p99_ms,
            t.p50_ms,
            t.p99_ms,
            t.model_bytes,
            t.model_full_bytes,
            t.batch_bytes_per_epoch,
            t.peak_resident_kb
                .map_or("?".into(), |k| format!("{:.0}", k as f64 / 1024.0))
        );
        out.push(t);
    }
    print_phases(&out);
    Ok(serde_json::to_value(out)?)
}

/// What [`fleet_mission::memory::small_pages_only`] did, in words.
fn huge_pages_said(pages: fleet_mission::memory::HugePages) -> String {
    use fleet_mission::memory::{HugePages, ALLOW_THP};
    match pages {
        HugePages::Off => "off, as the model server runs".into(),
        HugePages::AsSet => format!("as {ALLOW_THP} says"),
        HugePages::Refused => "the kernel refused to turn them off".into(),
    }
}

/// Milliseconds an epoch per phase, a column per size (nested phases indented under the
/// phase that holds them are in its figure too).
fn print_phases(runs: &[fleet::experiment::epoch_timing::EpochTiming]) {
    let mut names: Vec<&str> = vec![];
    for (name, _) in runs.iter().flat_map(|t| &t.phases_ms) {
        if !names.contains(&name.as_str()) {
            names.push(name);
        }
    }
    let sizes: Vec<String> = runs.iter().map(|t| format!("{} x {}", t.grid[0], t.grid[1])).collect();
    println!("\n| phase (ms an epoch) | {} |", sizes.join(" | "));
    println!("|---|{}", "---|".repeat(runs.len()));
    for name in names {
        let cells: Vec<String> = runs
            .iter()
            .map(|t| {
                t.phases_ms
                    .iter()
                    .find(|(n, _)| n == name)
                    .map_or("-".into(), |(_, ms)| format!("{ms:.1}"))
            })
            .collect();
        println!("| {name} | {} |", cells.join(" | "));
    }
}

/// A late batch's re-fit from a checkpoint against one from epoch 0.
fn refit_bench(epochs: usize, late: u64, grid: &str) -> anyhow::Result<serde_json::Value> {
    let (rows, cols) = grid_size(grid)?;
    eprintln!("driving a {epochs}-epoch mission twice (not timed)...");
    let t = fleet::experiment::refit_timing::run(rows, cols, epochs, late)?;
    println!(
        "{} epochs at {} x {}, boat-2's last {} epochs late: re-fit from a checkpoint {:.1} ms ({} epochs \
            again), from epoch 0 {:.1} ms ({} epochs); same model: {}",
        t.epochs,
        t.grid[0],
        t.grid[1],
        t.late_epochs,
        t.with_checkpoints_s * 1e3,
        t.with_checkpoints_epochs,
        t.from_epoch_0_s * 1e3,
        t.from_epoch_0_epochs,
        t.same_model
    );
    Ok(serde_json::to_value(t)?)
}

/// Placement and gappy timings, pysensors timed on the same basis in the same run.
fn sensing_bench(repeats: usize, no_peers: bool) -> anyhow::Result<serde_json::Value> {
    let pb = super::progress_bar(10, "sensing");
    let rows = sensing_timing::run(repeats, !no_peers, |msg| {
        pb.set_message(msg.to_string());
        pb.inc(1);
    });
    pb.finish_and_clear();
    println!("| operation | median ms | min ms | peer | peer median ms | speed-up |");
    println!("|---|---|---|---|---|---|");
    for r in &rows {
        let (peer, pm, up) = match (&r.peer, r.peer_median_ms) {
            (Some(p), Some(ms)) => (p.as_str(), format!("{ms:.3}"), format!("{:.1}x", ms / r.median_ms)),
            _ => ("", String::new(), String::new()),
        };
        println!(
            "| {} | {:.3} | {:.3} | {peer} | {pm} | {up} |",
            r.what, r.median_ms, r.min_ms
        );
    }
    Ok(serde_json::to_value(rows)?)
}

/// Ours beside the peers, one table of ratios (the peer's seconds over ours: above 1 we are
/// faster), each with its spread over the alternating pairs.
fn peers_bench(repeats: usize, cases: &[usize]) -> anyhow::Result<serde_json::Value> {
    if let Some(c) = cases.iter().find(|&&c| !(1..=4).contains(&c)) {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "--cases: {c} is not a Table 1 case (1-4)"
        )));
    }
    let total = cases.len() * 11 + 2;
    let pb = super::progress_bar(total as u64, "peers");
    let report = peers::run(repeats, cases, |msg| {
        pb.set_message(msg.to_string());
        pb.inc(1);
    })
    .map_err(|e| match e.downcast_ref::<peers::PeersError>() {
        Some(peers::PeersError::Missing(_)) => fleet_exit::bad_input(e),
        _ => e,
    })?;
    pb.finish_and_clear();
    println!(
        "Ours: {}. Peers: one BLAS thread ({}).",
        report.ours_threads,
        peer_versions(&report.peers)
    );
    let peak = report.peak_gflops_per_core;
    if let Some(p) = peak {
        println!("One core's peak here: {p:.1} GFLOP/s (clock x the vector units' flops a cycle).");
    }
    println!(
        "{} alternating pairs per cell; ratio = the peer's seconds over ours (above 1: we are faster).",
        report.repeats
    );
    println!();
    println!(concat!(
        "| cell | peer | ours median s | peer median s | ratio median [min, max] | agreement |",
        " ours GFLOP/s (of peak) |"
    ));
    println!("|---|---|---|---|---|---|---|");
    for c in &report.cells {
        let rate = match (c.gflops, peak) {
            (Some(g), Some(p)) => format!("{g:.2} ({:.0}%)", 100.0 * g / p),
            (Some(g), None) => format!("{g:.2}"),
            _ => String::new(),
        };
        let agreement = match c.ours.as_str() {
            "point_qr" => format!("{} pivots differ", c.agreement),
            _ => format!("eigenvalues {:.1e} apart", c.agreement),
        };
        let r = c.ratio;
        println!(
            "| {} | {} | {:.4} | {:.4} | {:.2}x [{:.2}, {:.2}] | {agreement} | {rate} |",
            c.what, c.peer, c.ours_median_s, c.peer_median_s, r.median, r.min, r.max
        );
    }
    let slower: Vec<&str> = report
        .cells
        .iter()
        .filter(|c| c.ratio.median < 1.0)
        .map(|c| c.what.as_str())
        .collect();
    println!();
    match slower.is_empty() {
        true => println!("No cell slower than its peer."),
        false => println!("Slower than the peer: {}.", slower.join("; ")),
    }
    Ok(serde_json::to_value(report)?)
}

/// The peers' package versions, as the worker reported them.
fn peer_versions(hello: &serde_json::Value) -> String {
    hello["versions"]
        .as_object()
        .map(|v| {
            v.iter()
                .map(|(k, v)| format!("{k} {}", v.as_str().unwrap_or("?")))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default()
}
