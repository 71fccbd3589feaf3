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
//!   same steps); until it has a model the measured cells' mean fills the grid.

use crate::dmd::{DmdConfig, DmdModel, Method, RankPolicy};
use crate::fusion::AerialNoise;
use crate::fusion::Scheme;
use crate::grid::Grid;
use crate::mission;
use crate::mission::server::ServerCore;
use crate::mission::vehicle::VehicleBrain;
use crate::process::FieldSeries;
use crate::protocol::{Sample, VehicleKind};
use crate::sensing::gappy;
use faer::Mat;
use serde::{Deserialize, Serialize};

/// Where boats go.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Placement {
    /// Block pivoted QR over the model's spatial modes (Alg. 2).
    Qr,
    /// Greedy D-optimal disks.
    DOptimal,
    /// Uniformly random non-overlapping disks (seeded): the baseline.
    Random,
}

/// Every choice of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TeamConfig {
    pub aerials: usize,
    /// Aerial frames every this many steps (time rate).
    pub aerial_period: usize,
    /// Aerials keep every this-many-th cell (space rate).
    pub aerial_stride: usize,
    /// Aerial noise std at the aerial, and its growth per cell of distance.
    pub aerial_sigma0: f64,
    pub aerial_growth_per_cell: f64,
    pub boats: usize,
    /// Boat samples (and model updates) every this many steps.
    pub boat_period: usize,
    /// Sensing radius in cells.
    pub radius: f64,
    /// Boat noise standard deviation.
    pub boat_sigma: f64,
    /// Steps of aerial-only data before the first model.
    pub init_steps: usize,
    /// `full`, `optimal`, `energy:<f>` or an integer (`rank = 6` or `rank = "6"`).
    #[serde(deserialize_with = "rank_text")]
    pub rank: String,
    pub method: Method,
    pub gamma: f64,
    pub placement: Placement,
    pub fusion: Scheme,
    /// Floor of the aerials' coverage density.
    pub density_floor: f64,
    pub seed: u64,
}

impl Default for TeamConfig {
    fn default() -> Self {
        Self {
            aerials: 2,
            aerial_period: 1,
            aerial_stride: 5,
            aerial_sigma0: 0.01,
            aerial_growth_per_cell: 0.0005,
            boats: 5,
            boat_period: 5,
            radius: 10.0,
            boat_sigma: 0.01,
            init_steps: 20,
            rank: "10".into(),
            method: Method::General,
            gamma: 1.0,
            placement: Placement::Qr,
            fusion: Scheme::InverseVariance,
            density_floor: 0.2,
            seed: 7,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TeamError {
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error(transparent)]
    Dmd(#[from] crate::dmd::DmdError),
    #[error(transparent)]
    Sensing(#[from] crate::sensing::SensingError),
    #[error(transparent)]
    Fusion(#[from] crate::fusion::FusionError),
    #[error(transparent)]
    Grid(#[from] crate::grid::GridError),
}

/// Per-step mean squared errors of the three teams, and what the fleet did.
///
/// Scoring (every team over the same steps, never a team without data): the heterogeneous and
/// aerial-only teams have data from step 0; the boat-only team from its first boat sample
/// (`boat_only[k]` is `None` before). The `mean_*` are over steps `scored_from..`, the first
/// step where every team has data; `*_from_step0` (the two teams that have data there) are
/// reported beside them, labelled.
#[derive(Debug, Clone, Serialize)]
pub struct TeamOutcome {
    pub heterogeneous: Vec<f64>,
    pub aerial_only: Vec<f64>,
    pub boat_only: Vec<Option<f64>>,
    /// The first step where every team has data.
    pub scored_from: usize,
    /// Time-averaged MSE over steps `scored_from..`.
    pub mean_heterogeneous: f64,
    pub mean_aerial_only: f64,
    pub mean_boat_only: f64,
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
    /// Model rank after the last update.
    pub rank: usize,
}

impl TeamConfig {
    pub fn validate(&self, grid: &Grid, frames: usize) -> Result<RankPolicy, TeamError> {
        let bad = |m: String| Err(TeamError::Config(m));
        let rank: RankPolicy = self.rank.parse().map_err(|e: String| TeamError::Config(e))?;
        if self.aerials == 0 || self.boats == 0 {
            return bad("a heterogeneous team needs at least one aerial and one boat".into());
        }
        if self.aerial_period == 0 || self.boat_period == 0 || self.aerial_stride == 0 {
            return bad("periods and stride must be at least 1".into());
        }
        if self.init_steps < 3 || self.init_steps + self.boat_period > frames {
            return bad(format!("init_steps {} must be >= 3 and leave at least one epoch of {} steps in {frames} frames", self.init_steps, self.boat_period));
        }
        let nonneg = [self.aerial_sigma0, self.aerial_growth_per_cell, self.boat_sigma, self.density_floor];
        if nonneg.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || !(self.radius.is_finite() && self.radius >= 0.0) {
            return bad("noise, radius and density floor must be finite and >= 0".into());
        }
        if self.density_floor > 1.0 {
            return bad("density_floor must be in [0, 1]".into());
        }
        if grid.is_empty() {
            return bad("empty grid".into());
        }
        if self.method == Method::LongTerm {
            return bad("method = \"long-term\": its operator has every one of the grid's N modes, so the boats' gappy fit is underdetermined and every disk scores the same (block QR sees Phi Phi^T = I); a team or mission uses \"general\" (default) or \"batch\", which keep the rank".into());
        }
        if self.method != Method::LongTerm && self.gamma != 1.0 {
            return bad(format!("gamma = {}: the forgetting factor applies to method = \"long-term\" only ({:?} keeps every snapshot)", self.gamma, self.method));
        }
        if !(self.gamma > 0.0 && self.gamma <= 1.0) {
            return bad(format!("gamma = {}: must be in (0, 1]", self.gamma));
        }
        let lattice = grid.strided(self.aerial_stride)?;
        if self.aerials > lattice.rows * lattice.cols {
            return bad(format!(
                "aerials = {}: the aerial lattice has only {} cells ({} x {} grid, aerial_stride {}), so some aerial would see nothing; use at most {} aerials or a smaller aerial_stride",
                self.aerials,
                lattice.rows * lattice.cols,
                grid.rows,
                grid.cols,
                self.aerial_stride,
                lattice.rows * lattice.cols
            ));
        }
        if !disk_fits(grid, self.boats, self.radius) {
            return bad(match largest_radius(grid, self.boats) {
                Some(r) => format!("radius = {}: {} boats' disks of that radius do not fit side by side on the {} x {} grid; at most radius {r}", self.radius, self.boats, grid.rows, grid.cols),
                None => format!("boats = {}: more boats than cells on the {} x {} grid", self.boats, grid.rows, grid.cols),
            });
        }
        Ok(rank)
    }
}

/// The rank as text, from a string (`"optimal"`, `"6"`) or a bare integer (`6`).
fn rank_text<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Rank {
        Text(String),
        Number(u64),
    }
    match Rank::deserialize(d).map_err(|_| serde::de::Error::custom("rank: give \"full\", \"optimal\", \"energy:<fraction>\" or a positive integer"))? {
        Rank::Text(t) => Ok(t),
        Rank::Number(n) => Ok(n.to_string()),
    }
}

/// The largest sensing radius (cells) at which `boats` disks fit side by side on `grid`: a
/// disk inside the grid, and the disks' cells together no more than the grid's.
fn largest_radius(grid: &Grid, boats: usize) -> Option<usize> {
    (0..grid.rows.min(grid.cols)).take_while(|&r| disk_fits(grid, boats, r as f64)).last()
}

fn disk_fits(grid: &Grid, boats: usize, radius: f64) -> bool {
    let span = 2 * radius.floor() as usize + 1;
    if span > grid.rows.min(grid.cols) {
        return false;
    }
    let centre = crate::grid::Cell::new(grid.rows / 2, grid.cols / 2);
    boats.saturating_mul(grid.disk(centre, radius).len()) <= grid.len()
}

fn mse(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len().max(1) as f64
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
pub fn run(cfg: &TeamConfig, truth: &FieldSeries, mut progress: impl FnMut(usize, usize)) -> Result<TeamOutcome, TeamError> {
    let grid = Grid::new(truth.rows, truth.cols, 1.0)?;
    let frames = truth.frames();
    let mut server = ServerCore::new(cfg, grid, frames)?;
    let n = grid.len();
    let boat_var = cfg.boat_sigma * cfg.boat_sigma;
    let truth_at = |k: usize| column(&truth.snapshots, k);
    // Each vehicle as the vehicle node runs it; offline they reach every place in time.
    let mut brains: Vec<VehicleBrain> = server
        .vehicles()
        .iter()
        .enumerate()
        .map(|(v, spec)| {
            let noise = match spec.kind {
                VehicleKind::Aerial => server.assimilator().aerial_noise(),
                VehicleKind::Boat => AerialNoise { sigma0: cfg.boat_sigma, growth_per_m: 0.0 },
            };
            VehicleBrain::new(&spec.id, spec.kind, grid, *server.schedule(), noise, mission::vehicle_rng(cfg.seed, v), f64::MAX)
        })
        .collect();

    let mut out = TeamOutcome {
        heterogeneous: vec![],
        aerial_only: vec![],
        boat_only: vec![],
        scored_from: 0,
        mean_heterogeneous: 0.0,
        mean_aerial_only: 0.0,
        mean_boat_only: 0.0,
        heterogeneous_from_step0: 0.0,
        aerial_only_from_step0: 0.0,
        boat_steps: vec![],
        disks: vec![],
        aerial_positions: vec![],
        snapshots: vec![],
        rank: 0,
    };
    // Boat-only team: its snapshots at boat steps, its model once it has enough. It has no
    // estimate before its first sample (those steps are not scored), then its latest snapshot
    // until it has a model.
    let boat_cfg = DmdConfig { method: Method::Batch, rank: cfg.rank.parse().map_err(TeamError::Config)?, debias: Default::default(), gamma: cfg.gamma, forgetting: Default::default() };
    let mut boat_snaps: Vec<Vec<f64>> = vec![];
    let mut boat_model: Option<(DmdModel, Mat<f64>, usize)> = None; // model, basis, step of its newest snapshot
    let mut boat_guess: Option<Vec<f64>> = None;

    for e in 0..server.schedule().epochs() {
        let steps = server.steps_of(e);
        let allocation = server.allocation(e).ok_or_else(|| TeamError::Config(format!("no allocation for epoch {e}")))?;
        let mut batches = vec![];
        for brain in &mut brains {
            let plan = server.plan(&brain.id, e, 1).ok_or_else(|| TeamError::Config(format!("no plan of {} for epoch {e}", brain.id)))?;
            brain.set_plan(plan);
            batches.extend(brain.sense_epoch(e, truth_at)?);
        }
        let boat_samples: Vec<Sample> = batches.iter().filter(|b| b.kind == VehicleKind::Boat).flat_map(|b| b.samples.iter().cloned()).collect();
        for b in batches {
            server.ingest(b).map_err(|err| match err {
                crate::mission::server::IngestError::Model(m) => m,
                other => TeamError::Config(other.to_string()),
            })?;
        }
        if server.next_epoch() != e + 1 {
            return Err(TeamError::Config(format!("epoch {e} was not assimilated with every batch in")));
        }
        for k in steps.clone() {
            let x = truth_at(k);
            out.heterogeneous.push(mse(&server.snapshots[k], &x));
            out.aerial_only.push(mse(&server.aerial_estimates[k], &x));
            // Boat-only team, from the same boat samples.
            let here: Vec<&Sample> = boat_samples.iter().filter(|s| s.step as usize == k).collect();
            let measured_cells: Vec<usize> = here.iter().flat_map(|s| s.cells.iter().map(|&c| c as usize)).collect();
            let measured_vals: Vec<f64> = here.iter().flat_map(|s| s.values.iter().copied()).collect();
            let boat_est = if !measured_cells.is_empty() {
                let mean = measured_vals.iter().sum::<f64>() / measured_vals.len() as f64;
                let mut est = match &boat_model {
                    Some((_, b, _)) => gappy::reconstruct(b.as_ref(), &measured_cells, &measured_vals, boat_var).map(|g| g.field).unwrap_or_else(|_| vec![mean; n]),
                    None => vec![mean; n],
                };
                for (&c, &v) in measured_cells.iter().zip(&measured_vals) {
                    est[c] = v;
                }
                boat_snaps.push(est.clone());
                if boat_snaps.len() >= 3 {
                    let z = mission::to_mat(&boat_snaps);
                    let m = boat_snaps.len() - 1;
                    let bm = boat_cfg.init(z.subcols(0, m), z.subcols(1, m))?;
                    let (p, b) = mission::fit_to(bm.as_ref(), &est)?;
                    boat_model = Some((p, b, k));
                }
                boat_guess = Some(est.clone());
                Some(est)
            } else {
                match &boat_model {
                    // Its model steps are boat periods.
                    Some((p, _, at)) => Some(p.predict((k - at) as f64 / cfg.boat_period as f64)),
                    None => boat_guess.clone(),
                }
            };
            out.boat_only.push(boat_est.map(|b| mse(&b, &x)));
            if e > 0 && server.schedule().sample_steps(VehicleKind::Boat, e).contains(&k) {
                out.boat_steps.push(k);
                out.disks.push(allocation.boats.iter().flatten().map(|(_, c)| *c).collect());
                out.aerial_positions.push(allocation.aerials.clone());
                out.snapshots.push(server.snapshots[k].clone());
            }
            progress(k + 1, frames);
        }
    }
    out.scored_from = out.boat_only.iter().position(Option::is_some).unwrap_or(frames);
    let mean_from = |v: &[f64], from: usize| v[from.min(v.len())..].iter().sum::<f64>() / v.len().saturating_sub(from).max(1) as f64;
    out.mean_heterogeneous = mean_from(&out.heterogeneous, out.scored_from);
    out.mean_aerial_only = mean_from(&out.aerial_only, out.scored_from);
    out.mean_boat_only = mean_from(&out.boat_only.iter().map(|v| v.unwrap_or(0.0)).collect::<Vec<_>>(), out.scored_from);
    out.heterogeneous_from_step0 = mean_from(&out.heterogeneous, 0);
    out.aerial_only_from_step0 = mean_from(&out.aerial_only, 0);
    out.rank = server.assimilator().rank();
    Ok(out)
}
