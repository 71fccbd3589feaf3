//! The loop of DESIGN.md ("The loop", steps 1-5) run offline and deterministically on a truth
//! field: aerials in coverage formation see coarse noisy frames every `period` steps; boats
//! measure disks of radius `radius` every `period` steps at the places block QR (or a random
//! draw) chose from the current model; the estimates are fused into one snapshot per step and
//! assimilated online; metrics compare every team's estimate with the truth at every step.
//!
//! Teams, all on the same truth and the same noise draws:
//! - heterogeneous: the fused snapshots (aerial + boats' gappy estimate, or the model's
//!   prediction between boat samples);
//! - aerial-only: the upsampled aerial frame (held between frames);
//! - boat-only: a DMD model built from boat data alone, the boats at the heterogeneous
//!   model's disks (the paper's reading): at a boat step its snapshot is the gappy estimate on
//!   its own model's modes, between boat steps its own prediction. It has no estimate before
//!   its first sample (those steps are not scored for any team: every team is scored over the
//!   same steps); until it has a model, and when its modes are not determined by the disks or
//!   their fit leaves the range of every value measured so far (widened by that range), the
//!   measured cells' mean fills the grid.

use faer::Mat;
use fleet_math::dmd::{DmdConfig, DmdModel, Method};
use fleet_math::fusion::AerialNoise;
use fleet_math::fusion::{mean_scored, mse};
use fleet_math::grid::Grid;
use fleet_math::process::FieldSeries;
use fleet_math::sensing::gappy;
use fleet_mission::assimilator::BoatDisk;
use fleet_mission::protocol::{MeasurementBatch, Sample, VehicleKind};
use fleet_mission::server::ServerCore;
pub use fleet_mission::team::{Placement, TeamConfig, TeamError};
use fleet_mission::vehicle::VehicleBrain;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// Per-step mean squared errors of the three teams, and what the fleet did.
///
/// Scoring (every team over the same steps, never a team without data): the heterogeneous and
/// aerial-only teams have data from step 0; the boat-only team from its first boat sample
/// (`boat_only[k]` is `None` before). The `mean_*` are over steps `scored_from..`, the first
/// step where every team has data; `*_from_step0` (the two teams that have data there) are
/// reported beside them, labelled.
#[derive(Debug, Clone, Default, Serialize)]
pub struct TeamOutcome {
    pub heterogeneous: Vec<f64>,
    pub aerial_only: Vec<f64>,
    pub boat_only: Vec<Option<f64>>,
    /// The heterogeneous team's calibration at each step: the mean over cells of error^2 /
    /// reported variance (1 when the reported variance is the error's).
    pub calibration: Vec<f64>,
    /// The first step where every team has data.
    pub scored_from: usize,
    /// Time-averaged MSE over steps `scored_from..`.
    pub mean_heterogeneous: f64,
    pub mean_aerial_only: f64,
    pub mean_boat_only: f64,
    /// Calibration averaged over steps `scored_from..`.
    pub mean_calibration: f64,
    /// Time-averaged MSE over every step (teams with data from step 0 only).
    pub heterogeneous_from_step0: f64,
    pub aerial_only_from_step0: f64,
    /// Boat disk centres `(row, col)` at each boat step, and the aerials' positions (m).
    pub boat_steps: Vec<usize>,
    pub disks: Vec<Vec<(usize, usize)>>,
    pub aerial_positions: Vec<Vec<(f64, f64)>>,
    /// The heterogeneous team's fused snapshot at each boat step (for figures).
    #[serde(skip)]
    pub snapshots: Vec<Vec<f64>>,
    /// Their reported variance per cell.
    #[serde(skip)]
    pub snapshot_variances: Vec<Vec<f64>>,
    /// Model rank after the last update.
    pub rank: usize,
    /// Every change of a sensor's verdict ([`fleet_mission::health`]).
    pub verdicts: Vec<fleet_mission::health::Verdict>,
    /// What the health tests did to the readings.
    pub screened: fleet_mission::health::Screened,
    /// With a fault: the steps whose readings it altered (or silenced), and each boat test's
    /// information on an offset by vehicle and step ([`fleet_mission::health::Screen::information`]).
    #[serde(skip)]
    pub altered: std::collections::BTreeSet<u64>,
    #[serde(skip)]
    pub information: BTreeMap<(usize, u64), f64>,
    /// The heterogeneous team's reliability by decile of reported variance over the scored
    /// steps: per decile (smallest variance first), mean error^2 over mean reported variance
    /// (1 when the variance is the error's there, not only on average).
    pub reliability: Vec<f64>,
    /// Each decile's mean reported variance (the diagram's x).
    pub reliability_variance: Vec<f64>,
    /// `(reported variance, error^2)` at every cell with a truth, per step (for the deciles).
    #[serde(skip)]
    cell_errors: Vec<Vec<(f32, f32)>>,
}

/// Deciles of reliability: pooled `(variance, error^2)` sorted by variance, cut into ten
/// equal counts; per decile the mean variance and mean error^2 / mean variance.
pub fn deciles(pairs: &mut [(f32, f32)]) -> (Vec<f64>, Vec<f64>) {
    if pairs.len() < 10 {
        return (vec![], vec![]);
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = pairs.len();
    (0..10)
        .map(|d| {
            let part = &pairs[d * n / 10..(d + 1) * n / 10];
            let var = part.iter().map(|p| p.0 as f64).sum::<f64>() / part.len() as f64;
            let err = part.iter().map(|p| p.1 as f64).sum::<f64>() / part.len() as f64;
            (var, err / var.max(1e-300))
        })
        .unzip()
}

/// The expected normalised calibration error of a reliability by decile ([`deciles`]): the
/// mean over the deciles of `|RMV - RMSE| / RMV` (root mean variance against root mean squared
/// error, the measure of Levi et al. 2022), which is `|1 - sqrt(ratio)|` for each decile's
/// ratio of mean error^2 to mean variance. 0 when every decile is calibrated; NaN without
/// deciles.
pub fn ence(reliability: &[f64]) -> f64 {
    reliability.iter().map(|r| (1.0 - r.max(0.0).sqrt()).abs()).sum::<f64>() / reliability.len() as f64
}

/// Mean over cells of error^2 / reported variance.
/// Over the cells where the truth has a value.
fn calibration(estimate: &[f64], variance: &[f64], truth: &[f64]) -> f64 {
    let (sum, n) = estimate
        .iter()
        .zip(variance)
        .zip(truth)
        .filter(|(_, t)| !t.is_nan())
        .fold((0.0, 0usize), |(s, n), ((e, v), t)| {
            (s + (e - t).powi(2) / v.max(1e-300), n + 1)
        });
    // A frame without a truth is not scored, as in `mse`.
    if n == 0 {
        return f64::NAN;
    }
    sum / n as f64
}

fn column(m: &Mat<f64>, k: usize) -> Vec<f64> {
    m.col(k).iter().copied().collect()
}

/// Run the loop on `truth` (already on the model grid) with the fleet's own engine: every
/// vehicle a [`VehicleBrain`] sensing with its own random stream under the plans of a
/// [`ServerCore`], which assimilates their batches epoch by epoch, exactly as the networked
/// fleet does (so the networked run equals this one by construction). Only the baselines are
/// added here: the aerial-only team reads the server's aerial estimate of each step, the
/// boat-only team builds its own model from the boats' samples.
pub fn run(
    cfg: &TeamConfig,
    truth: &FieldSeries,
    progress: impl FnMut(usize, usize),
) -> Result<TeamOutcome, TeamError> {
    run_placing(cfg, truth, false, None, progress)
}

/// Whether `cfg` can run on `truth` as [`run`] would run it (its grid, its frames, its land):
/// the same check the team makes when it starts, made before any run.
pub fn check(cfg: &TeamConfig, truth: &FieldSeries) -> Result<(), TeamError> {
    let (grid, cfg) = on_truth(cfg, truth)?;
    cfg.validate(&grid, truth.frames())
}

/// The grid of `truth` and `cfg` with the truth's land: what a team runs on.
fn on_truth(cfg: &TeamConfig, truth: &FieldSeries) -> Result<(Grid, TeamConfig), TeamError> {
    let grid = Grid::new(truth.rows, truth.cols, 1.0)?;
    let cfg = TeamConfig {
        land: truth.land(),
        ..cfg.clone()
    };
    Ok((grid, cfg))
}

/// What a failing sensor does to an epoch's batches before the server hears them: alters them
/// in place (`vehicle_of` gives a batch's vehicle index) and says which steps it changed.
pub type Alteration<'a> = &'a dyn Fn(&mut [MeasurementBatch], &dyn Fn(&MeasurementBatch) -> usize) -> BTreeSet<u64>;

/// [`run`] with every epoch's batches altered by `alter` (a sensor failing: the fault study
/// says how), the health tests' information on an offset kept.
pub fn run_altered(cfg: &TeamConfig, truth: &FieldSeries, alter: Alteration) -> Result<TeamOutcome, TeamError> {
    run_placing(cfg, truth, false, Some(alter), |_, _| {})
}

/// [`run`] with the boats placed by an oracle that knows the truth (a diagnostic, not a
/// placement a fleet can use): at each boat epoch a copy of the fleet senses the epoch with
/// the boats idle, and the disks go where that copy's estimate at the boats' sampling steps is
/// furthest from the truth ([`where_the_error_is`]). It bounds what putting the disks where the
/// error is can buy over the configured placement, on the same truth and noise.
pub fn run_oracle(cfg: &TeamConfig, truth: &FieldSeries) -> Result<TeamOutcome, TeamError> {
    run_placing(cfg, truth, true, None, |_, _| {})
}

/// Every vehicle senses epoch `e` under the server's plan; their batches.
fn sense(
    server: &ServerCore,
    brains: &mut [VehicleBrain],
    e: u64,
    truth_at: &impl Fn(usize) -> Vec<f64>,
) -> Result<Vec<MeasurementBatch>, TeamError> {
    let mut batches = vec![];
    for brain in brains {
        let plan = server
            .plan(&brain.id, e, 1)
            .ok_or_else(|| TeamError::Config(format!("no plan of {} for epoch {e}", brain.id)))?;
        brain.set_plan(plan);
        batches.extend(brain.sense_epoch(e, truth_at)?);
    }
    Ok(batches)
}

/// The server assimilates epoch `e` from `batches` (every batch of it).
fn assimilate(server: &mut ServerCore, batches: Vec<MeasurementBatch>, e: u64) -> Result<(), TeamError> {
    for b in batches {
        server.ingest(b).map_err(|err| match err {
            fleet_mission::server::IngestError::Model(m) => m,
            other => TeamError::Config(other.to_string()),
        })?;
    }
    if server.next_epoch() != e + 1 {
        return Err(TeamError::Config(format!(
            "epoch {e} was not assimilated with every batch in"
        )));
    }
    Ok(())
}

/// The oracle's disks for boat epoch `e`: a copy of the server and the vehicles (the same
/// random streams, so the same aerial noise) runs the epoch with the boats idle; the squared
/// error of its estimate, summed over the boats' sampling steps, is what the disks should
/// cover.
fn oracle_disks(
    server: &ServerCore,
    brains: &[VehicleBrain],
    e: u64,
    truth_at: &impl Fn(usize) -> Vec<f64>,
    cfg: &TeamConfig,
) -> Result<Vec<Option<BoatDisk>>, TeamError> {
    let grid = *server.assimilator().grid();
    let mut probe = server.clone();
    probe.redirect_boats(e, vec![None; cfg.boats])?;
    let mut copies = brains.to_vec();
    let batches = sense(&probe, &mut copies, e, truth_at)?;
    assimilate(&mut probe, batches, e)?;
    let mut err2 = vec![0.0; grid.len()];
    for k in probe.schedule().sample_steps(VehicleKind::Boat, e) {
        let estimate = step_of(probe.history().estimate(k))?;
        for ((s, x), t) in err2.iter_mut().zip(estimate.iter()).zip(truth_at(k)) {
            if !t.is_nan() {
                *s += (x - t).powi(2);
            }
        }
    }
    let excluded = cfg
        .fence
        .as_ref()
        .map_or_else(|| vec![false; grid.len()], |f| f.excluded(&grid));
    Ok(where_the_error_is(&grid, &err2, cfg.boats, cfg.radius, &excluded)
        .into_iter()
        .map(Some)
        .chain(std::iter::repeat(None))
        .take(cfg.boats)
        .collect())
}

/// Up to `m` disks of `radius`, not overlapping and outside `excluded`, chosen greedily by the
/// most `err2` summed over the disk: the disk with the most first, then the most among those
/// that do not touch it, and so on. Each is `(cells, centre)`.
pub fn where_the_error_is(grid: &Grid, err2: &[f64], m: usize, radius: f64, excluded: &[bool]) -> Vec<BoatDisk> {
    let mut taken = excluded.to_vec();
    taken.resize(grid.len(), false);
    let disks: Vec<(Vec<usize>, f64)> = (0..grid.len())
        .map(|i| grid.disk(grid.cell(i), radius))
        .map(|d| {
            let sum = d.iter().map(|&c| err2[c]).sum();
            (d, sum)
        })
        .collect();
    let mut out = vec![];
    while out.len() < m {
        let best = disks
            .iter()
            .enumerate()
            .filter(|(_, (d, _))| !d.is_empty() && d.iter().all(|&c| !taken[c]))
            .max_by(|a, b| a.1 .1.total_cmp(&b.1 .1).then(b.0.cmp(&a.0)));
        let Some((i, (d, _))) = best else { break };
        d.iter().for_each(|&c| taken[c] = true);
        let centre = grid.cell(i);
        out.push((d.clone(), (centre.row, centre.col)));
    }
    out
}

impl TeamOutcome {
    /// The fused team's step against the truth `x`: its MSE, calibration, and each cell's
    /// reported variance beside its squared error (the reliability diagram's).
    fn score_fused(&mut self, x: &[f64], estimate: &[f64], variance: &[f64]) {
        self.heterogeneous.push(mse(estimate, x));
        self.calibration.push(calibration(estimate, variance, x));
        self.cell_errors.push(
            x.iter()
                .zip(estimate)
                .zip(variance)
                .filter(|((t, _), _)| !t.is_nan())
                .map(|((t, e), v)| (*v as f32, ((e - t) * (e - t)) as f32))
                .collect(),
        );
    }
}

fn run_placing(
    cfg: &TeamConfig,
    truth: &FieldSeries,
    oracle: bool,
    alter: Option<Alteration>,
    mut progress: impl FnMut(usize, usize),
) -> Result<TeamOutcome, TeamError> {
    let (grid, cfg) = on_truth(cfg, truth)?;
    let (cfg, frames) = (&cfg, truth.frames());
    let mut server = ServerCore::new(cfg, grid, frames)?.with_aerial_history();
    if alter.is_some() {
        server = server.with_screen_information();
    }
    let truth_at = |k: usize| column(&truth.snapshots, k);
    let mut brains = brains_of(&server, cfg, grid);
    let mut out = TeamOutcome::default();
    let mut boat_only = BoatOnly::new(cfg, grid.len());
    for e in 0..server.schedule().epochs() {
        let steps = server.steps_of(e);
        if oracle && e > 0 && !server.schedule().sample_steps(VehicleKind::Boat, e).is_empty() {
            let disks = oracle_disks(&server, &brains, e, &truth_at, cfg)?;
            server.redirect_boats(e, disks)?;
        }
        let allocation = server
            .allocation(e)
            .ok_or_else(|| TeamError::Config(format!("no allocation for epoch {e}")))?;
        let mut batches = sense(&server, &mut brains, e, &truth_at)?;
        if let Some(alter) = alter {
            out.altered.extend(alter(&mut batches, &|b| {
                server.roster().index_of(&b.vehicle).unwrap_or(usize::MAX)
            }));
        }
        let boat_samples: Vec<Sample> = batches
            .iter()
            .filter(|b| b.kind == VehicleKind::Boat)
            .flat_map(|b| b.samples.iter().cloned())
            .collect();
        assimilate(&mut server, batches, e)?;
        for k in steps.clone() {
            let x = truth_at(k);
            let (estimate, variance) = (
                step_of(server.history().estimate(k))?,
                step_of(server.history().variance(k))?,
            );
            out.score_fused(&x, &estimate, &variance);
            out.aerial_only.push(mse(&server.aerial_estimates[k], &x));
            // Boat-only team, from the same boat samples.
            let here: Vec<&Sample> = boat_samples.iter().filter(|s| s.step as usize == k).collect();
            out.boat_only
                .push(boat_only.step(k, &here)?.map(|b| mse(&b, &x)).filter(|v| !v.is_nan()));
            if e > 0 && server.schedule().sample_steps(VehicleKind::Boat, e).contains(&k) {
                out.boat_steps.push(k);
                out.disks
                    .push(allocation.boats.iter().flatten().map(|(_, c)| *c).collect());
                out.aerial_positions.push(allocation.aerials.clone());
                out.snapshots.push(estimate.to_vec());
                out.snapshot_variances.push(variance.to_vec());
            }
            progress(k + 1, frames);
        }
    }
    out.rank = server.assimilator().rank();
    out.verdicts = server.verdicts();
    out.screened = server.health().1;
    out.information = server
        .assimilator()
        .screen_state()
        .information()
        .cloned()
        .unwrap_or_default();
    out.score(frames);
    Ok(out)
}

/// Each vehicle as the vehicle node runs it; offline they reach every place in time.
pub(crate) fn brains_of(server: &ServerCore, cfg: &TeamConfig, grid: Grid) -> Vec<VehicleBrain> {
    server
        .vehicles()
        .iter()
        .enumerate()
        .map(|(v, spec)| {
            let noise = match spec.kind {
                VehicleKind::Aerial => server.assimilator().aerial_noise(),
                VehicleKind::Boat => AerialNoise {
                    sigma0: cfg.boat_sigma,
                    growth_per_m: 0.0,
                },
            };
            let rng = fleet_mission::vehicle::vehicle_rng(cfg.seed, v);
            VehicleBrain::new(&spec.id, spec.kind, grid, *server.schedule(), noise, rng, f64::MAX)
        })
        .collect()
}

/// The boat-only team: its snapshots at boat steps, its model once it has enough. It has no
/// estimate before its first sample (those steps are not scored), then its latest snapshot
/// until it has a model.
struct BoatOnly {
    cfg: DmdConfig,
    boat_var: f64,
    boat_period: usize,
    n: usize,
    snaps: Vec<Vec<f64>>,
    /// The model, its basis, and the step of its newest snapshot.
    model: Option<(DmdModel, Mat<f64>, usize)>,
    guess: Option<Vec<f64>>,
    /// The least and the most of every value the boats have measured.
    seen: (f64, f64),
}

/// Whether a reconstruction stays within the range of the values measured so far, widened by
/// that range on either side. The disks' rows of the modes can be nearly collinear (4 disks of
/// 13 cells for 6 modes on the 500 hPa height): the least-squares fit then amplifies the noise
/// into values hundreds of times the field's (4e5 m for a 5,500 m height), and a model fitted
/// on that snapshot grows 100-fold a boat period. Such a fit is no estimate of the field: the
/// team keeps the measured mean, as when the modes are not determined at all.
fn plausible(field: &[f64], (lo, hi): (f64, f64)) -> bool {
    let width = hi - lo;
    field.iter().all(|&v| v >= lo - width && v <= hi + width)
}

impl BoatOnly {
    fn new(cfg: &TeamConfig, n: usize) -> Self {
        Self {
            cfg: DmdConfig {
                method: Method::Batch,
                rank: cfg.rank,
                debias: Default::default(),
                gamma: cfg.gamma,
                forgetting: Default::default(),
            },
            boat_var: cfg.boat_sigma * cfg.boat_sigma,
            boat_period: cfg.boat_period,
            n,
            snaps: vec![],
            model: None,
            guess: None,
            seen: (f64::INFINITY, f64::NEG_INFINITY),
        }
    }

    /// Its estimate at step `k` from the boats' samples there (none: its forecast or guess).
    fn step(&mut self, k: usize, here: &[&Sample]) -> Result<Option<Vec<f64>>, TeamError> {
        let measured_cells: Vec<usize> = here.iter().flat_map(|s| s.cells.iter().map(|&c| c as usize)).collect();
        let measured_vals: Vec<f64> = here.iter().flat_map(|s| s.values.iter().copied()).collect();
        if measured_cells.is_empty() {
            return Ok(match &self.model {
                // Its model steps are boat periods.
                Some((p, _, at)) => Some(p.predict((k - at) as f64 / self.boat_period as f64)),
                None => self.guess.clone(),
            });
        }
        let mean = measured_vals.iter().sum::<f64>() / measured_vals.len() as f64;
        self.seen = measured_vals
            .iter()
            .fold(self.seen, |(lo, hi), &v| (lo.min(v), hi.max(v)));
        let mut est = match &self.model {
            Some((_, b, _)) => gappy::reconstruct(b.as_ref(), &measured_cells, &measured_vals, self.boat_var)
                .ok()
                .map(|g| g.field)
                .filter(|f| plausible(f, self.seen))
                .unwrap_or_else(|| vec![mean; self.n]),
            None => vec![mean; self.n],
        };
        for (&c, &v) in measured_cells.iter().zip(&measured_vals) {
            est[c] = v;
        }
        self.snaps.push(est.clone());
        if self.snaps.len() >= 3 {
            let z = fleet_mission::assimilator::to_mat(&self.snaps);
            let m = self.snaps.len() - 1;
            let bm = self.cfg.init(z.subcols(0, m), z.subcols(1, m))?;
            let (p, b) = fleet_mission::assimilator::fit_to(bm.as_ref(), &est)?;
            self.model = Some((p, b, k));
        }
        self.guess = Some(est.clone());
        Ok(Some(est))
    }
}

impl TeamOutcome {
    /// The means over the scored steps: from the first where every team has data (the
    /// boat-only team's first estimate), and from step 0 for the teams that have data there.
    fn score(&mut self, frames: usize) {
        self.scored_from = self.boat_only.iter().position(Option::is_some).unwrap_or(frames);
        let mean_from = |v: &[f64], from: usize| mean_scored(&v[from.min(v.len())..]);
        self.mean_heterogeneous = mean_from(&self.heterogeneous, self.scored_from);
        self.mean_aerial_only = mean_from(&self.aerial_only, self.scored_from);
        self.mean_boat_only = mean_from(
            &self.boat_only.iter().map(|v| v.unwrap_or(f64::NAN)).collect::<Vec<_>>(),
            self.scored_from,
        );
        self.mean_calibration = mean_from(&self.calibration, self.scored_from);
        self.heterogeneous_from_step0 = mean_from(&self.heterogeneous, 0);
        let mut pooled: Vec<(f32, f32)> = self.cell_errors.drain(..).skip(self.scored_from).flatten().collect();
        (self.reliability_variance, self.reliability) = deciles(&mut pooled);
        self.aerial_only_from_step0 = mean_from(&self.aerial_only, 0);
    }
}

/// A step of the core's history (in memory in an experiment: a miss is a defect, said).
fn step_of(step: std::io::Result<std::borrow::Cow<'_, [f64]>>) -> Result<std::borrow::Cow<'_, [f64]>, TeamError> {
    step.map_err(|e| TeamError::History(e.to_string()))
}
