//! `fleet dmd`: fit a model online to a field and print its spectrum and errors.

use anyhow::{bail, Context};
use clap::ValueEnum;
use faer::Mat;
use fleet::experiment::run_online;
use fleet_exit::{bad_input, InputResult};
use fleet_math::dmd::{Debias, DmdConfig, Method, RankPolicy};
use fleet_math::dmd::{Forgetting, ForgettingDirections, ForgettingUnit};
use fleet_math::process::synthetic::{table1_field, EigStudy, Table1Profile, TABLE1_CASES};
use fleet_math::process::FieldSeries;
use serde_json::json;
use std::path::PathBuf;

#[derive(ValueEnum, Clone, Copy, Debug)]
enum Example {
    /// The paper's Table 1 field, case 1: 10 x 10 grid, 501 snapshots, noise variance 0.4.
    Table1,
    /// The paper's Fig. 7 field: 20 x 20 grid, 1001 snapshots, dominant eigenvalue -1, noise 0.01.
    EigStudy,
}

#[derive(ValueEnum, Clone, Copy, Debug)]
enum Layout {
    /// A 2-D array holds one snapshot per column (N x T), PyDMD's convention.
    Columns,
    /// A 2-D array holds one snapshot per row (T x N).
    Rows,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// A float64 .npy: (frames, rows, cols), or 2-D snapshots (see --layout). Without it, the
    /// bundled example is used.
    #[arg(long)]
    input: Option<PathBuf>,
    /// Bundled example field when no --input is given.
    #[arg(long, value_enum, default_value = "table1")]
    example: Example,
    #[arg(long, value_enum, default_value = "columns")]
    layout: Layout,
    /// batch | general | long-term
    #[arg(long, default_value = "general")]
    method: Method,
    /// full | optimal | energy:<f> | <integer>
    #[arg(long, default_value = "full")]
    rank: RankPolicy,
    /// Noise-robust eigenvalues: none | fb | tls (batch and general only).
    #[arg(long, default_value = "none")]
    debias: Debias,
    /// Forgetting factor of the long-term method.
    #[arg(long, default_value_t = 1.0)]
    gamma: f64,
    /// What gamma multiplies: the past once per update (batch, the paper's reading) or each
    /// pair by its age (pair, odmd's).
    #[arg(long, value_enum, default_value = "batch")]
    forgetting: ForgettingUnit,
    /// Which directions forgetting applies to: only those the new data excites (bounded), or
    /// all (odmd's; unbounded when the data does not excite every direction).
    #[arg(long, value_enum, default_value = "excited")]
    forgetting_directions: ForgettingDirections,
    /// Snapshot pairs in the initial fit (default: a fifth of the pairs, at least N for long-term).
    #[arg(long)]
    init: Option<usize>,
    /// Snapshot pairs per update.
    #[arg(long, default_value_t = 10)]
    tau: usize,
    /// Seconds between snapshots (default: the example's, or 1 for files).
    #[arg(long)]
    dt: Option<f64>,
    /// Eigenvalues to print.
    #[arg(long, default_value_t = 8)]
    top: usize,
    /// Write the model summary as JSON here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the model for numpy into this directory: eigenvalues.npy (complex128, r),
    /// modes.npy (complex128, N x r), amplitudes.npy (complex128, r, fitted to the first
    /// snapshot) and summary.json (the JSON of --out).
    #[arg(long)]
    save: Option<PathBuf>,
}

fn load(args: &Args) -> anyhow::Result<FieldSeries> {
    let Some(path) = &args.input else {
        return Ok(match args.example {
            Example::Table1 => table1_field(&TABLE1_CASES[0], Table1Profile::Sech, 0.4, 1),
            Example::EigStudy => EigStudy::field(0.01, 1234),
        });
    };
    let a = fleet_math::npy::read(path)?;
    let p = path.display().to_string();
    a.check_finite(&p)?;
    let dt = 1.0;
    Ok(match (a.shape.as_slice(), args.layout) {
        (&[t, rows, cols], _) => {
            let n = rows * cols;
            FieldSeries {
                rows,
                cols,
                dt,
                snapshots: Mat::from_fn(n, t, |i, j| a.data[j * n + i]),
            }
        }
        (&[n, t], Layout::Columns) => FieldSeries {
            rows: n,
            cols: 1,
            dt,
            snapshots: Mat::from_fn(n, t, |i, j| a.data[i * t + j]),
        },
        (&[t, n], Layout::Rows) => FieldSeries {
            rows: n,
            cols: 1,
            dt,
            snapshots: Mat::from_fn(n, t, |i, j| a.data[j * n + i]),
        },
        (s, _) => bail!("{p}: expected a 3-D (frames, rows, cols) or 2-D snapshot array, found shape {s:?}"),
    })
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let field = load(&args).input()?;
    let init = check(&args, &field).input()?;
    run_checked(args, field, init)
}

/// The arguments against the field: `--dt`, `--gamma` (long-term only), enough snapshots for
/// `--init`. Returns the initial fit's pairs.
fn check(args: &Args, field: &FieldSeries) -> anyhow::Result<usize> {
    if let Some(dt) = args.dt {
        if !(dt.is_finite() && dt > 0.0) {
            bail!("--dt must be positive, got {dt}");
        }
    }
    if !(args.gamma > 0.0 && args.gamma <= 1.0) {
        bail!("--gamma {}: a forgetting factor is in (0, 1]", args.gamma);
    }
    if args.gamma != 1.0 && args.method != Method::LongTerm {
        bail!(
            "--gamma {}: forgetting applies to --method long-term only (the {} method keeps every snapshot)",
            args.gamma,
            args.method
        );
    }
    let (n, pairs) = (field.dim(), field.frames().saturating_sub(1));
    if pairs < 2 {
        bail!("need at least 3 snapshots, got {}", field.frames());
    }
    let init = args.init.unwrap_or(match args.method {
        Method::LongTerm => n.max(pairs / 5),
        _ => (pairs / 5).max(1),
    });
    if init > pairs {
        bail!("--init {init} is more than the {pairs} snapshot pairs available");
    }
    Ok(init)
}

/// The relative error of the model's reconstruction of the whole record from its first
/// snapshot (PyDMD's convention).
fn reconstruction_error(fitted: &fleet_math::dmd::DmdModel, field: &FieldSeries) -> f64 {
    let (mut err2, mut norm2) = (0.0, 0.0);
    for t in 0..field.frames() {
        let p = fitted.predict(t as f64);
        for (a, b) in p.iter().zip(field.snapshots.col(t).iter()) {
            err2 += (a - b) * (a - b);
            norm2 += b * b;
        }
    }
    (err2 / norm2.max(f64::MIN_POSITIVE)).sqrt()
}

/// The `top` eigenvalues, discrete and continuous.
fn print_eigenvalues(summary: &fleet_math::dmd::ModelSummary, top: usize) {
    println!(
        "{:>4}  {:>24}  {:>10}  {:>26}",
        "#", "lambda (discrete)", "|lambda|", "ln(lambda)/dt"
    );
    for (i, (l, c)) in summary
        .eigenvalues
        .iter()
        .zip(&summary.continuous_eigenvalues)
        .take(top)
        .enumerate()
    {
        println!(
            "{:>4}  {:>11.6} {:>+11.6}i  {:>10.6}  {:>12.5} {:>+12.5}i",
            i + 1,
            l[0],
            l[1],
            (l[0] * l[0] + l[1] * l[1]).sqrt(),
            c[0],
            c[1]
        );
    }
}

/// `--save DIR`: the eigenvalues, modes and amplitudes as complex128 `.npy`, and the summary.
fn save_model(
    dir: &std::path::Path,
    fitted: &fleet_math::dmd::DmdModel,
    doc: &serde_json::Value,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let m = &fitted.modes.modes;
    let (rows, r) = (m.nrows(), m.ncols());
    let modes: Vec<num_complex::Complex64> = (0..rows)
        .flat_map(|i| (0..r).map(move |j| (i, j)))
        .map(|(i, j)| num_complex::Complex64::new(m[(i, j)].re, m[(i, j)].im))
        .collect();
    let c = |v: &[faer::c64]| {
        v.iter()
            .map(|z| num_complex::Complex64::new(z.re, z.im))
            .collect::<Vec<_>>()
    };
    fleet_math::npy::write(dir.join("eigenvalues.npy"), &[r], &c(&fitted.modes.eigenvalues))?;
    fleet_math::npy::write(dir.join("modes.npy"), &[rows, r], &modes)?;
    fleet_math::npy::write(dir.join("amplitudes.npy"), &[r], &c(&fitted.amplitudes))?;
    std::fs::write(dir.join("summary.json"), serde_json::to_string_pretty(&doc)?)
        .with_context(|| format!("writing {}", dir.join("summary.json").display()))?;
    println!(
        "wrote {}/eigenvalues.npy, modes.npy, amplitudes.npy and summary.json",
        dir.display()
    );
    Ok(())
}

fn run_checked(args: Args, mut field: FieldSeries, init: usize) -> anyhow::Result<()> {
    if let Some(dt) = args.dt {
        field.dt = dt;
    }
    let (n, pairs) = (field.dim(), field.frames() - 1);
    let cfg = DmdConfig {
        method: args.method,
        rank: args.rank,
        debias: args.debias,
        gamma: args.gamma,
        forgetting: Forgetting {
            unit: args.forgetting,
            directions: args.forgetting_directions,
        },
    };
    let updates = (pairs - init).div_ceil(args.tau.max(1));
    let pb = super::progress_bar(updates as u64 + 1, "assimilating");
    let t0 = std::time::Instant::now();
    let model = run_online(&cfg, field.snapshots.as_ref(), init, args.tau, |_| {
        pb.inc(1);
        Ok(())
    })
    .map_err(|e| {
        if e.is_input() {
            bad_input(e)
        } else {
            anyhow::Error::new(e)
        }
    })
    .context("fitting the model")?;
    let fit_s = t0.elapsed().as_secs_f64();
    pb.finish_and_clear();
    let modes = model.decompose()?;

    // Reconstruction from the first snapshot over the whole record (PyDMD's convention).
    let x0: Vec<f64> = field.snapshots.col(0).iter().copied().collect();
    let fitted = modes.model(&x0, field.dt)?;
    let rel = reconstruction_error(&fitted, &field);
    let summary = fitted.summary();
    println!(
        "{} DMD of {} snapshots on a {} x {} grid (N = {n}): rank {}, {} pairs assimilated in {:.1} ms ({} updates of \
            {})",
        cfg.method,
        field.frames(),
        field.rows,
        field.cols,
        model.rank(),
        model.pairs(),
        fit_s * 1e3,
        updates,
        args.tau
    );
    print_eigenvalues(&summary, args.top);
    println!("relative reconstruction error over the record (from x(0)): {rel:.4}");
    let doc = json!({
        "config": cfg, "grid": [field.rows, field.cols], "frames": field.frames(), "init": init,
        "tau": args.tau, "model": summary, "relative_reconstruction_error": rel,
    });
    if let Some(out) = &args.out {
        std::fs::write(out, serde_json::to_string_pretty(&doc)?)
            .with_context(|| format!("writing {}", out.display()))?;
        println!("wrote {}", out.display());
    }
    if let Some(dir) = &args.save {
        save_model(dir, &fitted, &doc)?;
    }
    Ok(())
}
