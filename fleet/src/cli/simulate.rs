//! `fleet simulate`: generate a truth field as a `(frames, rows, cols)` `.npy` plus a JSON
//! sidecar of every parameter.

use anyhow::{bail, Context};
use clap::ValueEnum;
use fleet_exit::InputResult;
use fleet_math::process::plasma::{PlasmaCloud, Preset};
use fleet_math::process::synthetic::{plume_field, table1_field, EigStudy, Table1Profile, TABLE1_CASES};
use fleet_math::process::{dataset, FieldSeries};
use serde_json::json;
use std::path::PathBuf;

#[derive(ValueEnum, Clone, Copy, Debug, PartialEq)]
enum Process {
    /// The plasma-cloud simulator (docs/simulator.md).
    PlasmaCloud,
    /// The paper's Table 1 timing field (cosh(x) cosh(y) times a damped oscillation).
    Table1,
    /// The Fig. 7 eigenvalue study's field (dominant continuous-time eigenvalue -1).
    EigStudy,
    /// A moving, rotating Gaussian plume.
    Plume,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to simulate (also accepted as --process).
    #[arg(value_enum)]
    process: Option<Process>,
    #[arg(long = "process", value_enum, id = "process_flag")]
    process_flag: Option<Process>,
    /// Plasma cloud preset.
    #[arg(long, value_enum, default_value = "cloud1")]
    preset: Preset,
    /// Grid as ROWSxCOLS (plasma cloud: rows along y, cols along the drift; default 96x384;
    /// plume: default 48x96).
    #[arg(long)]
    grid: Option<String>,
    /// Frames to write (plasma cloud default 100; plume default 100).
    #[arg(long)]
    frames: Option<usize>,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Table 1 case 1-4.
    #[arg(long, default_value_t = 1)]
    case: usize,
    /// Measurement noise variance added to the synthetic fields.
    #[arg(long, default_value_t = 0.0)]
    noise: f64,
    /// Output .npy (the sidecar goes beside it as .json).
    #[arg(long)]
    out: PathBuf,
}

fn parse_grid(s: &str) -> anyhow::Result<(usize, usize)> {
    let (r, c) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--grid {s:?}: expected ROWSxCOLS, e.g. 96x384"))?;
    let (r, c): (usize, usize) = (
        r.trim().parse().context("--grid rows")?,
        c.trim().parse().context("--grid cols")?,
    );
    if r == 0 || c == 0 {
        bail!("--grid {s:?}: rows and cols must be positive");
    }
    Ok((r, c))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    simulate(args).input()
}

/// The plasma cloud at the preset's parameters (with `--seed`, `--grid`, `--frames`), and its
/// sidecar: the parameters, the frames' times and the solver's statistics.
fn plasma_cloud(args: &Args, t0: std::time::Instant) -> anyhow::Result<(FieldSeries, serde_json::Value)> {
    let mut params = args.preset.params();
    params.seed = args.seed;
    if let Some(g) = &args.grid {
        let (rows, cols) = parse_grid(g)?;
        (params.ny, params.nx) = (rows, cols);
    }
    let frames = args.frames.unwrap_or(100);
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    fleet_math::process::check_size(params.ny, params.nx, frames)
        .map_err(|e| anyhow::anyhow!("--grid/--frames: {e}"))?;
    let mut sim = PlasmaCloud::new(params.clone()).context("setting up the plasma cloud")?;
    let pb = super::progress_bar(frames as u64, "plasma cloud");
    let field = sim
        .run(frames, |k| {
            pb.set_message(format!("t = {:.2}", k as f64 * params.out_dt));
            pb.inc(1);
        })
        .context("simulating")?;
    pb.finish_and_clear();
    let stats = sim.solver_stats();
    let secs = t0.elapsed().as_secs_f64();
    eprintln!(
        "{} steps, {} potential solves, {:.1} CG iterations per solve (max {}), {:.1} s",
        sim.steps,
        stats.solves,
        stats.iterations as f64 / stats.solves.max(1) as f64,
        stats.max_iterations,
        secs
    );
    let meta = json!({
        "process": "plasma-cloud", "preset": args.preset, "params": params, "frames": frames,
        "shape": [frames, params.ny, params.nx], "ly": params.ly(), "h": params.h(),
        "frame_times": (0..frames).map(|k| k as f64 * params.out_dt).collect::<Vec<_>>(),
        "steps": sim.steps, "solver": stats, "seconds": secs,
        "units": "nondimensional: length a (cloud e-folding radius), time a/V0, density N/N_peak",
    });
    Ok((field, meta))
}

/// Every error here is the arguments' (the simulators refuse what they cannot do).
fn simulate(args: Args) -> anyhow::Result<()> {
    let process = match (args.process, args.process_flag) {
        (Some(a), Some(b)) if a != b => bail!("two different processes given ({a:?} and {b:?})"),
        (Some(a), _) | (None, Some(a)) => a,
        (None, None) => bail!("say what to simulate: plasma-cloud | table1 | eig-study | plume"),
    };
    if !(args.noise.is_finite() && args.noise >= 0.0) {
        bail!("--noise must be a variance >= 0, got {}", args.noise);
    }
    let t0 = std::time::Instant::now();
    let (field, meta): (FieldSeries, serde_json::Value) = match process {
        Process::PlasmaCloud => plasma_cloud(&args, t0)?,
        Process::Table1 => {
            let case = TABLE1_CASES
                .get(args.case.wrapping_sub(1))
                .with_context(|| format!("--case must be 1-4, got {}", args.case))?;
            let f = table1_field(case, Table1Profile::Cosh, args.noise, args.seed);
            let meta = json!({
                "process": "table1", "case": args.case, "profile": "cosh", "noise_var": args.noise,
                "seed": args.seed, "pairs": case.pairs, "grid": [case.ny, case.nx], "dt": f.dt
            });
            (f, meta)
        }
        Process::EigStudy => {
            let f = EigStudy::field(args.noise, args.seed);
            let meta = json!({"process": "eig-study", "noise_var": args.noise, "seed": args.seed, "dt": f.dt,
                "true_dominant_continuous_eigenvalue": EigStudy::TRUE_EIGENVALUE});
            (f, meta)
        }
        Process::Plume => {
            let (rows, cols) = match &args.grid {
                Some(g) => parse_grid(g)?,
                None => (48, 96),
            };
            let frames = args.frames.unwrap_or(100);
            if frames == 0 {
                bail!("--frames must be at least 1");
            }
            fleet_math::process::check_size(rows, cols, frames).map_err(|e| anyhow::anyhow!("--grid/--frames: {e}"))?;
            let f = plume_field(rows, cols, frames, args.noise, args.seed);
            let meta = json!({
                "process": "plume", "grid": [rows, cols], "frames": frames, "noise_var": args.noise,
                "seed": args.seed, "dt": f.dt
            });
            (f, meta)
        }
    };
    dataset::save(&args.out, &field, Some(&meta))?;
    println!(
        "wrote {} ({} frames of {} x {}) and {}",
        args.out.display(),
        field.frames(),
        field.rows,
        field.cols,
        dataset::sidecar_path(&args.out).display()
    );
    Ok(())
}
