//! `fleet experiment`: the paper's evaluation end to end from one TOML file — Table 2 (MSE of
//! heterogeneous, aerial-only and boat-only teams, QR versus random placement), Fig. 10 (MSE
//! over time), Fig. 11 (truth beside reconstruction with the boats' disks), Fig. 7 (dominant
//! eigenvalue estimates, box plots) and Fig. 8 (forgetting factor) — as `report.md`, PNG
//! figures and `results.json`. Same file and seed, same JSON, byte for byte (timings go to
//! `timings.json`).

mod figures;

use super::claims;
use super::comparison::{Comparison, AERIAL_ONLY, BOAT_ONLY, HETEROGENEOUS, ORACLE, RANDOM};
use super::faults::{self, FaultKind, FaultRun};
use super::stats::{Interval, Outcome};
use super::team::{self, Placement, TeamConfig, TeamOutcome};
use super::{dominant_continuous, eig_study, run_online};
use crate::plot::{self, Series};
use anyhow::{bail, Context};
use fleet_math::dmd::{DmdConfig, Method, RankPolicy};
use fleet_math::process::plasma::Preset;
use fleet_math::process::synthetic::EigStudy;
use fleet_math::process::truth::{averaged_by, TruthSource};
use fleet_math::process::FieldSeries;
use fleet_mission::health::Health;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// One row of Table 2: sampling rates in time (steps) and space (cells of the simulator's grid)
/// for aerials (AV) and boats (MV), and the noise standard deviation of both.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Row {
    /// The simulator's cloud (`preset = "cloud1"`), or a `(frames, rows, cols)` `.npy`
    /// dataset (`dataset = "f.npy"`) as the truth (at the simulator grid's scale: it is
    /// area-averaged by `mv_space` like the simulator's output).
    #[serde(flatten)]
    pub truth: TruthSource,
    /// Aerial frames every this many steps.
    pub av_time: usize,
    /// Boat samples (and model updates) every this many steps.
    pub mv_time: usize,
    /// The aerials' space rate: every this-many-th cell of the truth's grid (on the model grid,
    /// every `av_space / mv_space`-th).
    pub av_space: usize,
    /// The boats' space rate, which sets the model grid: the truth is area-averaged by it.
    pub mv_space: usize,
    /// The noise standard deviation of both aerials and boats (field units).
    pub noise: f64,
    /// The paper's MSE for this row, when it has one (shown beside ours).
    #[serde(default)]
    pub paper_mse: Option<f64>,
}

/// The experiment file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ExperimentConfig {
    /// The truth's seed (one simulated cloud per preset, as the paper has one dataset per
    /// cloud) and Figs. 7-8's.
    pub seed: u64,
    /// The teams' seeds: sensor noise, the vehicles' random streams, random placement. Every
    /// team of a seed sees the same truth and the same noise; Table 2 gives the mean over seeds
    /// with a 95% interval, and paired differences. Default: `[seed]`.
    #[serde(default)]
    pub seeds: Vec<u64>,
    /// Fusion schemes run besides the team's (the heterogeneous team, QR disks), reported as
    /// `heterogeneous-<scheme>`.
    #[serde(default)]
    pub extra_fusions: Vec<fleet_math::fusion::Scheme>,
    /// Placements run besides QR and random (with the team's fusion), reported as
    /// `heterogeneous-<placement>` and compared with both.
    #[serde(default)]
    pub extra_placements: Vec<Placement>,
    /// Also run the oracle, a diagnostic that knows the truth: the boats' disks go where the
    /// estimate's error is (see [`team::run_oracle`]). Reported as `heterogeneous-oracle` and
    /// compared with QR, random and the extra placements: how much placement could buy.
    #[serde(default)]
    pub oracle: bool,
    /// Simulator grid `[rows, cols]` (for the preset rows: a dataset's grid is its file's, and
    /// an experiment of datasets only is refused one) and frames.
    #[serde(default)]
    pub truth_grid: Option<[usize; 2]>,
    /// Steps of every run (a preset's frames; a dataset's first `frames`).
    pub frames: usize,
    /// Boats' sensing radius in simulator cells (divided by `mv_space` on the model grid).
    pub radius: f64,
    /// Everything else of the team (rates, noise and radius come from the rows).
    #[serde(default)]
    pub team: TeamConfig,
    #[serde(rename = "row")]
    pub rows: Vec<Row>,
    /// Sensor failures to inject, each in its own run of the QR team with and without the
    /// health tests (`bias`, `stuck`, `spikes`, `drift`, `overexposed`, `silent`; see
    /// [`super::faults::FaultKind`]).
    #[serde(default)]
    pub faults: Vec<FaultKind>,
    /// Trials per noise level of the eigenvalue study (0 skips Fig. 7).
    #[serde(default)]
    pub eig_trials: usize,
    /// Forgetting factors of Fig. 8 (empty skips it).
    #[serde(default)]
    pub forgetting: Vec<f64>,
    /// What Fig. 8's factors multiply: the past once per update (`batch`, the paper's
    /// reading, default) or each pair by its age (`pair`, odmd's).
    #[serde(default)]
    pub forgetting_unit: fleet_math::dmd::ForgettingUnit,
    /// Whether `[team]` gives `aerial_growth_per_cell` (in the field's units, for every row);
    /// otherwise each row's is [`fleet_mission::team::default_growth`] of its `noise`.
    #[serde(skip)]
    pub growth_given: bool,
}

/// `[team]` keys an experiment sets elsewhere, and where: a value there would be ignored.
pub const SET_ELSEWHERE: [(&str, &str); 8] = [
    ("aerial_period", "each [[row]]'s av_time"),
    ("boat_period", "each [[row]]'s mv_time"),
    ("aerial_stride", "each [[row]]'s av_space / mv_space"),
    ("aerial_sigma0", "each [[row]]'s noise"),
    ("boat_sigma", "each [[row]]'s noise"),
    ("radius", "the top-level radius (truth cells, divided by mv_space)"),
    (
        "placement",
        "the experiment: QR and random on every row, others by extra_placements",
    ),
    ("seed", "the top-level seeds"),
];

/// Refuse a `[team]` key the experiment sets itself, with one line saying where it is set.
fn refuse_row_keys(text: &str) -> anyhow::Result<()> {
    let table: toml::Table = toml::from_str(text)?;
    let Some(team) = table.get("team").and_then(|t| t.as_table()) else {
        return Ok(());
    };
    match SET_ELSEWHERE.iter().find(|(key, _)| team.contains_key(*key)) {
        Some((key, by)) => bail!("[team] {key}: an experiment sets it by {by}; remove it from [team]"),
        None => Ok(()),
    }
}

/// `values` with NaN where the figure's truth has none: land and cloud drawn the same in every
/// panel (an estimate is 0 on land, which was the colour bar's lowest colour beside the truth's
/// no-data).
fn where_valued(values: &[f64], truth: &[f64]) -> Vec<f64> {
    values
        .iter()
        .zip(truth)
        .map(|(&v, t)| if t.is_nan() { f64::NAN } else { v })
        .collect()
}

impl Row {
    /// The truth's name in tables and figure files: the preset (`Cloud1`) or the file stem.
    pub fn name(&self) -> String {
        self.truth.name()
    }

    /// The row's first cells in the per-row tables: `| name | AV/MV time | AV/MV space | noise |`
    /// (a truth's name alone does not tell its rows apart).
    fn cells(&self) -> String {
        let (t, s) = ((self.av_time, self.mv_time), (self.av_space, self.mv_space));
        format!(
            "| {} | {}/{} | {}/{} | {} |",
            self.name(),
            t.0,
            t.1,
            s.0,
            s.1,
            self.noise
        )
    }
}

impl ExperimentConfig {
    /// `truth_grid` is the simulator's: needed when a row is a preset (at least 8 x 8), and
    /// refused when every row is a dataset (each has its file's grid; a value would be ignored).
    fn check_truth_grid(&self) -> anyhow::Result<()> {
        let presets: Vec<String> = (self.rows.iter())
            .filter(|r| matches!(r.truth, TruthSource::Preset(_)))
            .map(Row::name)
            .collect();
        match (self.truth_grid, presets.is_empty()) {
            (None, false) => bail!(
                "truth_grid: the preset rows ({}) need the simulator's grid",
                presets.join(", ")
            ),
            (Some(g), true) => bail!(
                "truth_grid = [{}, {}]: every row's truth is a dataset, whose grid is its file's; remove it",
                g[0],
                g[1]
            ),
            (Some(g), false) if g.iter().any(|&n| n < 8) => bail!("truth_grid: need at least an 8 x 8 simulator grid"),
            _ => Ok(()),
        }
    }

    /// The simulator's grid (rows that are datasets ignore it).
    pub fn sim_grid(&self) -> [usize; 2] {
        self.truth_grid.unwrap_or([0, 0])
    }

    pub fn from_toml(text: &str) -> anyhow::Result<Self> {
        let cfg: Self =
            toml::from_str(text).map_err(|e| anyhow::anyhow!(fleet_mission::config::toml_error(text, &e)))?;
        if cfg.rows.is_empty() {
            bail!("the experiment has no [[row]]");
        }
        refuse_row_keys(text)?;
        let cfg = Self {
            growth_given: fleet_mission::team::gives_growth(text),
            ..cfg
        };
        for (i, r) in cfg.rows.iter().enumerate() {
            let r_ = format!("[[row]] {} ({})", i + 1, r.name());
            if r.av_time == 0 || r.mv_time == 0 || r.av_space == 0 || r.mv_space == 0 || r.av_space % r.mv_space != 0 {
                bail!("{r_}: rates must be >= 1 and av_space a multiple of mv_space");
            }
            if !(r.noise.is_finite() && r.noise >= 0.0) {
                bail!("{r_}: noise must be >= 0");
            }
            if let (TruthSource::Preset(_), Some(g)) = (&r.truth, cfg.truth_grid) {
                if g[0] / r.mv_space < 4 || g[1] / r.mv_space < 4 {
                    bail!("{r_}: the model grid would be smaller than 4 x 4");
                }
            }
        }
        cfg.check_truth_grid()?;
        if cfg.frames < 10 {
            bail!("need at least 10 frames");
        }
        if cfg.forgetting.iter().any(|g| !(*g > 0.0 && *g <= 1.0)) {
            bail!("forgetting factors must be in (0, 1]");
        }
        let mut seeds = cfg.seeds.clone();
        seeds.sort_unstable();
        seeds.dedup();
        if seeds.len() != cfg.seeds.len() {
            bail!("seeds: each seed once (a repeated seed would count the same run twice)");
        }
        if cfg.extra_fusions.contains(&cfg.team.fusion) {
            bail!("extra_fusions: {} is the team's own fusion already", cfg.team.fusion);
        }
        if let Some(p) = cfg
            .extra_placements
            .iter()
            .find(|p| matches!(p, Placement::Qr | Placement::Random))
        {
            bail!("extra_placements: {p} runs already (every row has the QR and the random team)");
        }
        for &placement in &cfg.extra_placements {
            TeamConfig {
                placement,
                ..cfg.team.clone()
            }
            .check_choices()
            .with_context(|| format!("extra_placements: {placement}"))?;
        }
        Ok(cfg)
    }

    /// The teams' seeds.
    pub fn seeds(&self) -> Vec<u64> {
        if self.seeds.is_empty() {
            vec![self.seed]
        } else {
            self.seeds.clone()
        }
    }

    /// The team of one row, with the first seed.
    pub fn team_for(&self, r: &Row, placement: Placement) -> TeamConfig {
        self.team_for_seed(r, placement, self.seeds()[0])
    }

    /// The team of one row for one seed.
    pub fn team_for_seed(&self, r: &Row, placement: Placement, seed: u64) -> TeamConfig {
        TeamConfig {
            aerial_period: r.av_time,
            boat_period: r.mv_time,
            aerial_stride: r.av_space / r.mv_space,
            aerial_sigma0: r.noise,
            aerial_growth_per_cell: match self.growth_given {
                true => self.team.aerial_growth_per_cell,
                false => fleet_mission::team::default_growth(r.noise),
            },
            boat_sigma: r.noise,
            radius: self.radius / r.mv_space as f64,
            placement,
            seed,
            ..self.team.clone()
        }
    }
}

/// A team's MSE at each step (`None`: no data yet) and, for a fused team, its calibration
/// at each step (mean over cells of error^2 / reported variance).
#[derive(Debug, Clone)]
pub struct TeamSteps {
    pub team: String,
    pub mse: Vec<Option<f64>>,
    pub calibration: Option<Vec<f64>>,
}

impl TeamSteps {
    fn fused(team: &str, o: &TeamOutcome) -> Self {
        Self {
            team: team.into(),
            mse: fleet_math::fusion::scored(&o.heterogeneous),
            calibration: Some(o.calibration.clone()),
        }
    }
}

/// One seed of one row: every team's time-averaged MSE over the steps where all have data.
#[derive(Debug, Clone, Serialize)]
pub struct SeedResult {
    pub seed: u64,
    /// By team name (`heterogeneous`, `aerial-only`, `boat-only`, `heterogeneous-random`,
    /// `heterogeneous-<scheme>`).
    pub mse: BTreeMap<String, f64>,
    /// From step 0, for the teams that have data there (labelled in the report).
    pub heterogeneous_from_step0: f64,
    pub aerial_only_from_step0: f64,
    /// Fused teams: calibration averaged over the scored steps.
    pub calibration: BTreeMap<String, f64>,
    /// Fused teams: calibration by decile of reported variance ([`team::deciles`]).
    pub reliability: BTreeMap<String, Vec<f64>>,
    /// Fused teams: the expected normalised calibration error of those deciles ([`team::ence`]).
    pub ence: BTreeMap<String, f64>,
    /// Each fault of `faults` on the QR team, with and without the health tests.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub faults: BTreeMap<FaultKind, FaultRun>,
    /// Over the healthy fused teams' runs: sensors marked (a false alarm: nothing failed), and
    /// sensor-steps tested.
    pub false_alarms: u64,
    pub sensor_checks: u64,
    /// Over the same runs: values refused as spikes, and aerial frames and quadrants refused.
    pub false_refusals: [u64; 3],
}

#[derive(Debug, Clone, Serialize)]
pub struct RowResult {
    pub row: Row,
    pub model_grid: [usize; 2],
    /// The first step every team has data at (the boat-only team's first sample): scoring
    /// starts there for every team.
    pub scored_from: usize,
    /// Steps whose truth frame has no value at any cell: no vehicle sensed anything there and
    /// no team is scored there.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub empty_frames: Vec<usize>,
    pub seeds: Vec<SeedResult>,
    /// Mean over seeds with its 95% interval, by team.
    pub teams: BTreeMap<String, Interval>,
    pub heterogeneous_from_step0: Interval,
    pub aerial_only_from_step0: Interval,
    /// heterogeneous - aerial-only, heterogeneous - boat-only, QR - random (and each extra
    /// fusion scheme - the team's own).
    pub comparisons: Vec<Comparison>,
    /// Fused teams: calibration (mean error^2 / reported variance over cells and scored
    /// steps), mean over seeds with its 95% interval.
    pub calibration: BTreeMap<String, Interval>,
    /// Fused teams: calibration by decile of reported variance, per decile the mean over seeds
    /// with its 95% interval.
    pub reliability: BTreeMap<String, Vec<Interval>>,
    /// Fused teams: the expected normalised calibration error ([`team::ence`]), mean over seeds
    /// with its 95% interval.
    pub ence: BTreeMap<String, Interval>,
    /// Fused teams: the fraction of scored steps, pooled over seeds, where the team's MSE is
    /// at most the better single team's (aerial-only or boat-only).
    pub at_most_best_single: BTreeMap<String, f64>,
    /// The claims the fused estimate is held to, each with whether this row's numbers show it.
    pub claims: Vec<claims::Check>,
    /// Each fault of `faults`, over the seeds ([`faults::summarise`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<faults::FaultSummary>,
    /// Over every healthy fused team's runs and seeds: sensors marked (nothing failed), and
    /// sensor-steps tested.
    pub false_alarms: u64,
    pub sensor_checks: u64,
    pub false_refusals: [u64; 3],
    /// The first seed's QR run (Fig. 11).
    #[serde(skip)]
    pub figure: TeamOutcome,
    /// Per seed, per team, per step MSE (`None`: the team has no data yet): `per_step.csv`
    /// and Fig. 10.
    #[serde(skip)]
    pub per_step: Vec<(u64, Vec<TeamSteps>)>,
}

impl RowResult {
    /// Mean over seeds with the 95% interval at each step, by team (steps where a team has no
    /// data are left out).
    pub fn curves(&self) -> Vec<(String, Vec<(usize, Interval)>)> {
        let Some((_, first)) = self.per_step.first() else {
            return vec![];
        };
        first
            .iter()
            .enumerate()
            .map(|(t, steps)| {
                let points = (0..steps.mse.len())
                    .filter_map(|k| {
                        let v: Vec<f64> = self.per_step.iter().filter_map(|(_, teams)| teams[t].mse[k]).collect();
                        (v.len() == self.per_step.len()).then(|| (k, Interval::of(&v)))
                    })
                    .collect();
                (steps.team.clone(), points)
            })
            .collect()
    }
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
    pub verdict: PaperClaims,
}

/// The two claims the paper makes, checked on the most complex preset run: each verdict read
/// from the 95% interval of the paired difference over seeds.
#[derive(Debug, Clone, Serialize)]
pub struct PaperClaims {
    /// The row's truth (the most complex preset run, else the first dataset).
    pub preset: Option<String>,
    pub heterogeneous_vs_aerial_only: Option<Outcome>,
    pub heterogeneous_vs_boat_only: Option<Outcome>,
    pub qr_vs_random: Option<Outcome>,
}

fn rank_of(p: Preset) -> u8 {
    match p {
        Preset::Cloud2 => 0,
        Preset::Cloud1 => 1,
        Preset::Cloud10 => 2,
    }
}

/// Every team of one row and seed: the QR run (all three teams), the random-placement run, and
/// each extra fusion scheme's run.
fn run_seed(
    cfg: &ExperimentConfig,
    r: &Row,
    truth: &FieldSeries,
    seed: u64,
) -> Result<(SeedResult, TeamOutcome, Vec<TeamSteps>), team::TeamError> {
    let qr = team::run(&cfg.team_for_seed(r, Placement::Qr, seed), truth, |_, _| {})?;
    let random = team::run(&cfg.team_for_seed(r, Placement::Random, seed), truth, |_, _| {})?;
    let mut mse = BTreeMap::from([
        (HETEROGENEOUS.to_string(), qr.mean_heterogeneous),
        (AERIAL_ONLY.into(), qr.mean_aerial_only),
        (BOAT_ONLY.into(), qr.mean_boat_only),
        (RANDOM.into(), random.mean_heterogeneous),
    ]);
    let mut calibration = BTreeMap::from([
        (HETEROGENEOUS.to_string(), qr.mean_calibration),
        (RANDOM.into(), random.mean_calibration),
    ]);
    let mut reliability = BTreeMap::from([
        (HETEROGENEOUS.to_string(), qr.reliability.clone()),
        (RANDOM.into(), random.reliability.clone()),
    ]);
    let mut steps = vec![
        TeamSteps::fused(HETEROGENEOUS, &qr),
        TeamSteps {
            team: AERIAL_ONLY.into(),
            mse: fleet_math::fusion::scored(&qr.aerial_only),
            calibration: None,
        },
        TeamSteps {
            team: BOAT_ONLY.into(),
            mse: qr.boat_only.clone(),
            calibration: None,
        },
        TeamSteps::fused(RANDOM, &random),
    ];
    let extras = extra_runs(cfg, r, truth, seed)?;
    for (name, other) in &extras {
        mse.insert(name.clone(), other.mean_heterogeneous);
        calibration.insert(name.clone(), other.mean_calibration);
        reliability.insert(name.clone(), other.reliability.clone());
        steps.push(TeamSteps::fused(name, other));
    }
    let mut healthy = vec![&qr, &random];
    healthy.extend(extras.iter().map(|(_, o)| o));
    let (false_alarms, sensor_checks, false_refusals) = healthy_screening(&healthy);
    let faults = faults::run_faults(&cfg.team_for_seed(r, Placement::Qr, seed), truth, &cfg.faults)?
        .into_iter()
        .collect();
    let result = SeedResult {
        seed,
        faults,
        false_alarms,
        sensor_checks,
        false_refusals,
        mse,
        heterogeneous_from_step0: qr.heterogeneous_from_step0,
        aerial_only_from_step0: qr.aerial_only_from_step0,
        ence: reliability.iter().map(|(t, r)| (t.clone(), team::ence(r))).collect(),
        calibration,
        reliability,
    };
    Ok((result, qr, steps))
}

/// The fused teams run besides QR and random, by name: each extra fusion scheme and placement,
/// and the oracle.
fn extra_runs(
    cfg: &ExperimentConfig,
    r: &Row,
    truth: &FieldSeries,
    seed: u64,
) -> Result<Vec<(String, TeamOutcome)>, team::TeamError> {
    let qr = cfg.team_for_seed(r, Placement::Qr, seed);
    let mut out = vec![];
    for &fusion in &cfg.extra_fusions {
        let cfg = TeamConfig { fusion, ..qr.clone() };
        out.push((format!("{HETEROGENEOUS}-{fusion}"), team::run(&cfg, truth, |_, _| {})?));
    }
    for &placement in &cfg.extra_placements {
        let team = cfg.team_for_seed(r, placement, seed);
        out.push((
            format!("{HETEROGENEOUS}-{placement}"),
            team::run(&team, truth, |_, _| {})?,
        ));
    }
    if cfg.oracle {
        out.push((ORACLE.into(), team::run_oracle(&qr, truth)?));
    }
    Ok(out)
}

/// What the health tests did on healthy fleets (nothing failed): sensors marked, sensor-steps
/// tested, and values refused as spikes, aerial frames and quadrants refused.
fn healthy_screening(runs: &[&TeamOutcome]) -> (u64, u64, [u64; 3]) {
    let marked = runs
        .iter()
        .map(|o| o.verdicts.iter().filter(|v| v.to != Health::Ok).count() as u64)
        .sum();
    let checks = runs.iter().map(|o| o.screened.checks).sum();
    let refused = runs.iter().fold([0; 3], |[a, b, c], o| {
        let s = &o.screened;
        [a + s.spikes_refused, b + s.frames_refused, c + s.quadrants_refused]
    });
    (marked, checks, refused)
}

/// `f` over `jobs` on every core, results in job order (so the output does not depend on the
/// scheduling: each job is deterministic on its own).
fn parallel<J: Sync, T: Send>(jobs: &[J], f: impl Fn(&J) -> T + Sync + Send) -> Vec<T> {
    use rayon::prelude::*;
    jobs.par_iter().map(f).collect()
}

/// Run everything; `progress(message)` is called as work proceeds (for a progress bar), and
/// `units()` tells how many calls to expect. Rows and seeds run in parallel.
pub fn run(
    cfg: &ExperimentConfig,
    progress: impl FnMut(&str) + Send,
) -> anyhow::Result<(Results, BTreeMap<String, FieldSeries>)> {
    let progress = std::sync::Mutex::new(progress);
    let say = |m: &str| (progress.lock().unwrap_or_else(|p| p.into_inner()))(m);
    let (cache, truths) = make_truths(cfg, &say)?;
    check_rows(cfg, &truths)?;
    let seeds = cfg.seeds();
    let jobs: Vec<(usize, u64)> = (0..cfg.rows.len())
        .flat_map(|i| seeds.iter().map(move |&s| (i, s)))
        .collect();
    let outs = parallel(&jobs, |&(i, seed)| {
        let r = &cfg.rows[i];
        let what = format!(
            "{} {}/{} {}/{} seed {seed}",
            r.name(),
            r.av_time,
            r.mv_time,
            r.av_space,
            r.mv_space
        );
        let out = run_seed(cfg, r, &truths[i], seed).with_context(|| what.clone());
        say(&what);
        out
    });
    let mut outs = outs.into_iter();
    let mut rows = vec![];
    for (i, r) in cfg.rows.iter().enumerate() {
        let mine: Vec<_> = seeds.iter().map(|_| outs.next().expect("one output per job")).collect();
        rows.push(summarise_row(cfg, r, &truths[i], &seeds, mine)?);
    }
    let eig_study = eigenvalue_study(cfg, &say)?;
    let forgetting = forgetting_curves(cfg, &say)?;
    let verdict = verdict_of(&rows);
    let config = cfg.clone();
    Ok((
        Results {
            config,
            rows,
            eig_study,
            forgetting,
            verdict,
        },
        cache,
    ))
}

/// One truth per cloud, simulated once (in parallel), and each row's truth on its model grid.
#[allow(clippy::type_complexity)]
/// Every row's teams checked on the row's field before anything runs: a setting the field
/// cannot hold (more initial steps than the file has frames, a mask that leaves no room) is
/// the file's fault, one line naming the row, exit 2, not an internal error at its first seed.
fn check_rows(cfg: &ExperimentConfig, truths: &[FieldSeries]) -> anyhow::Result<()> {
    let placements = [Placement::Qr, Placement::Random]
        .into_iter()
        .chain(cfg.extra_placements.iter().copied());
    for (r, truth) in cfg.rows.iter().zip(truths) {
        fleet_math::process::units::check_noise(r.noise)
            .map_err(|why| fleet_exit::bad_input(anyhow::anyhow!("{}: {why}", r.name())))?;
        for p in placements.clone() {
            team::check(&cfg.team_for_seed(r, p, cfg.seeds()[0]), truth)
                .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("{}: {e}", r.name())))?;
        }
    }
    Ok(())
}

fn make_truths(
    cfg: &ExperimentConfig,
    say: &(impl Fn(&str) + Sync),
) -> anyhow::Result<(BTreeMap<String, FieldSeries>, Vec<FieldSeries>)> {
    let mut names: Vec<&Row> = vec![];
    for r in &cfg.rows {
        if !names.iter().any(|n| n.name() == r.name()) {
            names.push(r);
        }
    }
    let fulls = parallel(&names, |r| {
        let out = r
            .truth
            .full((cfg.sim_grid(), cfg.frames, cfg.seed), None, |_| {})
            .with_context(|| r.name());
        say(&format!("truth {}", r.name()));
        out
    });
    let mut cache = BTreeMap::new();
    for (r, full) in names.iter().zip(fulls) {
        cache.insert(r.name(), full?);
    }
    let truths: Vec<FieldSeries> = cfg
        .rows
        .iter()
        .map(|r| averaged_by(&cache[&r.name()], r.mv_space).with_context(|| r.name()))
        .collect::<anyhow::Result<_>>()?;
    Ok((cache, truths))
}

/// What one seed of a row gives: its result, the figure's data, its per-step errors.
type SeedOut = anyhow::Result<(SeedResult, TeamOutcome, Vec<TeamSteps>)>;

/// A row over its seeds: each team's mean with its interval, the paired comparisons,
/// calibration, and where the fused teams beat the better single team.
fn summarise_row(
    cfg: &ExperimentConfig,
    r: &Row,
    truth: &FieldSeries,
    seeds: &[u64],
    outs: Vec<SeedOut>,
) -> anyhow::Result<RowResult> {
    let mut seed_results = vec![];
    let mut per_step = vec![];
    let mut figure = None;
    for (&seed, out) in seeds.iter().zip(outs) {
        let (result, qr, steps) = out?;
        seed_results.push(result);
        per_step.push((seed, steps));
        figure.get_or_insert(qr);
    }
    let figure = figure.expect("at least one seed");
    let of = |team: &str| seed_results.iter().map(|s| s.mse[team]).collect::<Vec<f64>>();
    let teams: BTreeMap<String, Interval> = seed_results[0]
        .mse
        .keys()
        .map(|t| (t.clone(), Interval::of(&of(t))))
        .collect();
    let comparisons = comparisons_of(cfg, &of);
    let (calibration, reliability) = calibration_over(&seed_results);
    let ence = seed_results[0]
        .ence
        .keys()
        .map(|t| {
            (
                t.clone(),
                Interval::of(&seed_results.iter().map(|s| s.ence[t]).collect::<Vec<_>>()),
            )
        })
        .collect();
    let at_most_best_single = at_most_best_single(&per_step, figure.scored_from);
    let claims = claims::of(&comparisons, &teams, &at_most_best_single, &reliability);
    let step0 = |f: fn(&SeedResult) -> f64| Interval::of(&seed_results.iter().map(f).collect::<Vec<_>>());
    let fault_runs: Vec<&BTreeMap<FaultKind, FaultRun>> = seed_results.iter().map(|s| &s.faults).collect();
    let faults = faults::summarise(&of(HETEROGENEOUS), &fault_runs);
    Ok(RowResult {
        faults,
        false_alarms: seed_results.iter().map(|s| s.false_alarms).sum(),
        sensor_checks: seed_results.iter().map(|s| s.sensor_checks).sum(),
        false_refusals: seed_results.iter().fold([0; 3], |[a, b, c], s| {
            let [x, y, z] = s.false_refusals;
            [a + x, b + y, c + z]
        }),
        row: r.clone(),
        model_grid: [truth.rows, truth.cols],
        empty_frames: (0..truth.frames())
            .filter(|&k| truth.snapshots.col(k).iter().all(|v| v.is_nan()))
            .collect(),
        scored_from: figure.scored_from,
        heterogeneous_from_step0: step0(|s| s.heterogeneous_from_step0),
        aerial_only_from_step0: step0(|s| s.aerial_only_from_step0),
        seeds: seed_results,
        teams,
        comparisons,
        calibration,
        reliability,
        ence,
        at_most_best_single,
        claims,
        figure,
        per_step,
    })
}

/// The paired differences a row reports: the fused team against each single team and random
/// disks, each extra fusion and placement against the fused team (and random), the oracle's.
fn comparisons_of(cfg: &ExperimentConfig, of: &impl Fn(&str) -> Vec<f64>) -> Vec<Comparison> {
    let compare = |a: &str, b: &str| {
        let d = Interval::paired(&of(a), &of(b));
        Comparison {
            first: a.into(),
            second: b.into(),
            difference: d,
            verdict: Outcome::of(&d),
        }
    };
    let mut comparisons = vec![
        compare(HETEROGENEOUS, AERIAL_ONLY),
        compare(HETEROGENEOUS, BOAT_ONLY),
        compare(HETEROGENEOUS, RANDOM),
    ];
    for scheme in &cfg.extra_fusions {
        comparisons.push(compare(&format!("{HETEROGENEOUS}-{scheme}"), HETEROGENEOUS));
    }
    for placement in &cfg.extra_placements {
        let name = format!("{HETEROGENEOUS}-{placement}");
        comparisons.push(compare(&name, HETEROGENEOUS));
        comparisons.push(compare(&name, RANDOM));
    }
    if cfg.oracle {
        comparisons.push(compare(ORACLE, HETEROGENEOUS));
        comparisons.push(compare(ORACLE, RANDOM));
        for placement in &cfg.extra_placements {
            comparisons.push(compare(ORACLE, &format!("{HETEROGENEOUS}-{placement}")));
        }
    }
    comparisons
}

/// Each fused team's calibration, and its calibration by decile: the mean over seeds with its
/// interval (per decile).
type Calibrations = (BTreeMap<String, Interval>, BTreeMap<String, Vec<Interval>>);
fn calibration_over(seeds: &[SeedResult]) -> Calibrations {
    let overall = seeds[0]
        .calibration
        .keys()
        .map(|t| {
            let of = seeds.iter().map(|s| s.calibration[t]).collect::<Vec<_>>();
            (t.clone(), Interval::of(&of))
        })
        .collect();
    let by_decile = seeds[0]
        .reliability
        .iter()
        .map(|(t, first)| {
            let at = |d: usize| {
                seeds
                    .iter()
                    .filter_map(|s| s.reliability[t].get(d).copied())
                    .collect::<Vec<_>>()
            };
            (t.clone(), (0..first.len()).map(|d| Interval::of(&at(d))).collect())
        })
        .collect();
    (overall, by_decile)
}

/// Fig. 7: the dominant eigenvalue's estimates by method and noise level.
fn eigenvalue_study(cfg: &ExperimentConfig, progress: &impl Fn(&str)) -> anyhow::Result<Vec<EigBox>> {
    let mut eig = vec![];
    if cfg.eig_trials == 0 {
        return Ok(eig);
    }
    let methods = [
        ("batch", Method::Batch),
        ("general", Method::General),
        ("long-term", Method::LongTerm),
    ];
    for (level, var) in [0.01, 0.04, 0.1].into_iter().enumerate() {
        for (label, method) in methods {
            progress(&format!("Fig. 7 {label} var {var}"));
            let v = eig_study::Variant::new(label, method, RankPolicy::Full, Default::default(), 1.0);
            let estimates = (0..cfg.eig_trials)
                .map(|t| eig_study::estimate(&v, var, eig_study::trial_seed(cfg.seed, level, t)))
                .collect::<Result<Vec<_>, _>>()?;
            eig.push(EigBox {
                method: label.into(),
                noise_var: var,
                estimates,
            });
        }
    }
    Ok(eig)
}

/// Fig. 8: the dominant eigenvalue as pairs arrive, batch against long-term with forgetting.
fn forgetting_curves(cfg: &ExperimentConfig, progress: &impl Fn(&str)) -> anyhow::Result<Vec<ForgettingCurve>> {
    let mut forgetting = vec![];
    if cfg.forgetting.is_empty() {
        return Ok(forgetting);
    }
    let field = EigStudy::field(0.01, cfg.seed);
    let z = field.snapshots.as_ref();
    let config = |method, gamma, forgetting| DmdConfig {
        method,
        rank: RankPolicy::Full,
        debias: Default::default(),
        gamma,
        forgetting,
    };
    let mut curves: Vec<(String, DmdConfig)> = vec![("batch".into(), config(Method::Batch, 1.0, Default::default()))];
    for &g in &cfg.forgetting {
        let c = config(Method::LongTerm, g, cfg.forgetting_unit.into());
        curves.push((format!("long-term gamma {g}"), c));
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
    Ok(forgetting)
}

/// What the paired intervals say on the most complex cloud's first row.
fn verdict_of(rows: &[RowResult]) -> PaperClaims {
    let top = rows
        .iter()
        .filter_map(|r| r.row.truth.preset())
        .max_by_key(|p| rank_of(*p));
    let first_of_top = match top {
        Some(p) => rows.iter().find(|r| r.row.truth.preset() == Some(p)),
        None => rows.first(),
    };
    let verdict_of = |r: &RowResult, second: &str| {
        r.comparisons
            .iter()
            .find(|c| c.first == HETEROGENEOUS && c.second == second)
            .map(|c| c.verdict)
    };
    PaperClaims {
        preset: first_of_top.map(|r| r.row.name()),
        heterogeneous_vs_aerial_only: first_of_top.and_then(|r| verdict_of(r, AERIAL_ONLY)),
        heterogeneous_vs_boat_only: first_of_top.and_then(|r| verdict_of(r, BOAT_ONLY)),
        qr_vs_random: first_of_top.and_then(|r| verdict_of(r, RANDOM)),
    }
}

/// For each fused team: the fraction of steps from `from` on, pooled over seeds, where its
/// MSE is at most the better of the aerial-only and boat-only teams'.
fn at_most_best_single(per_step: &[(u64, Vec<TeamSteps>)], from: usize) -> BTreeMap<String, f64> {
    let mut count: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for (_, teams) in per_step {
        let of = |name: &str| teams.iter().find(|t| t.team == name).map(|t| &t.mse);
        let (Some(a), Some(b)) = (of(AERIAL_ONLY), of(BOAT_ONLY)) else {
            continue;
        };
        for t in teams.iter().filter(|t| t.calibration.is_some()) {
            let c = count.entry(t.team.clone()).or_default();
            for k in from..t.mse.len() {
                if let (Some(x), Some(a), Some(b)) = (t.mse[k], a[k], b[k]) {
                    c.1 += 1;
                    if x <= a.min(b) {
                        c.0 += 1;
                    }
                }
            }
        }
    }
    count
        .into_iter()
        .map(|(t, (wins, all))| (t, wins as f64 / all.max(1) as f64))
        .collect()
}

/// Work units `run` reports, for a progress bar.
pub fn units(cfg: &ExperimentConfig) -> usize {
    let clouds = cfg
        .rows
        .iter()
        .map(Row::name)
        .collect::<std::collections::BTreeSet<_>>()
        .len();
    clouds
        + cfg.rows.len() * cfg.seeds().len()
        + if cfg.eig_trials > 0 { 9 } else { 0 }
        + if cfg.forgetting.is_empty() {
            0
        } else {
            cfg.forgetting.len() + 1
        }
}

/// `per_step.csv`: one line per row, seed, team and step where the team has data
/// (`row,preset,seed,team,step,mse,calibration`; `row` counts the experiment's rows from 1;
/// `calibration` is empty for the single-source teams, which report no variance), so every
/// figure and table can be recomputed with pandas.
fn write_per_step(dir: &Path, res: &Results) -> anyhow::Result<()> {
    let mut csv = String::from("row,preset,seed,team,step,mse,calibration\n");
    for (i, r) in res.rows.iter().enumerate() {
        for (seed, teams) in &r.per_step {
            for t in teams {
                for (k, v) in t.mse.iter().enumerate() {
                    if let Some(v) = v {
                        let c = t.calibration.as_ref().map_or(String::new(), |c| format!("{:e}", c[k]));
                        writeln!(csv, "{},{},{seed},{},{k},{v:e},{c}", i + 1, r.row.name(), t.team)?;
                    }
                }
            }
        }
    }
    std::fs::write(dir.join("per_step.csv"), csv)?;
    Ok(())
}

/// What the report's sections read, and what they write: the markdown and the figures' names.
struct Report<'a> {
    dir: &'a Path,
    res: &'a Results,
    truths: &'a BTreeMap<String, FieldSeries>,
    md: String,
    figures: Vec<String>,
}

/// An interval as the tables show it: `mean [lo, hi]`, or the mean alone from one seed.
fn interval_cell(i: &Interval) -> String {
    let e3 = |v: f64| format!("{v:.3e}");
    if i.n > 1 {
        format!("{} [{}, {}]", e3(i.mean), e3(i.lo), e3(i.hi))
    } else {
        e3(i.mean)
    }
}

/// The teams beyond the paper's four: other fusions and placements, and the oracle.
fn extra_teams(res: &Results) -> Vec<String> {
    let mut extra: Vec<String> = res
        .config
        .extra_fusions
        .iter()
        .map(|f| f.to_string())
        .chain(res.config.extra_placements.iter().map(|p| p.to_string()))
        .map(|x| format!("{HETEROGENEOUS}-{x}"))
        .collect();
    if res.config.oracle {
        extra.push(ORACLE.into());
    }
    extra
}

/// Write `results.json`, `per_step.csv`, the figures and `report.md` into `dir`.
pub fn write_report(
    dir: &Path,
    res: &Results,
    truths: &BTreeMap<String, FieldSeries>,
    command: &str,
) -> anyhow::Result<Vec<String>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    std::fs::write(dir.join("results.json"), serde_json::to_string_pretty(res)?)?;
    let mut r = Report {
        dir,
        res,
        truths,
        md: String::new(),
        figures: vec![],
    };
    r.intro(command)?;
    write_per_step(dir, res)?;
    r.table2()?;
    r.differences()?;
    r.fused_teams()?;
    r.reliability()?;
    r.claims()?;
    r.sensor_health()?;
    r.verdict()?;
    r.fig10()?;
    r.fig11()?;
    r.eig_study()?;
    r.forgetting()?;
    std::fs::write(dir.join("report.md"), r.md)?;
    Ok(r.figures)
}

impl Report<'_> {
    /// The heading, what made the report, and what the truth and the team were.
    fn intro(&mut self, command: &str) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        writeln!(md, "# hetfleet experiment report\n")?;
        writeln!(
            md,
            "Made by `{command}`. Every number is in `results.json`, every per-step error in `per_step.csv` \
            (`row,preset,seed,team,step,mse,calibration`).\n"
        )?;
        let mut truths: Vec<String> = vec![];
        for r in &res.config.rows {
            let t = match r.truth {
                TruthSource::Preset(_) => format!(
                    "{} at {} x {}, {} frames (seed {})",
                    r.truth.describe(),
                    res.config.sim_grid()[0],
                    res.config.sim_grid()[1],
                    res.config.frames,
                    res.config.seed
                ),
                _ => r.truth.describe(),
            };
            if !truths.contains(&t) {
                truths.push(t);
            }
        }
        writeln!(
            md,
            "Truth: {}; area-averaged by the boats' space rate to the model grid. \
             Team: {} aerials, {} boats of radius {} truth cells, {} DMD at rank `{}`, `{}` fusion, {} initial \
             aerial-only steps. \
             MSE is averaged over the grid at each step, then over the scored steps.\n",
            truths.join("; "),
            res.config.team.aerials,
            res.config.team.boats,
            res.config.radius,
            res.config.team.method,
            res.config.team.rank,
            res.config.team.fusion,
            res.config.team.init_steps
        )?;
        Ok(())
    }

    /// Table 2: every team's time-averaged MSE per row, with the oracle explained when it ran.
    fn table2(&mut self) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        let seeds = res.config.seeds();
        writeln!(
            md,
            "## Table 2: time-averaged MSE, mean over {} seeds [95% interval]\n",
            seeds.len()
        )?;
        writeln!(
            md,
            "Every team is scored over the same steps: from the first step where every team has data (the boat-only \
                team's first sample, step `scored from`) to the end. \
             No team is scored where it has no data. Seeds {seeds:?} vary the sensor noise, the vehicles' random \
             streams and the random placement; every team of a seed sees the same truth and noise.{}\n",
            match res.config.rows.iter().any(|r| r.truth.preset().is_some()) {
                true => format!(
                    " A simulated truth is one cloud per preset (seed {}), as the paper has one dataset per cloud.",
                    res.config.seed
                ),
                false => String::new(),
            }
        )?;
        for r in res.rows.iter().filter(|r| !r.empty_frames.is_empty()) {
            writeln!(
                md,
                "Row {}: the truth has no value at any cell at {} steps ({:?}): frames without observations, no \
                 team scored there.\n",
                r.row.name(),
                r.empty_frames.len(),
                r.empty_frames
            )?;
        }
        let extra = extra_teams(res);
        if res.config.oracle {
            writeln!(
                md,
                "`{ORACLE}` is a diagnostic, not a placement a fleet can use: it knows the truth. At each boat epoch a \
                    copy of the fleet senses the epoch with the boats idle, \
                 and the disks go, greedily and without overlap, where that copy's estimate at the sampling step is \
                 furthest from the truth (most squared error over the disk). \
                 Its difference from QR bounds what putting the disks where the error is could buy on that row.\n"
            )?;
        }
        write!(
            md,
            "| cloud | AV time | MV time | AV space | MV space | noise | model grid | scored from | heterogeneous \
            (QR) | aerial-only | boat-only | heterogeneous (random) |"
        )?;
        for x in &extra {
            write!(md, " {x} |")?;
        }
        writeln!(md, " paper |")?;
        writeln!(md, "|{}", "---|".repeat(13 + extra.len()))?;
        for r in &res.rows {
            let w = &r.row;
            write!(
                md,
                "| {} | {} | {} | {} | {} | {} | {} x {} | {} |",
                w.name(),
                w.av_time,
                w.mv_time,
                w.av_space,
                w.mv_space,
                w.noise,
                r.model_grid[0],
                r.model_grid[1],
                r.scored_from
            )?;
            for t in [HETEROGENEOUS, AERIAL_ONLY, BOAT_ONLY, RANDOM]
                .iter()
                .map(|t| t.to_string())
                .chain(extra.iter().cloned())
            {
                write!(md, " {} |", interval_cell(&r.teams[&t]))?;
            }
            writeln!(md, " {} |", w.paper_mse.map_or("".into(), |v| format!("{v}")))?;
        }
        Ok(())
    }

    /// The paired differences per row, and the scores from step 0.
    fn differences(&mut self) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        writeln!(
            md,
            "\n### Paired differences (same seed, same truth and noise), mean [95% interval], and what they say\n"
        )?;
        let heads: Vec<String> = res.rows.first().map_or(vec![], |r| {
            r.comparisons
                .iter()
                .map(|c| format!("{} - {}", c.first, c.second))
                .collect()
        });
        writeln!(
            md,
            "| cloud | AV/MV time | AV/MV space | noise |{}",
            heads.iter().map(|h| format!(" {h} |")).collect::<String>()
        )?;
        writeln!(md, "|{}", "---|".repeat(4 + heads.len()))?;
        for r in &res.rows {
            write!(md, "{}", r.row.cells())?;
            for c in &r.comparisons {
                write!(md, " {} **{}** |", interval_cell(&c.difference), c.verdict.words())?;
            }
            writeln!(md)?;
        }
        writeln!(
            md,
            "\nScored from step 0 instead (labelled: only the teams with data there):\n"
        )?;
        writeln!(
            md,
            "| cloud | AV/MV time | AV/MV space | noise | heterogeneous, from step 0 | aerial-only, from step 0 \
            |\n|---|---|---|---|---|---|"
        )?;
        for r in &res.rows {
            writeln!(
                md,
                "{} {} | {} |",
                r.row.cells(),
                interval_cell(&r.heterogeneous_from_step0),
                interval_cell(&r.aerial_only_from_step0)
            )?;
        }
        Ok(())
    }

    /// The fused teams' calibration and the steps where they did at least as well as the better single team.
    fn fused_teams(&mut self) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        writeln!(
            md,
            "\n### The fused teams: calibration and per-step wins\n\n\
             Calibration: the mean over cells and scored steps of error^2 / reported variance, mean over seeds [95% \
             interval] (1 is calibrated; above 1 the reported variance is too small). \
             Steps won: the fraction of scored steps, pooled over seeds, where the team's MSE is at most the better \
             single team's (aerial-only or boat-only) at that step.\n"
        )?;
        let fused: Vec<String> = res
            .rows
            .first()
            .map_or(vec![], |r| r.calibration.keys().cloned().collect());
        writeln!(
            md,
            "| cloud | AV/MV time | AV/MV space | noise |{}",
            fused
                .iter()
                .map(|t| format!(" {t}: calibration | {t}: steps won |"))
                .collect::<String>()
        )?;
        writeln!(md, "|{}", "---|".repeat(4 + 2 * fused.len()))?;
        for r in &res.rows {
            write!(md, "{}", r.row.cells())?;
            for t in &fused {
                write!(
                    md,
                    " {} | {:.1}% |",
                    r.calibration
                        .get(t)
                        .map_or("".into(), |i| format!("{:.3} [{:.3}, {:.3}]", i.mean, i.lo, i.hi)),
                    100.0 * r.at_most_best_single.get(t).copied().unwrap_or(0.0)
                )?;
            }
            writeln!(md)?;
        }
        Ok(())
    }

    /// Calibration by decile of reported variance (the reliability diagram): whether the
    /// variance is right where it is small and where it is large, not only on average.
    fn reliability(&mut self) -> anyhow::Result<()> {
        let Report {
            dir, res, md, figures, ..
        } = self;
        writeln!(
            md,
            "\n### Calibration by decile of reported variance\n\n\
             Each fused team's cells and scored steps, pooled per seed, sorted by reported variance and cut into ten \
             equal parts; per part the mean error^2 over the mean reported variance (1: the variance is the error's \
             there), mean over seeds. The claim is 0.7-1.3 in every decile; `in band` counts the deciles that are. \
             ENCE, the expected normalised calibration error, is the mean over the deciles of |RMV - RMSE| / RMV (root \
             mean variance against root mean squared error; 0 is calibrated in every decile), mean over seeds [95% \
             interval].\n"
        )?;
        writeln!(
            md,
            "| cloud | team |{} in band | ENCE |",
            (1..=10).map(|d| format!(" d{d} |")).collect::<String>()
        )?;
        writeln!(md, "|{}", "---|".repeat(14))?;
        let mut series = vec![];
        for r in &res.rows {
            for (team, by_decile) in &r.reliability {
                if team == ORACLE || by_decile.is_empty() {
                    continue;
                }
                let means: Vec<f64> = by_decile.iter().map(|i| i.mean).collect();
                let in_band = means.iter().filter(|m| claims::DECILE_BAND.contains(*m)).count();
                let ence = r
                    .ence
                    .get(team)
                    .map_or(String::new(), |e| format!("{:.3} [{:.3}, {:.3}]", e.mean, e.lo, e.hi));
                writeln!(
                    md,
                    "| {} | {team} |{} {in_band}/10 | {ence} |",
                    r.row.name(),
                    means.iter().map(|m| format!(" {m:.2} |")).collect::<String>()
                )?;
                series.push(Series {
                    name: format!("{} {team}", r.row.name()),
                    points: means.iter().enumerate().map(|(d, &m)| ((d + 1) as f64, m)).collect(),
                });
            }
        }
        if !series.is_empty() {
            let name = "fig12-reliability.png";
            plot::lines(
                dir.join(name),
                "Calibration by decile of reported variance (1: calibrated; claim 0.7-1.3)",
                "decile of reported variance (1: smallest)",
                "mean error^2 / mean variance",
                &series,
                true,
            )?;
            writeln!(md, "\n![{name}]({name})\n")?;
            figures.push(name.into());
        }
        Ok(())
    }

    /// The claims, row by row: where each holds and where it does not, with its number.
    fn claims(&mut self) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        let Some(first) = res.rows.first() else {
            return Ok(());
        };
        writeln!(
            md,
            "\n### The claims, row by row\n\n\
             What the tables above say of each claim the fused estimate is held to (docs/results/README.md says what each means; docs/decisions say why \
             where one does not). A difference (the first team named minus the second) is in percent of the \
             second's MSE, mean [95% interval] over seeds; `not run`: the config has no such team.\n"
        )?;
        write!(md, "| cloud | AV/MV time | AV/MV space | noise |")?;
        for c in &first.claims {
            write!(md, " {} |", c.claim)?;
        }
        writeln!(md, "\n|{}", "---|".repeat(4 + first.claims.len()))?;
        for r in &res.rows {
            write!(md, "{}", r.row.cells())?;
            for c in &r.claims {
                write!(md, " {} |", c.cell())?;
            }
            writeln!(md)?;
        }
        let count = |claim: &str, held: bool| {
            res.rows
                .iter()
                .filter(|r| r.claims.iter().any(|c| c.claim == claim && c.holds == Some(held)))
                .count()
        };
        let (won, lost) = (
            count(claims::HORIZON_OVER_QR, true),
            count(claims::HORIZON_OVER_QR, false),
        );
        if won + lost > 0 {
            writeln!(
                md,
                "\nHorizon placement better than QR on **{won} of {}** rows (the claim: most).",
                won + lost
            )?;
        }
        let (held, run) = claims::tally(res.rows.iter().flat_map(|r| &r.claims));
        writeln!(md, "Claims held: **{held} of {run}** checked.")?;
        Ok(())
    }

    /// Sensor health: false alarms on the healthy fleets, and each injected fault's cost with
    /// and without the health tests.
    fn sensor_health(&mut self) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        let (alarms, checks) = res
            .rows
            .iter()
            .fold((0, 0), |(a, c), r| (a + r.false_alarms, c + r.sensor_checks));
        let [spikes, frames, quadrants] = res.rows.iter().fold([0; 3], |[a, b, c], r| {
            let [x, y, z] = r.false_refusals;
            [a + x, b + y, c + z]
        });
        if checks == 0 {
            return Ok(());
        }
        writeln!(
            md,
            "\n### Sensor health\n\nEvery reading is tested before the fusion uses it (the guide, docs/guide/sensor-health.md). \
             Healthy fleets (every fused team, row and seed): **{alarms} sensor(s) marked in {checks} sensor-steps \
             tested** ({:.1e} a sensor-step; the bias tests' design rate is about 1.0e-3 a tested step, the CUSUM's \
             7.7e-4 and the change test's 2.6e-4); healthy values refused \
             as spikes: {spikes}; healthy aerial frames refused: {frames}, quadrants: {quadrants}.\n",
            alarms as f64 / checks as f64
        )?;
        if res.rows.iter().all(|r| r.faults.is_empty()) {
            return Ok(());
        }
        writeln!(
            md,
            "One vehicle's sensor fails from mid-mission (the first boat; the first aerial for `overexposed` and \
             `silent`), each fault in its own run of the QR team on the same truth and noise as the healthy one. Cost: \
             the fused MSE over the healthy fleet's, per seed, mean [95% interval]; the claim is within +10% with the \
             tests. Withheld: the cost with the altered readings withheld (a test that knew which readings were bad \
             could do no better: the information the fault takes away). Marked: seeds where the faulty sensor was \
             suspect or excluded within 3 boat epochs of the fault's start, and the median epochs to the mark. \
             Knowable: the seeds in which a test that knew the fault (kind, size, sign, start) could have marked it \
             within those 3 epochs, expected, at 1e-3 false alarms: a stuck probe, a spike, an over-exposed frame or a \
             dark camera once one reached the server; an offset by the best test's power on the boat's differences \
             from the aerials at the lattice cells both measured (the only place an offset shows: docs/guide/sensor-health.md, \"Sensor \
             health\").\n"
        )?;
        writeln!(
            md,
            "| row | fault | MSE with the tests | cost with | MSE without | cost without | cost withheld | \
             marked within 3 epochs | knowable within 3 | median epochs |"
        )?;
        writeln!(md, "|{}", "---|".repeat(10))?;
        for r in &res.rows {
            faults::table(md, &r.row.name(), &r.faults)?;
        }
        Ok(())
    }

    /// What the paired intervals say on the most complex cloud.
    fn verdict(&mut self) -> anyhow::Result<()> {
        let Report { res, md, .. } = self;
        let v = &res.verdict;
        writeln!(md)?;
        if let (Some(p), Some(a), Some(b), Some(q)) = (
            &v.preset,
            v.heterogeneous_vs_aerial_only,
            v.heterogeneous_vs_boat_only,
            v.qr_vs_random,
        ) {
            writeln!(
                md,
                "On the most complex cloud run ({p}, its first row), read from the paired intervals: heterogeneous \
                    against aerial-only **{}**, heterogeneous against boat-only **{}**, QR placement against random \
                    placement **{}**.\n",
                a.words(),
                b.words(),
                q.words()
            )?;
        }
        Ok(())
    }
}
