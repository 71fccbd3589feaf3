//! The fleet's loop split the way the fleet is split (DESIGN.md "The loop"): what a vehicle
//! does ([`sense_aerial`], [`sense_boat`]: measure the truth where it is, with its own noise and
//! its own random stream) and what the model server does ([`Assimilator`]: assemble each
//! step's samples into estimates, fuse, update the model online, allocate the next sensing
//! places). The offline experiment drives both in one process; the Zenoh nodes run the same
//! functions on either side of the network, so the two give the same numbers.

use crate::dmd::{Dmd, DmdConfig, DmdModel};
use crate::fusion::{fuse, AerialFrame, AerialNoise, Estimate, Measured};
use crate::grid::{Cell, Grid};
use crate::kalman::{self, ModalFilter, Observation};
use crate::protocol::Sample;
use crate::sensing::{assign::assign, coverage, gappy, horizon, qr, real_basis};
use crate::team::{Missing, Placement, TeamConfig, TeamError};
use faer::Mat;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A vehicle's own random stream: the same seed and vehicle give the same noise whichever
/// process the vehicle runs in. Aerials are vehicles `0..aerials`, boats follow.
pub fn vehicle_rng(seed: u64, vehicle: usize) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(1 + vehicle as u64);
    rng
}

/// What aerial `me` sees at one step, and what any sensor sees at given cells (the sensor
/// model lives with the fusion that inverts it).
pub use crate::fusion::{aerial_region, sense_aerial, sense_cells};

/// What a boat measures at one step: every cell of its disk, with noise `sigma`.
pub fn sense_boat(
    grid: &Grid,
    truth: &[f64],
    step: u64,
    position: (f64, f64),
    cells: &[usize],
    sigma: f64,
    rng: &mut ChaCha8Rng,
) -> Result<Sample, crate::fusion::FusionError> {
    sense_cells(
        grid,
        truth,
        step,
        position,
        cells,
        crate::protocol::Noise {
            sigma0: sigma,
            growth_per_m: 0.0,
        },
        rng,
    )
}

/// A boat's disk: the cells it covers and its centre `(row, col)`.
pub type BoatDisk = (Vec<usize>, (usize, usize));

/// Where every vehicle should be for the next epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct Allocation {
    /// Per boat (in vehicle order): the disk's cells and centre, or `None` when there are more
    /// boats than disks.
    pub boats: Vec<Option<BoatDisk>>,
    /// Per aerial: its coverage position (metres).
    pub aerials: Vec<(f64, f64)>,
    /// Vehicles (by index: aerials, then boats) left out: on operator hold or without an
    /// autopilot. They sense nothing; the others share the work.
    pub held: std::collections::BTreeSet<usize>,
}

impl Allocation {
    /// The aerials that take part, and their positions.
    pub fn active_aerials(&self) -> (Vec<usize>, Vec<(f64, f64)>) {
        (0..self.aerials.len())
            .filter(|a| !self.held.contains(a))
            .map(|a| (a, self.aerials[a]))
            .unzip()
    }
}

/// One step of the aerials: the estimate on the fine grid (the coarse frame upsampled, for
/// the heuristic schemes and the aerial-only team) and what they saw this step, the lattice
/// cells with each value's own noise variance (what the Kalman filter observes: those errors
/// are independent, the upsampled field's are not).
#[derive(Debug, Clone)]
pub struct AerialSight {
    pub estimate: Estimate,
    /// The interpolation's own error variance per fine cell (from the frame's curvature).
    pub interpolation: Vec<f64>,
    pub cells: Vec<usize>,
    pub values: Vec<f64>,
    pub variance: Vec<f64>,
}

/// The model server's state: the model, the snapshots it was built from, and the calibrated
/// error of each source. A clone is independent (an offline experiment can try an epoch on
/// it and keep the original).
#[derive(Clone)]
pub struct Assimilator {
    cfg: TeamConfig,
    grid: Grid,
    dmd: DmdConfig,
    model: Option<Box<dyn Dmd>>,
    snapshots: Vec<Vec<f64>>,
    /// The model fitted to its newest snapshot, and a real basis of its modes.
    fitted: Option<(DmdModel, Mat<f64>)>,
    held_aerial: Option<Estimate>,
    held_interpolation: Vec<f64>,
    pred_var: f64,
    aerial_extra: f64,
    /// `fusion = "kalman"`: the variance (cells^2 per axis) of a displacement of the field's
    /// features the filter does not model, read from the boats' innovations
    /// ([`kalman::displacement_variance`]); horizon placement counts what a value removes of it.
    displacement: f64,
    placement_rng: ChaCha8Rng,
    boat_positions: Vec<(f64, f64)>,
    aerial_positions: Vec<(f64, f64)>,
    /// `fusion = "kalman"`: the modal filter, and how many steps past the newest snapshot its
    /// state is.
    filter: Option<(ModalFilter, u64)>,
    /// How far a boat goes in one step (m; infinite offline), for `placement = "horizon"`.
    boat_speed: f64,
    /// Cells outside the site's fence (empty: no fence): never in a disk, never an aerial place.
    excluded: Vec<bool>,
    /// The aerials' lattice cells, and the cells between them (which only the boats see).
    lattice: Vec<usize>,
    between_lattice: Vec<usize>,
}

/// The Assimilator's state between two epochs, without its snapshots (they are only appended
/// to: a checkpoint keeps how many there were) nor the fitted model (recomputed from the model
/// and the newest snapshot, bit for bit).
#[derive(Clone)]
pub struct AssimilatorCheckpoint {
    model: Option<Box<dyn Dmd>>,
    snapshots: usize,
    held_aerial: Option<Estimate>,
    held_interpolation: Vec<f64>,
    pred_var: f64,
    aerial_extra: f64,
    displacement: f64,
    placement_rng: ChaCha8Rng,
    boat_positions: Vec<(f64, f64)>,
    aerial_positions: Vec<(f64, f64)>,
    filter: Option<(ModalFilter, u64)>,
}

impl Assimilator {
    /// Its state now, to come back to with [`Self::rewind`].
    pub fn checkpoint(&self) -> AssimilatorCheckpoint {
        AssimilatorCheckpoint {
            model: self.model.clone(),
            snapshots: self.snapshots.len(),
            held_aerial: self.held_aerial.clone(),
            held_interpolation: self.held_interpolation.clone(),
            pred_var: self.pred_var,
            aerial_extra: self.aerial_extra,
            displacement: self.displacement,
            placement_rng: self.placement_rng.clone(),
            boat_positions: self.boat_positions.clone(),
            aerial_positions: self.aerial_positions.clone(),
            filter: self.filter.clone(),
        }
    }

    /// Back to a checkpoint taken earlier on this same Assimilator.
    pub fn rewind(&mut self, c: &AssimilatorCheckpoint) -> Result<(), TeamError> {
        self.model = c.model.clone();
        self.snapshots.truncate(c.snapshots);
        self.held_aerial = c.held_aerial.clone();
        self.held_interpolation = c.held_interpolation.clone();
        (self.pred_var, self.aerial_extra, self.displacement) = (c.pred_var, c.aerial_extra, c.displacement);
        self.placement_rng = c.placement_rng.clone();
        self.boat_positions = c.boat_positions.clone();
        self.aerial_positions = c.aerial_positions.clone();
        self.filter = c.filter.clone();
        self.fitted = None;
        if self.model.is_some() {
            self.refit()?;
        }
        Ok(())
    }

    pub fn new(cfg: &TeamConfig, grid: Grid, frames: usize) -> Result<Self, TeamError> {
        cfg.validate(&grid, frames)?;
        let rank = cfg.rank;
        let mut placement_rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let boat_positions = (0..cfg.boats)
            .map(|_| {
                (
                    placement_rng.random_range(0.0..grid.width_m()),
                    placement_rng.random_range(0.0..grid.height_m()),
                )
            })
            .collect();
        let excluded = cfg.fence.as_ref().map_or_else(Vec::new, |f| f.excluded(&grid));
        let formation = coverage::uniform_formation(&grid, cfg.aerials)?.positions;
        let aerial_positions = coverage::snap_inside(&grid, &excluded, &formation)
            .ok_or_else(|| TeamError::Config("the site's boundary leaves no cell of the grid inside it".into()))?;
        let lattice = grid.strided(cfg.aerial_stride)?;
        let mut on_lattice = vec![false; grid.len()];
        (0..lattice.rows * lattice.cols).for_each(|k| on_lattice[grid.index(lattice.fine_cell(k))] = true);
        Ok(Self {
            dmd: DmdConfig {
                method: cfg.method,
                rank,
                debias: Default::default(),
                gamma: cfg.gamma,
                forgetting: Default::default(),
            },
            cfg: cfg.clone(),
            grid,
            model: None,
            snapshots: vec![],
            fitted: None,
            held_aerial: None,
            held_interpolation: vec![0.0; grid.len()],
            pred_var: 1.0,
            aerial_extra: 0.0,
            displacement: 0.0,
            placement_rng,
            boat_positions,
            aerial_positions,
            excluded,
            lattice: (0..grid.len()).filter(|&i| on_lattice[i]).collect(),
            between_lattice: (0..grid.len()).filter(|&i| !on_lattice[i]).collect(),
            filter: None,
            boat_speed: f64::INFINITY,
        })
    }

    /// Boats go at most `speed` metres per step: `placement = "horizon"` plans only disks
    /// they can reach by their sampling step.
    pub fn set_boat_speed(&mut self, speed: f64) {
        self.boat_speed = speed;
    }

    /// Where boat `slot` will be (an experiment that places the boats itself says so).
    pub fn set_boat_position(&mut self, slot: usize, position: (f64, f64)) {
        if let Some(p) = self.boat_positions.get_mut(slot) {
            *p = position;
        }
    }

    pub fn boat_speed(&self) -> f64 {
        self.boat_speed
    }

    /// The calibrated variance of the model's prediction (per cell).
    pub fn prediction_variance(&self) -> f64 {
        self.pred_var
    }

    /// The variance per cell of the forecast `h` steps after the newest snapshot: the Kalman
    /// filter's, or the calibrated prediction variance for the other schemes.
    pub fn forecast_variance(&self, h: u64) -> Vec<f64> {
        match &self.filter {
            Some((f, at)) => f.forecast(h.saturating_sub(*at) as usize).1,
            None => vec![self.pred_var; self.grid.len()],
        }
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    pub fn aerial_noise(&self) -> AerialNoise {
        AerialNoise {
            sigma0: self.cfg.aerial_sigma0,
            growth_per_m: self.cfg.aerial_growth_per_cell,
        }
    }

    /// The aerials' current positions (what they should fly to).
    pub fn aerial_positions(&self) -> &[(f64, f64)] {
        &self.aerial_positions
    }

    pub fn boat_positions(&self) -> &[(f64, f64)] {
        &self.boat_positions
    }

    /// The model's rank (0 before the first fit).
    pub fn rank(&self) -> usize {
        self.model.as_ref().map_or(0, |m| m.rank())
    }

    /// The aerial estimate of a step from the aerials' samples (any order): the coarse frame
    /// reassembled, each value with its sampling aerial's noise at that distance, upsampled
    /// with its variance. A step without aerial samples holds the previous estimate.
    pub fn aerial_estimate(&mut self, samples: &[Sample]) -> Result<AerialSight, TeamError> {
        if samples.is_empty() {
            let estimate = self
                .held_aerial
                .clone()
                .ok_or(TeamError::NotReady(Missing::AerialData))?;
            return Ok(AerialSight {
                estimate,
                interpolation: self.held_interpolation.clone(),
                cells: vec![],
                values: vec![],
                variance: vec![],
            });
        }
        let mut frame = AerialFrame::assemble(&self.grid, self.cfg.aerial_stride, samples, self.aerial_noise())?;
        let seen: Vec<usize> = (0..frame.seen.len()).filter(|&k| frame.seen[k]).collect();
        let cells = seen
            .iter()
            .map(|&k| self.grid.index(frame.lattice.fine_cell(k)))
            .collect();
        let values = seen.iter().map(|&k| frame.values[k]).collect();
        let variance = seen.iter().map(|&k| frame.variance[k].max(1e-12)).collect();
        if frame.seen.iter().any(|s| !s) {
            // A lattice cell nobody saw this step: take the held estimate there.
            let held = self
                .held_aerial
                .as_ref()
                .ok_or(TeamError::NotReady(Missing::EarlierFrame))?;
            for k in (0..frame.seen.len()).filter(|&k| !frame.seen[k]) {
                let i = self.grid.index(frame.lattice.fine_cell(k));
                frame.values[k] = held.values[i];
                frame.variance[k] = held.variance[i];
            }
        }
        let estimate = frame.upsample()?;
        let interpolation = frame.interpolation_variance()?;
        self.held_aerial = Some(estimate.clone());
        self.held_interpolation = interpolation.clone();
        Ok(AerialSight {
            estimate,
            interpolation,
            cells,
            values,
            variance,
        })
    }

    /// The first model, from the initialisation's aerial estimates (one per step).
    pub fn initialise(&mut self, estimates: Vec<Vec<f64>>) -> Result<(), TeamError> {
        if estimates.len() < 3 {
            return Err(TeamError::NotReady(Missing::Snapshots { have: estimates.len() }));
        }
        let z = to_mat(&estimates);
        let m = estimates.len() - 1;
        self.model = Some(self.dmd.init(z.subcols(0, m), z.subcols(1, m))?);
        self.pred_var = self
            .held_aerial
            .as_ref()
            .map_or(1.0, |a| a.variance.iter().sum::<f64>() / self.grid.len() as f64)
            .max(1e-12);
        self.snapshots = estimates;
        self.refit()?;
        self.move_filter()
    }

    /// `fusion = "kalman"`: carry the filter into the refitted model's basis and dynamics (or
    /// start it, at the newest snapshot, with the calibrated prediction variance per cell).
    /// Its state is then at the newest snapshot: the fused one of the last step, which is the
    /// filter's own posterior mean.
    fn move_filter(&mut self) -> Result<(), TeamError> {
        if self.cfg.fusion != crate::fusion::Scheme::Kalman {
            return Ok(());
        }
        let (pred, basis) = self.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let dynamics = kalman::modal_dynamics(pred.modes.modes.as_ref(), &pred.modes.eigenvalues, basis.as_ref())?;
        match self.filter.take() {
            Some((mut f, _)) => {
                f.reproject(basis.clone(), dynamics)?;
                self.filter = Some((f, 0));
            }
            None => {
                let newest = self.snapshots.last().expect("snapshots after init");
                let mean: Vec<f64> = (0..basis.ncols())
                    .map(|j| basis.col(j).iter().zip(newest).map(|(b, x)| b * x).sum())
                    .collect();
                // The start: the modal state as uncertain as the prediction is per cell; the
                // process noise a hundredth of it per step and the model error the
                // prediction's variance, both re-estimated from the boats' innovations.
                let q = basis.ncols();
                let cov = Mat::from_fn(q, q, |i, j| if i == j { self.pred_var } else { 0.0 });
                self.filter = Some((
                    ModalFilter::new(basis.clone(), dynamics, mean, cov, 0.01 * self.pred_var, self.pred_var)?,
                    0,
                ));
            }
        }
        Ok(())
    }

    /// `fusion = "kalman"`: one step of the filter. The modes see the lattice cells the
    /// aerials saw this step (each with its noise at that distance) and the boats' disks (their
    /// noise); the detail (what the modes cannot hold) then sees the residuals. Before the
    /// update, the detail's forecast variance is checked against both sources' innovations
    /// and rescaled (adaptive inflation, damped and capped). The process noise and the model
    /// error are re-estimated at boat steps from the boats' innovations (their expected square
    /// is `h P h' + detail variance + boat noise`), smoothed, and clamped to the field's
    /// variance: they cannot run away.
    fn filter_step(
        &mut self,
        ahead: u64,
        aerial: &AerialSight,
        cells: &[usize],
        vals: &[f64],
    ) -> Result<Estimate, TeamError> {
        let boat_var = (self.cfg.boat_sigma * self.cfg.boat_sigma).max(1e-12);
        let aerial_extra = self.aerial_extra;
        let between_lattice = &self.between_lattice;
        let grid = self.grid;
        let displacement = &mut self.displacement;
        let Some((f, at)) = self.filter.as_mut() else {
            return Err(TeamError::NotReady(Missing::Model));
        };
        while *at < ahead {
            f.predict();
            *at += 1;
        }
        let boat_vars = vec![boat_var; cells.len()];
        // Boat innovations against the forecast, for the noise estimates.
        let (prior_mean, prior_var) = f.field();
        let prior_detail_var = f.detail_var.clone();
        let boats = Observation {
            cells,
            values: vals,
            variance: &boat_vars,
        };
        let lattice = Observation {
            cells: &aerial.cells,
            values: &aerial.values,
            variance: &aerial.variance,
        };
        if !aerial.cells.is_empty() {
            f.learn_persistence(&lattice, 1.0)?;
        }
        // The detail's forecast variance checked against what each source saw and rescaled
        // before the update, never grown past the field's own variance: every cell by the aerials'
        // check (every step, evenly spread: the detail's refresh and persistence are the same
        // everywhere), then the cells between the lattice by the boats' (at boat steps): the
        // interpolation's misfit there is seen only by them.
        let cap = variance_of(&aerial.estimate.values);
        if let Some(fit) = f.detail_fit(&lattice)? {
            f.rescale_detail(fit, cap, 0..f.detail_var.len());
        }
        if let Some(fit) = f.detail_fit(&boats)? {
            f.rescale_detail(fit, cap, between_lattice.iter().copied());
        }
        f.update(&[lattice, boats])?;
        // The detail: the aerial estimate at every cell (noise, interpolation and the
        // calibrated extra), then the boats.
        let all: Vec<usize> = (0..aerial.estimate.values.len()).collect();
        let aerial_var = aerial_detail_variance(&aerial.estimate.variance, &aerial.interpolation, aerial_extra);
        f.update_detail(&[
            Observation {
                cells: &all,
                values: &aerial.estimate.values,
                variance: &aerial_var,
            },
            boats,
        ])?;
        // The boats' innovations against the forecast: their expected square is the forecast's
        // variance there plus the boats' noise.
        if !cells.is_empty() {
            let mean_at = |v: &[f64]| cells.iter().map(|&c| v[c]).sum::<f64>() / cells.len() as f64;
            let field_var = variance_of(vals).max(1e-12);
            let d2 = cells
                .iter()
                .zip(vals)
                .map(|(&c, v)| (v - prior_mean[c]).powi(2))
                .sum::<f64>()
                / cells.len() as f64;
            let (detail_part, expected) = (mean_at(&prior_detail_var).max(1e-12), mean_at(&prior_var) + boat_var);
            let modal_part = expected - boat_var - detail_part;
            let s_hat = (f.model_error * (d2 - modal_part - boat_var) / detail_part).clamp(0.0, field_var);
            f.model_error = (0.7 * f.model_error + 0.3 * s_hat).clamp(1e-12, field_var);
            let nis = (d2 / expected).clamp(0.25, 4.0);
            f.process = (f.process * nis.sqrt()).clamp(1e-12, field_var);
            // The displacement the filter does not model, from the same innovations against
            // the forecast's squared gradient; smoothed as the model error is, and never more
            // than the grid's own extent (it cannot run away).
            let grad2 = grid.squared_gradient(&prior_mean)?;
            let innovation2: Vec<f64> = cells
                .iter()
                .zip(vals)
                .map(|(&c, v)| (v - prior_mean[c]).powi(2))
                .collect();
            let expected: Vec<f64> = cells.iter().map(|&c| prior_var[c] + boat_var).collect();
            let at: Vec<f64> = cells.iter().map(|&c| grad2[c]).collect();
            if let Some(s2) = kalman::displacement_variance(&innovation2, &expected, &at) {
                let extent = (grid.rows * grid.rows + grid.cols * grid.cols) as f64;
                *displacement = (0.7 * *displacement + 0.3 * s2).min(extent);
            }
        }
        let (values, variance) = f.field();
        Ok(Estimate { values, variance })
    }

    fn refit(&mut self) -> Result<(), TeamError> {
        let model = self.model.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let newest = self.snapshots.last().expect("snapshots after init");
        self.fitted = Some(fit_to(model.as_ref(), newest)?);
        Ok(())
    }

    /// The model fitted to the newest snapshot (forecasts count from it).
    pub fn model(&self) -> Option<&DmdModel> {
        self.fitted.as_ref().map(|f| &f.0)
    }

    /// Next epoch's places: block QR (or the configured alternative) on the model's modes,
    /// boats assigned by least total travel, aerials by Lloyd under the temporal density.
    pub fn allocate(&mut self) -> Result<Allocation, TeamError> {
        self.allocate_without(&Default::default())
    }

    /// [`Self::allocate`] with some vehicles (indices: aerials, then boats) left out: the
    /// disks go to the other boats (as many disks as boats free), Lloyd places the other
    /// aerials, and the held keep their places.
    pub fn allocate_without(&mut self, held: &std::collections::BTreeSet<usize>) -> Result<Allocation, TeamError> {
        let (pred, basis) = self.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let (cfg, grid) = (&self.cfg, &self.grid);
        let roster = crate::roster::Roster::of(cfg);
        let free: Vec<usize> = (0..cfg.boats)
            .filter(|&b| !held.contains(&roster.boat_index(b)))
            .collect();
        let mut boats = vec![None; cfg.boats];
        // `placement = "horizon"`: the filter's forecast at the next sampling step, and its
        // uncertainty there and over the horizon with the aerials observing as in their last
        // frame (each lattice value with its noise, the estimate everywhere with the
        // interpolation's error and the calibrated extra, as `filter_step` weighs them).
        let boat_var = (cfg.boat_sigma * cfg.boat_sigma).max(1e-12);
        let forecast = match (cfg.placement, &self.filter, &self.held_aerial) {
            (Placement::Horizon, Some((f, at)), Some(held)) => {
                let to = (cfg.boat_period as u64).saturating_sub(*at).max(1) as usize;
                let variance: Vec<f64> = self.lattice.iter().map(|&c| held.variance[c].max(1e-12)).collect();
                let everywhere = aerial_detail_variance(&held.variance, &self.held_interpolation, self.aerial_extra);
                let aerials = kalman::Scheduled {
                    cells: &self.lattice,
                    variance: &variance,
                    everywhere: &everywhere,
                };
                let g = f.ahead(to);
                let (mean, var) = g.field();
                Some((
                    g,
                    f.look_ahead(to, cfg.horizon_epochs * cfg.boat_period, &aerials, boat_var)?,
                    mean,
                    var,
                ))
            }
            (Placement::Horizon, _, _) => return Err(TeamError::NotReady(Missing::Model)),
            _ => None,
        };
        if let Some((g, ahead, mean, _)) = &forecast {
            let reach = self.boat_speed * cfg.boat_period as f64;
            let fleet: Vec<horizon::Boat> = free
                .iter()
                .map(|&b| horizon::Boat {
                    position: self.boat_positions[b],
                    reach_m: reach,
                })
                .collect();
            // What the filter does not model at the sampling step: the forecast's features
            // displaced, of variance s2 |grad x|^2 per cell.
            let unmodelled: Vec<f64> = grid
                .squared_gradient(mean)?
                .iter()
                .map(|g2| self.displacement * g2)
                .collect();
            let f = horizon::Forecast::of(g.basis(), ahead).with_unmodelled(&unmodelled);
            for c in horizon::plan_within(grid, &f, &fleet, cfg.radius, boat_var, &self.excluded)? {
                let b = free[c.boat];
                self.boat_positions[b] = grid.centre_m(c.centre);
                boats[b] = Some((c.cells, (c.centre.row, c.centre.col)));
            }
        } else {
            let disks: Vec<Vec<usize>> = match (free.len(), cfg.placement) {
                (0, _) => vec![],
                (k, Placement::Qr) => qr::block_qr_within(basis.as_ref(), grid, k, cfg.radius, &self.excluded)?
                    .into_iter()
                    .map(|d| d.cells)
                    .collect(),
                (k, Placement::DOptimal) => qr::block_dopt_within(basis.as_ref(), grid, k, cfg.radius, &self.excluded)?
                    .into_iter()
                    .map(|d| d.cells)
                    .collect(),
                (k, Placement::Random) => random_disks(grid, k, cfg.radius, &self.excluded, &mut self.placement_rng),
                (_, Placement::Horizon) => return Err(TeamError::NotReady(Missing::Model)),
            };
            let centres: Vec<(usize, usize)> = disks
                .iter()
                .map(|d| {
                    let (r, c) = d.iter().fold((0.0, 0.0), |(r, c), &i| {
                        (r + grid.cell(i).row as f64, c + grid.cell(i).col as f64)
                    });
                    (
                        (r / d.len() as f64).round() as usize,
                        (c / d.len() as f64).round() as usize,
                    )
                })
                .collect();
            let targets: Vec<(f64, f64)> = centres.iter().map(|&(r, c)| grid.centre_m(Cell::new(r, c))).collect();
            let starts: Vec<(f64, f64)> = free.iter().map(|&b| self.boat_positions[b]).collect();
            let (assignment, _) = if free.is_empty() {
                (vec![], 0.0)
            } else {
                assign(&starts, &targets, 1.0)?
            };
            for (&b, a) in free.iter().zip(&assignment) {
                if let Some(t) = a {
                    boats[b] = Some((disks[*t].clone(), centres[*t]));
                    self.boat_positions[b] = targets[*t];
                }
            }
        }
        // Aerials: Lloyd under the temporal density, or (horizon) under the forecast's
        // variance, floored.
        let density = match &forecast {
            Some((_, _, _, var)) => {
                let top = var.iter().cloned().fold(0.0, f64::max).max(1e-300);
                var.iter()
                    .map(|v| cfg.density_floor + (1.0 - cfg.density_floor) * v / top)
                    .collect()
            }
            None => coverage::temporal_density(pred, cfg.density_floor)?,
        };
        // Outside the fence there is nothing to cover.
        let density: Vec<f64> = density
            .iter()
            .enumerate()
            .map(|(i, &d)| {
                if self.excluded.get(i).copied().unwrap_or(false) {
                    0.0
                } else {
                    d
                }
            })
            .collect();
        let flying: Vec<usize> = (0..cfg.aerials).filter(|a| !held.contains(a)).collect();
        if !flying.is_empty() {
            let starts: Vec<(f64, f64)> = flying.iter().map(|&a| self.aerial_positions[a]).collect();
            let placed = coverage::lloyd(grid, &density, &starts, 50, 1e-3)?.positions;
            let placed = coverage::snap_inside(grid, &self.excluded, &placed)
                .expect("checked at construction: some cell is inside");
            for (&a, p) in flying.iter().zip(placed) {
                self.aerial_positions[a] = p;
            }
        }
        Ok(Allocation {
            boats,
            aerials: self.aerial_positions.clone(),
            held: held.clone(),
        })
    }

    /// Fuse one step `ahead` steps after the model's newest snapshot: the aerial estimate with
    /// the boats' gappy estimate (when `boats` has samples) or the model's prediction. Boat
    /// steps also re-calibrate each source against the boats' measurements.
    pub fn fuse_step(&mut self, ahead: u64, sight: &AerialSight, boats: &[Sample]) -> Result<Estimate, TeamError> {
        let n = self.grid.len();
        let boat_var = self.cfg.boat_sigma * self.cfg.boat_sigma;
        let (pred, basis) = self.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let predicted = pred.predict(ahead as f64);
        let mut aerial = sight.estimate.clone();
        // A canonical order (disks do not overlap, so first cells differ): the result does not
        // depend on the order the boats' samples arrived in.
        let mut boats: Vec<&Sample> = boats.iter().collect();
        boats.sort_by_key(|s| (s.cells.first().copied(), s.cells.len()));
        let cells: Vec<usize> = boats.iter().flat_map(|s| s.cells.iter().map(|&c| c as usize)).collect();
        let vals: Vec<f64> = boats.iter().flat_map(|s| s.values.iter().copied()).collect();
        let hifi = if !cells.is_empty() {
            // Innovations at the measured cells, less the boats' own noise: the aerials' error
            // is mostly interpolation and the prediction's mostly model error, and neither is
            // in their noise models.
            let innovation = |est: &[f64]| -> f64 {
                let m = cells.iter().zip(&vals).map(|(&c, v)| (est[c] - v).powi(2)).sum::<f64>() / cells.len() as f64;
                (m - boat_var).max(1e-12)
            };
            // (The Kalman filter models the interpolation's error itself: the extra is what
            // is left beyond it.)
            let modelled = |c: usize| {
                aerial.variance[c]
                    + if self.cfg.fusion == crate::fusion::Scheme::Kalman {
                        sight.interpolation[c]
                    } else {
                        0.0
                    }
            };
            let noise_part = cells.iter().map(|&c| modelled(c)).sum::<f64>() / cells.len() as f64;
            self.aerial_extra = (innovation(&aerial.values) - noise_part).max(0.0);
            self.pred_var = innovation(&predicted);
            match gappy::reconstruct(basis.as_ref(), &cells, &vals, boat_var) {
                Ok(g) => {
                    // Truncation error: the fit's residual at the measured cells, inflated for
                    // the degrees of freedom the fit used.
                    let dof = (cells.len() as f64 - basis.ncols() as f64).max(1.0);
                    let resid = cells
                        .iter()
                        .zip(&vals)
                        .map(|(&c, v)| (g.field[c] - v).powi(2))
                        .sum::<f64>()
                        / dof;
                    let extra = (resid - boat_var).max(0.0);
                    Estimate {
                        values: g.field,
                        variance: g.variance.iter().map(|v| v + extra).collect(),
                    }
                }
                // Too few independent cells for the modes: keep the prediction.
                Err(crate::sensing::SensingError::Underdetermined { .. }) => Estimate {
                    values: predicted,
                    variance: vec![self.pred_var; n],
                },
                Err(e) => return Err(e.into()),
            }
        } else {
            Estimate {
                values: predicted,
                variance: vec![self.pred_var; n],
            }
        };
        if self.cfg.fusion == crate::fusion::Scheme::Kalman {
            return self.filter_step(ahead, sight, &cells, &vals);
        }
        aerial.variance.iter_mut().for_each(|v| *v += self.aerial_extra);
        let measured = (!cells.is_empty()).then_some(Measured {
            cells: &cells,
            values: &vals,
            noise_var: boat_var,
        });
        Ok(fuse(self.cfg.fusion, n, &[&aerial, &hifi], measured)?)
    }

    /// Fold an epoch's fused snapshots into the model (pairs chained from the newest one) and
    /// refit.
    pub fn assimilate(&mut self, epoch: Vec<Vec<f64>>) -> Result<(), TeamError> {
        if epoch.is_empty() {
            return Ok(());
        }
        let mut chain = vec![self.snapshots.last().expect("snapshots after init").clone()];
        chain.extend(epoch.iter().cloned());
        let z = to_mat(&chain);
        let m = chain.len() - 1;
        self.model
            .as_mut()
            .ok_or(TeamError::NotReady(Missing::Model))?
            .update(z.subcols(0, m), z.subcols(1, m))?;
        self.snapshots.extend(epoch);
        self.refit()?;
        self.move_filter()
    }
}

/// A model fitted to its newest snapshot (forecasts count from it), and an orthonormal real
/// basis of its modes (for gappy reconstruction and placement).
pub fn fit_to(model: &dyn Dmd, newest: &[f64]) -> Result<(DmdModel, Mat<f64>), TeamError> {
    let modes = model.decompose()?;
    let basis = real_basis(modes.modes.as_ref())?;
    Ok((modes.model(newest, 1.0)?, basis))
}

/// Columns to a matrix.
pub fn to_mat(cols: &[Vec<f64>]) -> Mat<f64> {
    let n = cols.first().map_or(0, |c| c.len());
    Mat::from_fn(n, cols.len(), |i, j| cols[j][i])
}

/// The variance of a set of values (0 for none).
/// The aerial estimate's error variance per cell as the filter's detail sees it: its noise,
/// the interpolation's error and the calibrated extra (one definition for the update and for
/// the look ahead that plans on it).
fn aerial_detail_variance(noise: &[f64], interpolation: &[f64], extra: f64) -> Vec<f64> {
    noise
        .iter()
        .zip(interpolation)
        .map(|(v, i)| (v + i + extra).max(1e-12))
        .collect()
}

fn variance_of(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64
}

/// `m` random non-overlapping disks (rejection sampling; fewer if the grid is full).
fn random_disks(grid: &Grid, m: usize, radius: f64, excluded: &[bool], rng: &mut ChaCha8Rng) -> Vec<Vec<usize>> {
    let mut taken = if excluded.is_empty() {
        vec![false; grid.len()]
    } else {
        excluded.to_vec()
    };
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::process::synthetic::plume_field;
    use rand::seq::SliceRandom;

    #[test]
    fn arrival_order_does_not_change_the_estimates() {
        let truth = plume_field(24, 48, 30, 0.0, 1);
        let grid = Grid::new(24, 48, 1.0).unwrap();
        let cfg = TeamConfig {
            aerials: 3,
            boats: 4,
            radius: 3.0,
            rank: crate::dmd::RankPolicy::Fixed(6),
            init_steps: 10,
            aerial_stride: 3,
            ..TeamConfig::default()
        };
        let x = |k: usize| -> Vec<f64> { truth.snapshots.col(k).iter().copied().collect() };
        let run = |shuffle: bool| -> (Vec<f64>, Vec<f64>) {
            let mut server = Assimilator::new(&cfg, grid, 30).unwrap();
            let mut rngs: Vec<ChaCha8Rng> = (0..7).map(|v| vehicle_rng(cfg.seed, v)).collect();
            let mut order = ChaCha8Rng::seed_from_u64(99);
            let mut init = vec![];
            for k in 0..10 {
                let pos = server.aerial_positions().to_vec();
                let mut s: Vec<Sample> = (0..3)
                    .map(|a| {
                        sense_aerial(&grid, &x(k), k as u64, 3, &pos, a, server.aerial_noise(), &mut rngs[a]).unwrap()
                    })
                    .collect();
                if shuffle {
                    s.shuffle(&mut order);
                }
                init.push(server.aerial_estimate(&s).unwrap().estimate.values);
            }
            server.initialise(init).unwrap();
            let plan = server.allocate().unwrap();
            let mut boats: Vec<Sample> = plan
                .boats
                .iter()
                .enumerate()
                .filter_map(|(b, d)| {
                    d.as_ref()
                        .map(|(c, _)| sense_boat(&grid, &x(10), 10, (0.0, 0.0), c, 0.01, &mut rngs[3 + b]).unwrap())
                })
                .collect();
            if shuffle {
                boats.shuffle(&mut order);
            }
            let aerial = server.aerial_estimate(&[]).unwrap();
            let fused = server.fuse_step(1, &aerial, &boats).unwrap();
            server.assimilate(vec![fused.values.clone()]).unwrap();
            (fused.values, server.model().unwrap().predict(1.0))
        };
        let (a, b) = (run(false), run(true));
        assert_eq!(a.0, b.0, "fused snapshot depends on arrival order");
        assert_eq!(a.1, b.1, "model depends on arrival order");
    }

    #[test]
    fn each_aerial_senses_its_own_region_once() {
        let grid = Grid::new(12, 24, 1.0).unwrap();
        let truth = vec![1.0; grid.len()];
        let aerials = [(6.0, 6.0), (18.0, 6.0)];
        let noise = AerialNoise {
            sigma0: 0.0,
            growth_per_m: 0.0,
        };
        let mut rng = vehicle_rng(1, 0);
        let a = sense_aerial(&grid, &truth, 0, 3, &aerials, 0, noise, &mut rng).unwrap();
        let b = sense_aerial(&grid, &truth, 0, 3, &aerials, 1, noise, &mut rng).unwrap();
        let mut all: Vec<u32> = a.cells.iter().chain(&b.cells).copied().collect();
        all.sort();
        all.dedup();
        assert_eq!(all.len(), 4 * 8, "every lattice cell exactly once");
        assert_eq!(a.cells.len(), b.cells.len());
        assert!(a.values.iter().all(|&v| v == 1.0));
    }
}
