//! `fleet bench peers`: our kernels beside the Python peers' on the same data in the same run.
//!
//! The peers run in one Python process ([`Worker`], `bench/peers/worker.py`, embedded in the
//! binary so the command works from any directory), started with its BLAS pinned to one thread.
//! Each cell alternates one run of ours with one of the peer's, after a warm-up of each, so a
//! machine that slows down for a minute slows both; the ratio is taken per pair (the peer's
//! seconds over ours: above 1 we are faster) and summarised by its median and range. Every
//! Table 1 cell also compares the final operators' eigenvalues (both sides fit the same
//! snapshots), and point QR its pivots, so a faster wrong answer cannot pass for a win.

use super::eig_study::median;
use super::run_online;
use super::sensing_timing::pod_basis_48x96;
use super::table1;
use anyhow::Context;
use faer::{c64, MatRef};
use fleet_math::dmd::{Dmd, DmdConfig, DmdError};
use fleet_math::process::synthetic::{table1_field, Table1Case, Table1Profile, TABLE1_CASES};
use fleet_math::sensing::qr::point_qr;
use serde::Serialize;
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::Instant;

/// The peers' scripts, written beside the data at each run.
const SCRIPTS: [(&str, &str); 3] = [
    ("worker.py", include_str!("../../../bench/peers/worker.py")),
    ("paper_table.py", include_str!("../../../bench/peers/paper_table.py")),
    ("dmd_ref.py", include_str!("../../../bench/peers/dmd_ref.py")),
];

/// What to install when a peer is missing (the test script installs the same).
pub const INSTALL: &str = "python3 -m pip install numpy scipy pydmd odmd python-sensors";

/// The environment that pins the peers' BLAS and OpenMP to one thread.
const ONE_THREAD: [&str; 4] = [
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "GOTO_NUM_THREADS",
];

/// The Python peers, one request at a time.
pub struct Worker {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
}

/// Why the peers could not be started: a missing package (or Python) is the user's to
/// install, said in one line; anything else is ours.
#[derive(Debug, thiserror::Error)]
pub enum PeersError {
    #[error("the Python peers are not installed ({0}); install them with `{INSTALL}`")]
    Missing(String),
    #[error("the Python peers failed: {0}")]
    Failed(String),
}

impl Worker {
    /// Start `worker.py` from `dir` (where [`write_scripts`] put it) and ask its versions.
    pub fn start(dir: &Path) -> Result<(Self, Value), PeersError> {
        let mut cmd = Command::new("python3");
        cmd.arg(dir.join("worker.py"))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        ONE_THREAD.iter().for_each(|k| {
            cmd.env(k, "1");
        });
        let mut child = cmd.spawn().map_err(|e| PeersError::Missing(format!("python3: {e}")))?;
        let (stdin, stdout) = (child.stdin.take(), child.stdout.take());
        let (Some(stdin), Some(stdout)) = (stdin, stdout) else {
            return Err(PeersError::Failed("no pipes to python3".into()));
        };
        let mut worker = Self {
            child,
            stdin,
            stdout: BufReader::new(stdout),
        };
        match worker.ask(json!({"op": "hello"})) {
            Ok(hello) => Ok((worker, hello)),
            Err(e) => Err(worker.why_it_stopped(e)),
        }
    }

    /// One request and its answer.
    pub fn ask(&mut self, request: Value) -> anyhow::Result<Value> {
        writeln!(self.stdin, "{request}").context("writing to the peers")?;
        let mut line = String::new();
        self.stdout.read_line(&mut line).context("reading from the peers")?;
        anyhow::ensure!(!line.is_empty(), "the peers stopped");
        let answer: Value = serde_json::from_str(&line).context("the peers' answer")?;
        if let Some(e) = answer.get("error") {
            anyhow::bail!("the peers failed on {request}: {e}");
        }
        Ok(answer)
    }

    /// The worker's own account of why it stopped.
    fn why_it_stopped(mut self, e: anyhow::Error) -> PeersError {
        let status = self.child.wait().ok().and_then(|s| s.code());
        let mut stderr = String::new();
        if let Some(mut err) = self.child.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut err, &mut stderr);
        }
        let last = stderr.lines().last().unwrap_or("").to_string();
        // 3: the worker's own "missing: <package>"; 126 and 127: the shell's word for a
        // `python3` (a pyenv shim, a wrapper) that could not run its interpreter.
        match status {
            Some(3 | 126 | 127) => PeersError::Missing(last),
            _ => PeersError::Failed(format!("{e:#}; {last}")),
        }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Write the peers' scripts into `dir`.
pub fn write_scripts(dir: &Path) -> std::io::Result<()> {
    SCRIPTS
        .iter()
        .try_for_each(|(name, text)| std::fs::write(dir.join(name), text))
}

/// One cell: our kernel and one peer's, timed alternately.
#[derive(Debug, Clone, Serialize)]
pub struct Cell {
    pub what: String,
    pub ours: String,
    pub peer: String,
    pub ours_median_s: f64,
    pub peer_median_s: f64,
    /// The peer's seconds over ours, per alternating pair: median, smallest and largest.
    pub ratio: Spread,
    /// How far the answers are apart: the eigenvalues' Hausdorff distance (Table 1) or the
    /// number of pivots that differ (point QR).
    pub agreement: f64,
    /// Floating-point operations of one run of ours, where counted, and the rate reached.
    pub flops: Option<f64>,
    pub gflops: Option<f64>,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct Spread {
    pub median: f64,
    pub min: f64,
    pub max: f64,
}

impl Spread {
    fn of(mut v: Vec<f64>) -> Self {
        let min = v.iter().copied().fold(f64::INFINITY, f64::min);
        let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        Self {
            median: median(&mut v),
            min,
            max,
        }
    }
}

/// Timings of one cell: ours and the peer's, alternating after a warm-up of each, with each
/// side's last answer.
fn alternate<A, B>(
    repeats: usize,
    mut ours: impl FnMut() -> anyhow::Result<(f64, A)>,
    mut peer: impl FnMut() -> anyhow::Result<(f64, B)>,
) -> anyhow::Result<(Vec<f64>, Vec<f64>, A, B)> {
    let (_, mut a) = ours()?;
    let (_, mut b) = peer()?;
    let (mut ts, mut ps) = (vec![], vec![]);
    for _ in 0..repeats.max(1) {
        let (t, x) = ours()?;
        let (p, y) = peer()?;
        (a, b) = (x, y);
        ts.push(t);
        ps.push(p);
    }
    Ok((ts, ps, a, b))
}

fn cell(what: String, (ours, peer): (&str, &str), (ts, ps): (Vec<f64>, Vec<f64>), agreement: f64) -> Cell {
    let ratio = Spread::of(ps.iter().zip(&ts).map(|(p, t)| p / t).collect());
    Cell {
        what,
        ours: ours.into(),
        peer: peer.into(),
        ours_median_s: median(&mut ts.clone()),
        peer_median_s: median(&mut ps.clone()),
        ratio,
        agreement,
        flops: None,
        gflops: None,
    }
}

/// The peers a Table 1 row of ours is compared with: numpy's reference of the same method
/// (the one the figures are of), and the library a researcher would use for it.
fn peers_of(method: &str, with_eig: bool) -> Vec<&'static str> {
    match (method, with_eig) {
        ("batch", true) => vec!["batch_svd", "pydmd_full"],
        ("batch", false) => vec!["batch_svd"],
        ("general", _) => vec!["general"],
        ("general-r10", _) => vec!["general_r10"],
        (_, _) => vec!["longterm", "odmd"],
    }
}

/// One whole online run of ours, timed, with the final operator's eigenvalues.
fn ours_table1(
    case: &Table1Case,
    cfg: &DmdConfig,
    with_eig: bool,
    z: MatRef<'_, f64>,
) -> anyhow::Result<(f64, Vec<c64>)> {
    let t0 = Instant::now();
    let model = run_online(cfg, z, case.init, case.tau, |m: &dyn Dmd| {
        if with_eig {
            std::hint::black_box(m.decompose()?);
        }
        Ok::<(), DmdError>(())
    })?;
    let seconds = t0.elapsed().as_secs_f64();
    Ok((seconds, model.decompose()?.eigenvalues))
}

/// Largest distance from an eigenvalue of one set to its nearest in the other, both ways.
pub fn spectrum_distance(a: &[c64], b: &[c64]) -> f64 {
    let one = |a: &[c64], b: &[c64]| {
        a.iter()
            .map(|x| b.iter().map(|y| (x - y).norm()).fold(f64::INFINITY, f64::min))
            .fold(0.0, f64::max)
    };
    one(a, b).max(one(b, a))
}

fn eigs_of(answer: &Value) -> Vec<c64> {
    answer["eigs"]
        .as_array()
        .map(|v| {
            v.iter()
                .filter_map(|p| Some(c64::new(p[0].as_f64()?, p[1].as_f64()?)))
                .collect()
        })
        .unwrap_or_default()
}

/// Every Table 1 cell (four cases; batch, general, general at rank 10, long-term; with and
/// without the eigendecomposition at every update) beside its peers.
fn table1_cells(
    worker: &mut Worker,
    dir: &Path,
    repeats: usize,
    cases: &[usize],
    progress: &mut impl FnMut(&str),
) -> anyhow::Result<Vec<Cell>> {
    let mut out = vec![];
    for &ci in cases {
        let case = &TABLE1_CASES[ci - 1];
        let field = table1_field(case, Table1Profile::Sech, 0.4, ci as u64);
        let z = field.snapshots.as_ref();
        let data = write_matrix(dir, &format!("case{ci}.npy"), z)?;
        for (label, cfg, _) in table1::methods() {
            for with_eig in [false, true] {
                for peer in peers_of(label, with_eig) {
                    let eig = if with_eig { " +eig" } else { "" };
                    progress(&format!("case {ci} {label}{eig} / {peer}"));
                    let request = json!({"op": "table1", "data": data, "init": case.init, "tau": case.tau,
                                         "peer": peer, "eig": with_eig});
                    let (ts, ps, mine, theirs) = alternate(
                        repeats,
                        || ours_table1(case, &cfg, with_eig, z),
                        || {
                            let a = worker.ask(request.clone())?;
                            Ok((a["seconds"].as_f64().unwrap_or(f64::NAN), eigs_of(&a)))
                        },
                    )?;
                    let what = format!("Table 1 case {ci}, {label}{eig}");
                    let mut c = cell(what, (label, peer), (ts, ps), spectrum_distance(&mine, &theirs));
                    c.flops = table1_flops(case, label, with_eig);
                    c.gflops = c.flops.map(|f| f / c.ours_median_s / 1e9);
                    out.push(c);
                }
            }
        }
    }
    Ok(out)
}

/// Point QR of the 48 x 96 POD basis at rank 10 and 20 beside pysensors' `QR().fit`.
fn qr_cells(
    worker: &mut Worker,
    dir: &Path,
    repeats: usize,
    progress: &mut impl FnMut(&str),
) -> anyhow::Result<Vec<Cell>> {
    let mut out = vec![];
    for r in [10, 20] {
        progress(&format!("point QR r{r} / pysensors"));
        let phi = pod_basis_48x96(r);
        let basis = write_matrix(dir, &format!("basis{r}.npy"), phi.as_ref())?;
        let request = json!({"op": "qr", "basis": basis, "k": r});
        let (ts, ps, mine, theirs) = alternate(
            repeats,
            || {
                let t0 = Instant::now();
                let (pivots, _) = point_qr(phi.as_ref(), r);
                Ok((t0.elapsed().as_secs_f64(), pivots))
            },
            || {
                let a = worker.ask(request.clone())?;
                let pivots: Vec<usize> = a["pivots"]
                    .as_array()
                    .map(|v| v.iter().filter_map(|p| p.as_u64().map(|p| p as usize)).collect())
                    .unwrap_or_default();
                Ok((a["seconds"].as_f64().unwrap_or(f64::NAN), pivots))
            },
        )?;
        let differ = mine.iter().zip(&theirs).filter(|(a, b)| a != b).count() + mine.len().abs_diff(theirs.len());
        let what = format!("point QR {} x {r}", phi.nrows());
        let mut c = cell(what, ("point_qr", "pysensors QR.fit"), (ts, ps), differ as f64);
        // r pivots, each a pass of r-long dots and updates over every cell: about 4 N r^2.
        c.flops = Some(4.0 * phi.nrows() as f64 * (r * r) as f64);
        c.gflops = c.flops.map(|f| f / c.ours_median_s / 1e9);
        out.push(c);
    }
    Ok(out)
}

/// Floating-point operations of one whole Table 1 run of ours, counted from the arithmetic
/// (the leading terms of each factorisation and product; `n` cells, `m` pairs, `tau` a batch):
/// what a cell's seconds are set against to say how near the machine's peak it runs.
pub fn table1_flops(case: &Table1Case, method: &str, with_eig: bool) -> Option<f64> {
    let n = (case.nx * case.ny) as f64;
    let tau = case.tau as f64;
    let batches: Vec<f64> = (case.init..case.pairs)
        .step_by(case.tau)
        .map(|m| (m + case.tau).min(case.pairs) as f64)
        .collect();
    let svd = |a: f64, b: f64| {
        let (big, small) = (a.max(b), a.min(b));
        4.0 * big * small * small + 8.0 * small.powi(3)
    };
    let rank = |m: f64| n.min(m);
    let eig = |r: f64| {
        if with_eig {
            10.0 * r.powi(3) + 2.0 * n * r * r
        } else {
            0.0
        }
    };
    let init = case.init as f64;
    let total = match method {
        // A thin SVD of X (n x m) and Y W S^-1, every batch from scratch.
        "batch" => std::iter::once(init)
            .chain(batches)
            .map(|m| svd(n, m) + 2.0 * n * m * rank(m) + eig(rank(m)))
            .sum(),
        // U^T X_new twice, the QR of H, the SVD of Z ((r + tau) square), U and YW carried over.
        "general" | "general-r10" => {
            let r = |m: f64| {
                if method == "general" {
                    rank(m)
                } else {
                    10.0_f64.min(rank(m))
                }
            };
            svd(n, init)
                + batches
                    .iter()
                    .map(|&m| {
                        let r = r(m);
                        8.0 * n * r * tau
                            + 4.0 * n * tau * tau
                            + svd(r + tau, r + tau)
                            + 4.0 * n * (r + tau) * r
                            + eig(r)
                    })
                    .sum::<f64>()
        }
        // The Woodbury update: A X_new, the tau x tau solve, and the n x n rank-tau updates.
        "long-term" => {
            2.0 * n * n * init
                + n.powi(3)
                + batches
                    .iter()
                    .map(|_| 6.0 * n * n * tau + 2.0 * n * tau * tau + tau.powi(3) + eig(n))
                    .sum::<f64>()
        }
        _ => return None,
    };
    Some(total)
}

/// A matrix as `.npy` in `dir` (row-major, as numpy reads it by default), its path as text.
fn write_matrix(dir: &Path, name: &str, m: MatRef<'_, f64>) -> anyhow::Result<String> {
    let path = dir.join(name);
    let data: Vec<f64> = (0..m.nrows())
        .flat_map(|i| (0..m.ncols()).map(move |j| m[(i, j)]))
        .collect();
    fleet_math::npy::write(&path, &[m.nrows(), m.ncols()], &data)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(path.display().to_string())
}

/// What `fleet bench peers` measured: every cell, and the peers' versions and BLAS.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub repeats: usize,
    pub ours_threads: String,
    /// One core's peak double-precision rate (GFLOP/s, [`peak_per_core`]).
    pub peak_gflops_per_core: Option<f64>,
    pub peers: Value,
    pub cells: Vec<Cell>,
}

/// A scratch directory for the data and scripts, removed when dropped.
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Every cell, `repeats` alternating pairs each, over the Table 1 `cases` (1-4).
pub fn run(repeats: usize, cases: &[usize], mut progress: impl FnMut(&str)) -> anyhow::Result<Report> {
    let dir = Scratch(std::env::temp_dir().join(format!("hetfleet-peers-{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).with_context(|| format!("creating {}", dir.0.display()))?;
    write_scripts(&dir.0).context("writing the peers' scripts")?;
    let (mut worker, hello) = Worker::start(&dir.0)?;
    let mut cells = table1_cells(&mut worker, &dir.0, repeats, cases, &mut progress)?;
    cells.extend(qr_cells(&mut worker, &dir.0, repeats, &mut progress)?);
    Ok(Report {
        repeats,
        ours_threads: ours_threads(),
        peak_gflops_per_core: peak_per_core(),
        peers: hello,
        cells,
    })
}

/// How our kernels ran: faer's global parallelism as the server sets it.
fn ours_threads() -> String {
    match faer::get_global_parallelism() {
        faer::Par::Seq => "faer sequential (HETFLEET_LINALG_THREADS=1, the server's default)".into(),
        faer::Par::Rayon(n) => format!("faer on {n} threads (HETFLEET_LINALG_THREADS)"),
    }
}

/// One core's peak double-precision rate on this machine (GFLOP/s), from `/proc/cpuinfo`: its
/// clock times the flops a cycle its vector units can issue (two fused multiply-adds of 4 lanes
/// with AVX2 and FMA, of 8 with AVX-512, else two 2-lane SSE2 operations). `None` off Linux.
pub fn peak_per_core() -> Option<f64> {
    let info = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let field = |name: &str| {
        info.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
    };
    let mhz: f64 = field("cpu MHz")?.parse().ok()?;
    let flags = field("flags").unwrap_or_default();
    let has = |f: &str| flags.split_whitespace().any(|x| x == f);
    let per_cycle = match (has("avx512f"), has("avx2") && has("fma")) {
        (true, _) => 32.0,
        (false, true) => 16.0,
        _ => 4.0,
    };
    Some(mhz * 1e-3 * per_cycle)
}
