//! `fleet experiment`: the paper's evaluation end to end from one TOML file — Table 2 (MSE of
//! heterogeneous, aerial-only and boat-only teams, QR versus random placement), Fig. 10 (MSE
//! over time), Fig. 11 (truth beside reconstruction with the boats' disks), Fig. 7 (dominant
//! eigenvalue estimates, box plots) and Fig. 8 (forgetting factor) — as `report.md`, PNG
//! figures and `results.json`. Same file and seed, same JSON, byte for byte (timings go to
//! `timings.json`).

use super::team::{self, Placement, TeamConfig, TeamOutcome};
use super::{dominant_continuous, eig_study, run_online};
use crate::dmd::{DmdConfig, Method, RankPolicy};
use crate::grid::area_average;
use crate::plot::{self, Panel, Series};
use crate::process::plasma::Preset;
use crate::process::truth::{averaged_by, TruthSource};
use crate::process::synthetic::EigStudy;
use crate::process::FieldSeries;
use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// One row of Table 2: sampling rates in time (steps) and space (cells of the simulator's grid)
/// for aerials (AV) and boats (MV), and the noise standard deviation of both.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Row {
    /// The simulator's cloud, or
    #[serde(default)]
    pub preset: Option<Preset>,
    /// a `(frames, rows, cols)` `.npy` dataset as the truth (at the simulator grid's scale:
    /// it is area-averaged by `mv_space` like the simulator's output).
    #[serde(default)]
    pub dataset: Option<std::path::PathBuf>,
    pub av_time: usize,
    pub mv_time: usize,
    pub av_space: usize,
    pub mv_space: usize,
    pub noise: f64,
    /// The paper's MSE for this row, when it has one (shown beside ours).
    #[serde(default)]
    pub paper_mse: Option<f64>,
}

/// The experiment file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExperimentConfig {
    pub seed: u64,
    /// Simulator grid `[rows, cols]` and frames.
    pub truth_grid: [usize; 2],
    pub frames: usize,
    /// Boats' sensing radius in simulator cells (divided by `mv_space` on the model grid).
    pub radius: f64,
    /// Everything else of the team (rates, noise and radius come from the rows).
    #[serde(default)]
    pub team: TeamConfig,
    #[serde(rename = "row")]
    pub rows: Vec<Row>,
    /// Trials per noise level of the eigenvalue study (0 skips Fig. 7).
    #[serde(default)]
    pub eig_trials: usize,
    /// Forgetting factors of Fig. 8 (empty skips it).
    #[serde(default)]
    pub forgetting: Vec<f64>,
}

impl Row {
    /// The truth's name in tables and figure files: the preset (`Cloud1`) or the file stem.
    pub fn name(&self) -> String {
        match (&self.preset, &self.dataset) {
            (Some(p), _) => format!("{p:?}"),
            (None, Some(d)) => d.file_stem().map_or("dataset".into(), |s| s.to_string_lossy().to_string()),
            (None, None) => "?".into(),
        }
    }
}

impl ExperimentConfig {
    pub fn from_toml(text: &str) -> anyhow::Result<Self> {
        let cfg: Self = toml::from_str(text).map_err(|e| anyhow::anyhow!(crate::exit::toml_error(text, &e)))?;
        if cfg.rows.is_empty() {
            bail!("the experiment has no [[row]]");
        }
        for (i, r) in cfg.rows.iter().enumerate() {
            let r_ = format!("[[row]] {} ({})", i + 1, r.name());
            if r.preset.is_some() == r.dataset.is_some() {
                bail!("{r_}: give exactly one of preset or dataset");
            }
            if r.av_time == 0 || r.mv_time == 0 || r.av_space == 0 || r.mv_space == 0 || r.av_space % r.mv_space != 0 {
                bail!("{r_}: rates must be >= 1 and av_space a multiple of mv_space");
            }
            if !(r.noise.is_finite() && r.noise >= 0.0) {
                bail!("{r_}: noise must be >= 0");
            }
            if cfg.truth_grid[0] / r.mv_space < 4 || cfg.truth_grid[1] / r.mv_space < 4 {
                bail!("{r_}: the model grid would be smaller than 4 x 4");
            }
        }
        if cfg.frames < 10 || cfg.truth_grid.iter().any(|&n| n < 8) {
            bail!("need at least 10 frames and an 8 x 8 simulator grid");
        }
        if cfg.forgetting.iter().any(|g| !(*g > 0.0 && *g <= 1.0)) {
            bail!("forgetting factors must be in (0, 1]");
        }
        Ok(cfg)
    }

    /// The team of one row.
    pub fn team_for(&self, r: &Row, placement: Placement) -> TeamConfig {
        TeamConfig {
            aerial_period: r.av_time,
            boat_period: r.mv_time,
            aerial_stride: r.av_space / r.mv_space,
            aerial_sigma0: r.noise,
            boat_sigma: r.noise,
            radius: self.radius / r.mv_space as f64,
            placement,
            seed: self.seed,
            ..self.team.clone()
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct RowResult {
    pub row: Row,
    pub model_grid: [usize; 2],
    pub qr: TeamOutcome,
    pub random: TeamOutcome,
}

#[derive(Debug, Clone, Serialize)]
pub struct EigBox {
    pub method: String,
    pub noise_var: f64,
    pub estimates: Vec<[f64; 2]>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ForgettingCurve {
    pub label: String,
    /// (pairs assimilated, dominant continuous-time eigenvalue real part)
    pub points: Vec<(f64, f64)>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Results {
    pub config: ExperimentConfig,
    pub rows: Vec<RowResult>,
    pub eig_study: Vec<EigBox>,
    pub forgetting: Vec<ForgettingCurve>,
    pub verdict: Verdict,
}

/// The two claims the paper makes, checked on the most complex preset run.
#[derive(Debug, Clone, Serialize)]
pub struct Verdict {
    /// The row's truth (the most complex preset run, else the first dataset).
    pub preset: Option<String>,
    pub heterogeneous_beats_both: Option<bool>,
    pub qr_beats_random: Option<bool>,
}

/// The truth of a row on its model grid: the simulator at `truth_grid` (or the dataset),
/// area-averaged by `mv_space`.
fn truth_for(cfg: &ExperimentConfig, row: &Row, cache: &mut BTreeMap<String, FieldSeries>) -> anyhow::Result<FieldSeries> {
    let key = row.name();
    if !cache.contains_key(&key) {
        let source = TruthSource { preset: row.preset, dataset: row.dataset.clone() };
        cache.insert(key.clone(), source.full(cfg.truth_grid, cfg.frames, cfg.seed, |_| {}).with_context(|| key.clone())?);
    }
    averaged_by(&cache[&key], row.mv_space).with_context(|| key.clone())
}

fn rank_of(p: Preset) -> u8 {
    match p {
        Preset::Cloud2 => 0,
        Preset::Cloud1 => 1,
        Preset::Cloud10 => 2,
    }
}

/// Run everything; `progress(message)` is called as work proceeds (for a progress bar), and
/// `units()` tells how many calls to expect.
pub fn run(cfg: &ExperimentConfig, mut progress: impl FnMut(&str)) -> anyhow::Result<(Results, BTreeMap<String, FieldSeries>)> {
    let mut cache = BTreeMap::new();
    let mut rows = vec![];
    for r in &cfg.rows {
        progress(&format!("{} {}/{} {}/{}", r.name(), r.av_time, r.mv_time, r.av_space, r.mv_space));
        let truth = truth_for(cfg, r, &mut cache)?;
        let qr = team::run(&cfg.team_for(r, Placement::Qr), &truth, |_, _| {})?;
        let random = team::run(&cfg.team_for(r, Placement::Random), &truth, |_, _| {})?;
        rows.push(RowResult { row: r.clone(), model_grid: [truth.rows, truth.cols], qr, random });
    }
    let mut eig = vec![];
    if cfg.eig_trials > 0 {
        let methods = [("batch", Method::Batch), ("general", Method::General), ("long-term", Method::LongTerm)];
        for (level, var) in [0.01, 0.04, 0.1].into_iter().enumerate() {
            for (label, method) in methods {
                progress(&format!("Fig. 7 {label} var {var}"));
                let v = eig_study::Variant::new(label, method, RankPolicy::Full, Default::default(), 1.0);
                let estimates = (0..cfg.eig_trials)
                    .map(|t| eig_study::estimate(&v, var, eig_study::trial_seed(cfg.seed, level, t)))
                    .collect::<Result<Vec<_>, _>>()?;
                eig.push(EigBox { method: label.into(), noise_var: var, estimates });
            }
        }
    }
    let mut forgetting = vec![];
    if !cfg.forgetting.is_empty() {
        let field = EigStudy::field(0.01, cfg.seed);
        let z = field.snapshots.as_ref();
        let mut curves: Vec<(String, DmdConfig)> =
            vec![("batch".into(), DmdConfig { method: Method::Batch, rank: RankPolicy::Full, debias: Default::default(), gamma: 1.0 })];
        for &g in &cfg.forgetting {
            curves.push((format!("long-term gamma {g}"), DmdConfig { method: Method::LongTerm, rank: RankPolicy::Full, debias: Default::default(), gamma: g }));
        }
        for (label, c) in curves {
            progress(&format!("Fig. 8 {label}"));
            let mut points = vec![];
            run_online(&c, z, EigStudy::INIT, 60, |m| {
                // From the first update on: the initial fit of 400 pairs on a 400-cell grid is
                // square and fits the noise (its dominant eigenvalue is a spurious growing mode).
                if m.pairs() == EigStudy::INIT {
                    return Ok(());
                }
                let modes = m.decompose()?;
                if let Some(l) = dominant_continuous(&modes, field.dt) {
                    points.push((m.pairs() as f64, l.re));
                }
                Ok(())
            })?;
            forgetting.push(ForgettingCurve { label, points });
        }
    }
    let top = rows.iter().filter_map(|r| r.row.preset).max_by_key(|p| rank_of(*p));
    let first_of_top = match top {
        Some(p) => rows.iter().find(|r| r.row.preset == Some(p)),
        None => rows.first(),
    };
    let verdict = Verdict {
        preset: first_of_top.map(|r| r.row.name()),
        heterogeneous_beats_both: first_of_top.map(|r| r.qr.mean_heterogeneous < r.qr.mean_aerial_only && r.qr.mean_heterogeneous < r.qr.mean_boat_only),
        qr_beats_random: first_of_top.map(|r| r.qr.mean_heterogeneous < r.random.mean_heterogeneous),
    };
    Ok((Results { config: cfg.clone(), rows, eig_study: eig, forgetting, verdict }, cache))
}

/// Work units `run` reports, for a progress bar.
pub fn units(cfg: &ExperimentConfig) -> usize {
    cfg.rows.len() + if cfg.eig_trials > 0 { 9 } else { 0 } + if cfg.forgetting.is_empty() { 0 } else { cfg.forgetting.len() + 1 }
}

/// Write `results.json`, the figures and `report.md` into `dir`.
pub fn write_report(dir: &Path, res: &Results, truths: &BTreeMap<String, FieldSeries>, command: &str) -> anyhow::Result<Vec<String>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    std::fs::write(dir.join("results.json"), serde_json::to_string_pretty(res)?)?;
    let mut figures = vec![];
    let mut md = String::new();
    writeln!(md, "# hetfleet experiment report\n")?;
    writeln!(md, "Made by `{command}` (seed {}). Every number is in `results.json`.\n", res.config.seed)?;
    writeln!(
        md,
        "Truth: the plasma-cloud simulator at {} x {}, {} frames, area-averaged by the boats' space rate to the model grid. \
         Team: {} aerials, {} boats of radius {} simulator cells, {} DMD at rank `{}`, `{}` fusion, {} initial aerial-only steps. \
         MSE is averaged over the grid and over the steps after initialisation.\n",
        res.config.truth_grid[0],
        res.config.truth_grid[1],
        res.config.frames,
        res.config.team.aerials,
        res.config.team.boats,
        res.config.radius,
        res.config.team.method,
        res.config.team.rank,
        res.config.team.fusion,
        res.config.team.init_steps
    )?;
    writeln!(md, "## Table 2: time-averaged MSE\n")?;
    writeln!(md, "| cloud | AV time | MV time | AV space | MV space | noise | model grid | heterogeneous (QR) | aerial-only | boat-only | heterogeneous (random) | paper |")?;
    writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|")?;
    for r in &res.rows {
        let w = &r.row;
        writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} x {} | {:.4e} | {:.4e} | {:.4e} | {:.4e} | {} |",
            w.name(),
            w.av_time,
            w.mv_time,
            w.av_space,
            w.mv_space,
            w.noise,
            r.model_grid[0],
            r.model_grid[1],
            r.qr.mean_heterogeneous,
            r.qr.mean_aerial_only,
            r.qr.mean_boat_only,
            r.random.mean_heterogeneous,
            w.paper_mse.map_or("".into(), |v| format!("{v}"))
        )?;
    }
    let v = &res.verdict;
    writeln!(md)?;
    if let (Some(p), Some(h), Some(q)) = (&v.preset, v.heterogeneous_beats_both, v.qr_beats_random) {
        writeln!(
            md,
            "On the most complex cloud run ({p}, first row): the heterogeneous team's MSE is {} both homogeneous teams', and QR placement {} random placement.\n",
            if h { "below" } else { "**not** below" },
            if q { "beats" } else { "does **not** beat" }
        )?;
    }
    // Fig. 10: per cloud, its first row.
    writeln!(md, "## Fig. 10: MSE over time\n")?;
    let mut seen = vec![];
    for r in &res.rows {
        if seen.contains(&r.row.name()) {
            continue;
        }
        seen.push(r.row.name());
        let name = format!("fig10-{}.png", r.row.name()).to_lowercase();
        let s = |label: &str, v: &[f64]| Series { name: label.into(), points: v.iter().enumerate().map(|(k, &e)| (k as f64, e)).collect() };
        let series = [s("heterogeneous", &r.qr.heterogeneous), s("aerial-only", &r.qr.aerial_only), s("boat-only", &r.qr.boat_only), s("heterogeneous, random disks", &r.random.heterogeneous)];
        plot::lines(dir.join(&name), &format!("{}: MSE over the grid at each step", r.row.name()), "step", "MSE", &series, true)?;
        writeln!(md, "![{name}]({name})\n")?;
        figures.push(name);
    }
    // Fig. 11: the most complex cloud's first row, three boat steps.
    if let Some(r) = v.preset.as_ref().and_then(|p| res.rows.iter().find(|r| &r.row.name() == p)) {
        writeln!(md, "## Fig. 11: truth and reconstruction ({}), boats' disks in white\n", r.row.name())?;
        let truth = &truths[&r.row.name()];
        let (rows, cols) = (r.model_grid[0], r.model_grid[1]);
        let steps = &r.qr.boat_steps;
        let picks: Vec<usize> = if steps.len() >= 3 { vec![0, steps.len() / 2, steps.len() - 1] } else { (0..steps.len()).collect() };
        let radius = res.config.radius / r.row.mv_space as f64;
        let mut owned = vec![];
        for &i in &picks {
            let k = steps[i];
            let col: Vec<f64> = truth.snapshots.col(k).iter().copied().collect();
            owned.push((k, i, area_average(&col, truth.rows, truth.cols, rows, cols)?));
        }
        let mut panels = vec![];
        for (k, i, t) in &owned {
            let disks: Vec<(f64, f64, f64)> = r.qr.disks[*i].iter().map(|&(a, b)| (a as f64, b as f64, radius)).collect();
            panels.push(Panel { values: t, rows, cols, title: format!("truth, step {k}"), disks: disks.clone() });
            panels.push(Panel { values: &r.qr.snapshots[*i], rows, cols, title: format!("heterogeneous estimate, step {k}"), disks });
        }
        let range = plot::range_of(&panels[..panels.len().min(1)]);
        plot::png(dir.join("fig11.png"), &panels, Some(range))?;
        writeln!(md, "![fig11](fig11.png)\n")?;
        figures.push("fig11.png".into());
    }
    if !res.eig_study.is_empty() {
        writeln!(md, "## Fig. 7: dominant continuous-time eigenvalue (true -1 + 0i), {} trials\n", res.config.eig_trials)?;
        for (part, idx, reference) in [("real", 0usize, -1.0), ("imaginary", 1, 0.0)] {
            let groups: Vec<(String, Vec<f64>)> = res.eig_study.iter().map(|b| (format!("{} {}", b.method, b.noise_var), b.estimates.iter().map(|e| e[idx]).collect())).collect();
            let name = format!("fig7-{part}.png");
            plot::boxes(dir.join(&name), &format!("Dominant eigenvalue, {part} part (method, noise variance)"), part, &groups, Some(reference))?;
            writeln!(md, "![{name}]({name})\n")?;
            figures.push(name);
        }
        writeln!(md, "| method | noise variance | median real part | median imaginary part |\n|---|---|---|---|")?;
        for b in &res.eig_study {
            let mut re: Vec<f64> = b.estimates.iter().map(|e| e[0]).collect();
            let mut im: Vec<f64> = b.estimates.iter().map(|e| e[1]).collect();
            writeln!(md, "| {} | {} | {:.4} | {:.4} |", b.method, b.noise_var, eig_study::median(&mut re), eig_study::median(&mut im))?;
        }
        writeln!(md)?;
    }
    if !res.forgetting.is_empty() {
        writeln!(md, "## Fig. 8: forgetting factor (eigenvalue-study field, noise variance 0.01)\n")?;
        let series: Vec<Series> = res.forgetting.iter().map(|c| Series { name: c.label.clone(), points: c.points.clone() }).collect();
        plot::lines(dir.join("fig8.png"), "Dominant eigenvalue (real part) as pairs arrive; true value -1", "pairs assimilated", "Re(lambda)", &series, false)?;
        writeln!(md, "![fig8](fig8.png)\n")?;
        writeln!(
            md,
            "With `N = 400` cells, a forgetting factor keeps an effective memory of about `1/(1 - gamma)` pairs: \
             below ~400 (gamma 0.99 and less) the operator is fitted to fewer pairs than it has unknowns per row and its \
             dominant eigenvalue follows the noise.\n"
        )?;
        figures.push("fig8.png".into());
    }
    std::fs::write(dir.join("report.md"), md)?;
    Ok(figures)
}
