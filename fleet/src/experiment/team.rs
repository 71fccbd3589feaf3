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
//!   its own model's modes, between boat steps its own prediction. Until it has a model (the
//!   first `init_steps` steps) the measured cells' mean fills the grid.

use crate::dmd::{Dmd, DmdConfig, DmdModel, Method, RankPolicy};
use crate::fusion::{fuse, AerialFrame, AerialNoise, Estimate, Measured, Scheme};
use crate::grid::{Cell, Grid};
use crate::process::FieldSeries;
use crate::sensing::{assign::assign, coverage, gappy, qr, real_basis};
use faer::Mat;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
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
    /// `full`, `optimal`, `energy:<f>` or an integer.
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
#[derive(Debug, Clone, Serialize)]
pub struct TeamOutcome {
    pub heterogeneous: Vec<f64>,
    pub aerial_only: Vec<f64>,
    pub boat_only: Vec<f64>,
    /// Time-averaged MSE over the steps after initialisation.
    pub mean_heterogeneous: f64,
    pub mean_aerial_only: f64,
    pub mean_boat_only: f64,
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
        if grid.len() == 0 {
            return bad("empty grid".into());
        }
        Ok(rank)
    }
}

fn mse(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len().max(1) as f64
}

fn column(m: &Mat<f64>, k: usize) -> Vec<f64> {
    m.col(k).iter().copied().collect()
}

fn to_mat(cols: &[Vec<f64>]) -> Mat<f64> {
    let n = cols.first().map_or(0, |c| c.len());
    Mat::from_fn(n, cols.len(), |i, j| cols[j][i])
}

/// `m` random non-overlapping disks (rejection sampling; fewer if the grid is full).
fn random_disks(grid: &Grid, m: usize, radius: f64, rng: &mut ChaCha8Rng) -> Vec<Vec<usize>> {
    let mut taken = vec![false; grid.len()];
    let mut out = vec![];
    for _ in 0..m * 200 {
        if out.len() == m {
            break;
        }
        let c = Cell::new(rng.random_range(0..grid.rows), rng.random_range(0..grid.cols));
        let d = grid.disk(c, radius);
        if d.iter().all(|&i| !taken[i]) {
            d.iter().for_each(|&i| taken[i] = true);
            out.push(d);
        }
    }
    out
}

/// The model after fitting/updating, ready to predict forward from its newest snapshot.
fn fitted(model: &dyn Dmd, newest: &[f64]) -> Result<(DmdModel, Mat<f64>), TeamError> {
    let modes = model.decompose()?;
    let basis = real_basis(modes.modes.as_ref())?;
    Ok((modes.model(newest, 1.0)?, basis))
}

/// Run the loop on `truth` (already on the model grid).
pub fn run(cfg: &TeamConfig, truth: &FieldSeries, mut progress: impl FnMut(usize, usize)) -> Result<TeamOutcome, TeamError> {
    let grid = Grid::new(truth.rows, truth.cols, 1.0)?;
    let frames = truth.frames();
    let rank = cfg.validate(&grid, frames)?;
    let n = grid.len();
    let dmd = DmdConfig { method: cfg.method, rank, debias: Default::default(), gamma: cfg.gamma };
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let noise = AerialNoise { sigma0: cfg.aerial_sigma0, growth_per_m: cfg.aerial_growth_per_cell };
    let boat_var = cfg.boat_sigma * cfg.boat_sigma;
    let truth_at = |k: usize| column(&truth.snapshots, k);

    let mut aerials = coverage::uniform_formation(&grid, cfg.aerials)?.positions;
    let mut aerial_est: Option<Estimate> = None;
    let sense_aerial = |k: usize, aerials: &[(f64, f64)], rng: &mut ChaCha8Rng, held: &mut Option<Estimate>| -> Result<Estimate, TeamError> {
        if k % cfg.aerial_period == 0 || held.is_none() {
            *held = Some(AerialFrame::sense(&grid, &truth_at(k), cfg.aerial_stride, aerials, noise, rng)?.upsample()?);
        }
        Ok(held.clone().expect("set above"))
    };

    let mut out = TeamOutcome {
        heterogeneous: vec![],
        aerial_only: vec![],
        boat_only: vec![],
        mean_heterogeneous: 0.0,
        mean_aerial_only: 0.0,
        mean_boat_only: 0.0,
        boat_steps: vec![],
        disks: vec![],
        aerial_positions: vec![],
        snapshots: vec![],
        rank: 0,
    };

    // 1. Initialisation: aerial frames only; the first model from them.
    let mut snaps: Vec<Vec<f64>> = vec![];
    for k in 0..cfg.init_steps {
        let a = sense_aerial(k, &aerials, &mut rng, &mut aerial_est)?;
        let x = truth_at(k);
        let e = mse(&a.values, &x);
        out.heterogeneous.push(e);
        out.aerial_only.push(e);
        snaps.push(a.values);
        progress(k + 1, frames);
    }
    let z = to_mat(&snaps);
    let m0 = snaps.len() - 1;
    let mut model = dmd.init(z.subcols(0, m0), z.subcols(1, m0))?;
    let mut boats: Vec<(f64, f64)> = (0..cfg.boats).map(|_| (rng.random_range(0.0..grid.width_m()), rng.random_range(0.0..grid.height_m()))).collect();
    // Boat-only team: its snapshots at boat steps, its model once it has enough.
    let mut boat_snaps: Vec<Vec<f64>> = vec![];
    let mut boat_model: Option<(DmdModel, Mat<f64>, usize)> = None; // model, basis, step of its newest snapshot
    let boat_cfg = DmdConfig { method: Method::Batch, ..dmd };
    // The boat-only team knows nothing before its first sample: its estimate is 0 until then
    // (those steps count against it), then its latest snapshot until it has a model.
    let mut boat_guess: Vec<f64> = vec![0.0; n];
    for k in 0..cfg.init_steps {
        out.boat_only.push(mse(&boat_guess, &truth_at(k)));
    }
    // Prediction variance for inverse-variance fusion: mean squared innovation seen so far.
    let mut pred_var = aerial_est.as_ref().map_or(1.0, |a| a.variance.iter().sum::<f64>() / n as f64).max(1e-12);
    // The aerials' error beyond their noise model (interpolation), calibrated at boat steps.
    let mut aerial_extra = 0.0;

    let mut k0 = cfg.init_steps;
    while k0 < frames {
        let newest = snaps.last().expect("init snapshots").clone();
        let (pred, basis) = fitted(model.as_ref(), &newest)?;
        // 4. Placement from the current model.
        let disks: Vec<Vec<usize>> = match cfg.placement {
            Placement::Qr => qr::block_qr(basis.as_ref(), &grid, cfg.boats, cfg.radius)?.into_iter().map(|d| d.cells).collect(),
            Placement::DOptimal => qr::block_dopt(basis.as_ref(), &grid, cfg.boats, cfg.radius)?.into_iter().map(|d| d.cells).collect(),
            Placement::Random => random_disks(&grid, cfg.boats, cfg.radius, &mut rng),
        };
        let centres: Vec<(usize, usize)> = disks
            .iter()
            .map(|d| {
                // The disk's centre cell: the mean of its cells, snapped to a cell.
                let (r, c) = d.iter().fold((0.0, 0.0), |(r, c), &i| (r + grid.cell(i).row as f64, c + grid.cell(i).col as f64));
                ((r / d.len() as f64).round() as usize, (c / d.len() as f64).round() as usize)
            })
            .collect();
        let targets: Vec<(f64, f64)> = centres.iter().map(|&(r, c)| grid.centre_m(Cell::new(r, c))).collect();
        let (assignment, _) = assign(&boats, &targets, 1.0)?;
        for (b, a) in boats.iter_mut().zip(&assignment) {
            if let Some(t) = a {
                *b = targets[*t];
            }
        }
        let density = coverage::temporal_density(&pred, cfg.density_floor)?;
        aerials = coverage::lloyd(&grid, &density, &aerials, 50, 1e-3)?.positions;

        let k_end = (k0 + cfg.boat_period).min(frames);
        let boat_step = k_end - 1;
        let mut epoch: Vec<Vec<f64>> = vec![];
        for k in k0..k_end {
            let x = truth_at(k);
            let aerial = sense_aerial(k, &aerials, &mut rng, &mut aerial_est)?;
            let ahead = (k + 1 - k0) as f64;
            let predicted = pred.predict(ahead);
            let mut aerial = aerial;
            let (hifi, measured_cells, measured_vals) = if k == boat_step && k_end - k0 == cfg.boat_period {
                let cells: Vec<usize> = disks.iter().flatten().copied().collect();
                let vals: Vec<f64> = cells.iter().map(|&c| x[c] + cfg.boat_sigma * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut rng)).collect();
                // Calibrate each source's error against the boats' measurements (innovations
                // at the measured cells, less the boats' own noise): the aerials' error is
                // mostly interpolation, the prediction's mostly model error, and neither is in
                // their noise models.
                let innovation = |est: &[f64]| -> f64 {
                    let m = cells.iter().zip(&vals).map(|(&c, v)| (est[c] - v).powi(2)).sum::<f64>() / cells.len() as f64;
                    (m - boat_var).max(1e-12)
                };
                let noise_part = cells.iter().map(|&c| aerial.variance[c]).sum::<f64>() / cells.len() as f64;
                aerial_extra = (innovation(&aerial.values) - noise_part).max(0.0);
                pred_var = innovation(&predicted);
                let est = match gappy::reconstruct(basis.as_ref(), &cells, &vals, boat_var) {
                    Ok(g) => {
                        // Truncation error: the fit's residual at the measured cells, inflated
                        // for the degrees of freedom the fit used.
                        let dof = (cells.len() as f64 - basis.ncols() as f64).max(1.0);
                        let resid = cells.iter().zip(&vals).map(|(&c, v)| (g.field[c] - v).powi(2)).sum::<f64>() / dof;
                        let extra = (resid - boat_var).max(0.0);
                        Estimate { values: g.field, variance: g.variance.iter().map(|v| v + extra).collect() }
                    }
                    // Too few independent cells for the modes: keep the prediction.
                    Err(crate::sensing::SensingError::Underdetermined { .. }) => Estimate { values: predicted.clone(), variance: vec![pred_var; n] },
                    Err(e) => return Err(e.into()),
                };
                (est, cells, vals)
            } else {
                (Estimate { values: predicted.clone(), variance: vec![pred_var; n] }, vec![], vec![])
            };
            aerial.variance.iter_mut().for_each(|v| *v += aerial_extra);
            let measured = (!measured_cells.is_empty()).then_some(Measured { cells: &measured_cells, values: &measured_vals, noise_var: boat_var });
            let fused = fuse(cfg.fusion, n, &[&aerial, &hifi], measured)?;
            out.heterogeneous.push(mse(&fused.values, &x));
            out.aerial_only.push(mse(&aerial.values, &x));

            // Boat-only team.
            let boat_est = if !measured_cells.is_empty() {
                let est = match &boat_model {
                    Some((_, b, _)) => match gappy::reconstruct(b.as_ref(), &measured_cells, &measured_vals, boat_var) {
                        Ok(g) => g.field,
                        Err(_) => vec![measured_vals.iter().sum::<f64>() / measured_vals.len() as f64; n],
                    },
                    None => vec![measured_vals.iter().sum::<f64>() / measured_vals.len() as f64; n],
                };
                let mut est = est;
                for (&c, &v) in measured_cells.iter().zip(&measured_vals) {
                    est[c] = v;
                }
                boat_snaps.push(est.clone());
                if boat_snaps.len() >= 3 {
                    let z = to_mat(&boat_snaps);
                    let m = boat_snaps.len() - 1;
                    let bm = boat_cfg.init(z.subcols(0, m), z.subcols(1, m))?;
                    let (p, b) = fitted(bm.as_ref(), &est)?;
                    boat_model = Some((p, b, k));
                }
                boat_guess = est.clone();
                est
            } else {
                match &boat_model {
                    // Its model steps are boat periods.
                    Some((p, _, at)) => p.predict((k - at) as f64 / cfg.boat_period as f64),
                    None => boat_guess.clone(),
                }
            };
            out.boat_only.push(mse(&boat_est, &x));
            if k == boat_step {
                out.boat_steps.push(k);
                out.disks.push(centres.clone());
                out.aerial_positions.push(aerials.clone());
                out.snapshots.push(fused.values.clone());
            }
            epoch.push(fused.values);
            progress(k + 1, frames);
        }
        // 3. Assimilate the epoch's snapshots (pairs chained from the last one).
        let mut chain = vec![newest];
        chain.extend(epoch.iter().cloned());
        let z = to_mat(&chain);
        let m = chain.len() - 1;
        model.update(z.subcols(0, m), z.subcols(1, m))?;
        snaps.extend(epoch);
        k0 = k_end;
    }
    let tail = |v: &[f64]| v[cfg.init_steps..].iter().sum::<f64>() / (v.len() - cfg.init_steps).max(1) as f64;
    out.mean_heterogeneous = tail(&out.heterogeneous);
    out.mean_aerial_only = tail(&out.aerial_only);
    out.mean_boat_only = tail(&out.boat_only);
    out.rank = model.rank();
    Ok(out)
}
