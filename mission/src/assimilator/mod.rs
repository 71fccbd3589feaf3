//! The model server's side of the fleet's loop (DESIGN.md "The loop"): assemble each step's
//! samples into estimates, fuse, update the model online, allocate the next sensing places.
//! The vehicles' side (sensing the truth where they are, with their own noise and random
//! streams) is [`crate::vehicle`]. The offline experiment drives both in one process; the
//! Zenoh nodes run the same functions on either side of the network, so the two give the
//! same numbers.
//!
//! The [`Assimilator`] is its configuration ([`Setup`]: fixed when the mission starts) and its
//! state ([`AssimilatorState`]: a value, `Clone`); a checkpoint is a copy of the state.
//! [`fuse`] holds the per-step estimates and the filter's step, [`placement`] the allocation.

mod between;
mod fuse;
mod placement;
mod screening;

pub use fuse::AerialSight;
pub use placement::{Allocation, BoatDisk};

use crate::team::{Missing, TeamConfig, TeamError};
use faer::Mat;
use fleet_math::dmd::{Dmd, DmdConfig, DmdModel, Factored, Modes, Prepared};
use fleet_math::fusion::{AerialNoise, Estimate, Scheme};
use fleet_math::grid::Grid;
use fleet_math::kalman::{self, ModalFilter};
use fleet_math::sensing::{coverage, real_basis, real_basis_coordinates};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

/// What the mission fixes when it starts: the team, the grid, the DMD method, the fence's
/// mask, the aerial lattice and how fast boats go.
#[derive(Clone)]
pub struct Setup {
    cfg: TeamConfig,
    grid: Grid,
    dmd: DmdConfig,
    /// Cells outside the site's fence or on land (empty: neither): never an aerial place.
    excluded: Vec<bool>,
    /// Cells outside the fence (no disk touches one) and on land (no disk is centred on one,
    /// and a disk holds only its wet cells): [`fleet_math::sensing::Room`]. Empty: none.
    outside: Vec<bool>,
    dry: Vec<bool>,
    /// The cells with no data (`TeamConfig::land`): zero in every snapshot the model learns
    /// from, so they are zero rows of its snapshot matrices (the DMD of the other cells).
    land: Vec<usize>,
    /// The aerials' lattice cells, and which cells are on it (the others only the boats see).
    lattice: Vec<usize>,
    on_lattice: Vec<bool>,
    /// How far a boat goes in one step (m; infinite offline), for `placement = "horizon"`.
    boat_speed: f64,
    /// How each step is fused: `fusion` read once, here.
    fuser: Fuser,
}

/// How the assimilator fuses a step, chosen once from the team's `fusion` when it is made:
/// every place the two ways differ matches on this, never on the setting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fuser {
    /// `kalman`: the modal filter observes the aerial lattice and the boats' disks and
    /// forecasts by itself; it is carried into each refitted model's basis.
    Filter,
    /// `paper` or `inverse-variance`: the aerial estimate blended with the boats' gappy
    /// estimate on the model's modes (or the model's prediction without boat data).
    Blend(Scheme),
}

impl Fuser {
    /// The fuser a `fusion` setting names.
    pub fn of(scheme: Scheme) -> Self {
        match scheme {
            Scheme::Kalman => Self::Filter,
            blend => Self::Blend(blend),
        }
    }
}

/// Everything the assimilator learns as the mission goes: the model, the newest snapshot, the
/// calibrated error of each source, the filter, where the vehicles were sent. A value: a
/// checkpoint is a copy, and a rewind puts the copy back.
#[derive(Clone)]
pub struct AssimilatorState {
    model: Option<Box<dyn Dmd>>,
    /// The newest fused snapshot (the model's forecasts count from it).
    newest: Option<Vec<f64>>,
    /// The model fitted to its newest snapshot, and a real basis of its modes.
    fitted: Option<(Arc<DmdModel>, Arc<Mat<f64>>)>,
    /// `fitted`'s dynamics in its basis when the refit could make them in r x r
    /// ([`fit_with_dynamics`]; else the filter makes them from the modes).
    dynamics: Option<Mat<f64>>,
    held_aerial: Option<Estimate>,
    held_interpolation: Vec<f64>,
    pred_var: f64,
    /// The aerials' error beyond their noise (and, with the filter, beyond the interpolation's
    /// modelled error), pooled over the boat epochs: its `mean()` is the extra they are given.
    aerial_extra: fuse::Pooled,
    /// `fusion = "kalman"`: what the boats showed of the filter between the lattice.
    between: between::Between,
    /// `fusion = "kalman"`: the forecast's skill against the lattice at each step since the
    /// last [`Assimilator::take_skill`].
    forecast_skill: Vec<f64>,
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
    /// The boats' innovations against the forecast at the last step that had boat values
    /// (taken by [`Assimilator::take_innovation`]).
    innovation: Option<kalman::Innovation>,
    /// Every sensor's tests and verdict ([`crate::health`]).
    screen: crate::health::Screen,
    /// The field's mean level over the initialisation (one number on every wet cell, 0 on
    /// land): the model and the filter learn the field's anomalies about it, so a field plus a
    /// constant, or in other units, is the same problem to them, to rounding (a constant
    /// learned as a mode cost a synthetic field plus 280 +22%). One number, not a mean per
    /// cell: per cell it also took out the field's initial shape, and the default mission's
    /// map was 17% worse (3 seeds). `None` before the first model.
    mean: Option<Arc<Vec<f64>>>,
}

/// The assimilator's state between two epochs, to come back to.
pub type AssimilatorCheckpoint = AssimilatorState;

impl Setup {
    /// The aerials' noise model (the mission's settings).
    fn aerial_noise(&self) -> AerialNoise {
        AerialNoise {
            sigma0: self.cfg.aerial_sigma0,
            growth_per_m: self.cfg.aerial_growth_per_cell,
        }
    }

    /// `x` with the land cells at zero (a no-op without land).
    fn dry(&self, mut x: Vec<f64>) -> Vec<f64> {
        self.land.iter().for_each(|&c| x[c] = 0.0);
        x
    }

    /// An estimate with the land cells at zero, known exactly (nothing there to estimate).
    fn dry_estimate(&self, mut e: Estimate) -> Estimate {
        e.values = self.dry(e.values);
        self.land.iter().for_each(|&c| e.variance[c] = 0.0);
        e
    }
}

/// The model server's assimilator. A clone is independent (an offline experiment can try an
/// epoch on it and keep the original).
#[derive(Clone)]
pub struct Assimilator {
    /// Shared with the work made on other threads from the settings alone (a step's aerial
    /// sight beside the filter's step): fixed once the mission starts.
    setup: Arc<Setup>,
    state: AssimilatorState,
}

impl Assimilator {
    pub fn new(cfg: &TeamConfig, grid: Grid, frames: usize) -> Result<Self, TeamError> {
        cfg.validate(&grid, frames)?;
        let mut placement_rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let (w, h) = (grid.width_m(), grid.height_m());
        let boat_positions = (0..cfg.boats)
            .map(|_| (placement_rng.random_range(0.0..w), placement_rng.random_range(0.0..h)))
            .collect();
        let outside = cfg.fence.as_ref().map_or_else(Vec::new, |f| f.excluded(&grid));
        let mut dry = vec![];
        if !cfg.land.is_empty() {
            dry.resize(grid.len(), false);
            cfg.land.iter().for_each(|&c| dry[c as usize] = true);
        }
        let excluded = match (outside.is_empty(), dry.is_empty()) {
            (_, true) => outside.clone(),
            (true, false) => dry.clone(),
            (false, false) => outside.iter().zip(&dry).map(|(o, d)| *o || *d).collect(),
        };
        let formation = coverage::uniform_formation(&grid, cfg.aerials)?.positions;
        let aerial_positions = coverage::snap_inside(&grid, &excluded, &formation)
            .ok_or_else(|| TeamError::Config("the site's boundary leaves no cell of the grid inside it".into()))?;
        let lattice = grid.strided(cfg.aerial_stride)?;
        let mut on_lattice = vec![false; grid.len()];
        (0..lattice.rows * lattice.cols).for_each(|k| on_lattice[grid.index(lattice.fine_cell(k))] = true);
        let setup = Setup {
            dmd: DmdConfig {
                method: cfg.method,
                rank: cfg.rank,
                debias: Default::default(),
                gamma: cfg.gamma,
                forgetting: Default::default(),
            },
            cfg: cfg.clone(),
            grid,
            excluded,
            outside,
            dry,
            land: cfg.land.iter().map(|&c| c as usize).collect(),
            lattice: (0..grid.len()).filter(|&i| on_lattice[i]).collect(),
            on_lattice,
            boat_speed: f64::INFINITY,
            fuser: Fuser::of(cfg.fusion),
        };
        let state = AssimilatorState {
            model: None,
            newest: None,
            fitted: None,
            dynamics: None,
            held_aerial: None,
            held_interpolation: vec![0.0; grid.len()],
            pred_var: 1.0,
            aerial_extra: Default::default(),
            between: Default::default(),
            forecast_skill: vec![],
            displacement: 0.0,
            placement_rng,
            boat_positions,
            aerial_positions,
            filter: None,
            innovation: None,
            screen: Default::default(),
            mean: None,
        };
        Ok(Self {
            setup: Arc::new(setup),
            state,
        })
    }

    /// Its state now, to come back to with [`Self::rewind`].
    ///
    /// The fitted model (its modes are N x r complex, 47 MB at 384 x 768 and rank 10) and its
    /// dynamics are left out: they are what [`Self::refit`] makes of the model and the newest
    /// snapshot, so [`Self::rewind`] makes them again, to the bit.
    pub fn checkpoint(&self) -> AssimilatorCheckpoint {
        AssimilatorState {
            fitted: None,
            dynamics: None,
            ..self.state.clone()
        }
    }

    /// Back to a checkpoint taken earlier on this same Assimilator.
    pub fn rewind(&mut self, c: &AssimilatorCheckpoint) -> Result<(), TeamError> {
        self.state = c.clone();
        if self.state.model.is_some() {
            self.refit()?;
        }
        Ok(())
    }

    /// Boats go at most `speed` metres per step: `placement = "horizon"` plans only disks
    /// they can reach by their sampling step.
    pub fn set_boat_speed(&mut self, speed: f64) {
        Arc::make_mut(&mut self.setup).boat_speed = speed;
    }

    /// Where boat `slot` will be (an experiment that places the boats itself says so).
    pub fn set_boat_position(&mut self, slot: usize, position: (f64, f64)) {
        if let Some(p) = self.state.boat_positions.get_mut(slot) {
            *p = position;
        }
    }

    pub fn boat_speed(&self) -> f64 {
        self.setup.boat_speed
    }

    /// The calibrated variance of the model's prediction (per cell).
    pub fn prediction_variance(&self) -> f64 {
        self.state.pred_var
    }

    /// The variance per cell of the forecast `h` steps after the newest snapshot: the Kalman
    /// filter's, or the calibrated prediction variance for the other schemes; computed when
    /// called, on any thread, while the assimilator goes on (the filter is copied: its detail is
    /// a few fields).
    pub fn forecast_variance_later(&self, h: u64) -> impl FnOnce() -> Vec<f64> + Send + use<> {
        let filter = self
            .state
            .filter
            .as_ref()
            .map(|(f, at)| (f.clone(), h.saturating_sub(*at) as usize));
        let (pred_var, n) = (self.state.pred_var, self.setup.grid.len());
        move || match filter {
            Some((f, ahead)) => f.forecast(ahead).1,
            None => vec![pred_var; n],
        }
    }

    /// The cells off the model grid (no data in the truth: land), in order.
    pub fn land(&self) -> &[usize] {
        &self.setup.land
    }

    pub fn grid(&self) -> &Grid {
        &self.setup.grid
    }

    pub fn aerial_noise(&self) -> AerialNoise {
        self.setup.aerial_noise()
    }

    /// The aerials' current positions (what they should fly to).
    pub fn aerial_positions(&self) -> &[(f64, f64)] {
        &self.state.aerial_positions
    }

    pub fn boat_positions(&self) -> &[(f64, f64)] {
        &self.state.boat_positions
    }

    /// The boats' innovations of the last step [`Self::fuse_step`] fused boat values in, once.
    pub fn take_innovation(&mut self) -> Option<kalman::Innovation> {
        self.state.innovation.take()
    }

    /// The model's skill over the steps fused since the last call, as epoch `epoch`'s (`None`
    /// without the filter).
    pub fn take_skill(&mut self, epoch: u64) -> Option<crate::protocol::EpochSkill> {
        let s = &mut self.state;
        let steps = std::mem::take(&mut s.forecast_skill);
        s.filter.as_ref()?;
        Some(crate::protocol::EpochSkill {
            epoch,
            forecast: (!steps.is_empty()).then(|| steps.iter().sum::<f64>() / steps.len() as f64),
            between: s.between.skill,
        })
    }

    pub fn rank(&self) -> usize {
        self.state.model.as_ref().map_or(0, |m| m.rank())
    }

    /// The model fitted to the newest snapshot (forecasts count from it).
    pub fn model(&self) -> Option<&DmdModel> {
        self.state.fitted.as_ref().map(|f| f.0.as_ref())
    }

    /// The same model, shared: to read it on another thread while the assimilator goes on
    /// (the published model is assembled while the placement runs).
    pub fn model_shared(&self) -> Option<Arc<DmdModel>> {
        self.state.fitted.as_ref().map(|f| f.0.clone())
    }

    /// The first model, from the initialisation's aerial estimates (one per step).
    pub fn initialise(&mut self, estimates: Vec<Vec<f64>>) -> Result<(), TeamError> {
        if estimates.len() < 3 {
            return Err(TeamError::NotReady(Missing::Snapshots { have: estimates.len() }));
        }
        let estimates: Vec<Vec<f64>> = estimates.into_iter().map(|e| self.setup.dry(e)).collect();
        self.state.mean = Some(Arc::new(mean_of(&estimates, &self.setup.land)));
        let estimates: Vec<Vec<f64>> = estimates.into_iter().map(|e| self.less_mean(e)).collect();
        let z = to_mat(&estimates);
        let m = estimates.len() - 1;
        let s = &mut self.state;
        s.model = Some(self.setup.dmd.init(z.subcols(0, m), z.subcols(1, m))?);
        let n = self.setup.grid.len() as f64;
        s.pred_var = s
            .held_aerial
            .as_ref()
            .map_or(1.0, |a| a.variance.iter().sum::<f64>() / n)
            .max(1e-12);
        s.newest = estimates.into_iter().last();
        self.refit()?;
        self.move_filter()
    }

    /// Fold an epoch's fused snapshots into the model (pairs chained from the newest one) and
    /// refit.
    pub fn assimilate(&mut self, epoch: Vec<Vec<f64>>) -> Result<(), TeamError> {
        self.assimilate_prepared(epoch, None)
    }

    /// The part of the model update that needs only the pairs' first snapshots (the newest
    /// one, then `fused`: the epoch's fused steps but its last), as a job to run beside the
    /// epoch's last filter step ([`Dmd::prepare`]). The job takes the model with it: give
    /// [`Self::return_lent_model`] the model it returns before anything else is asked of this
    /// assimilator, and [`Self::assimilate_prepared`] what it made.
    pub fn lend_model_for_update<'a>(&mut self, fused: &'a [Vec<f64>]) -> Option<LentModel<'a>> {
        let newest = self.state.newest.clone()?;
        let model = self.state.model.take()?;
        Some(LentModel {
            model,
            setup: self.setup.clone(),
            mean: self.state.mean.clone(),
            newest,
            fused,
        })
    }

    /// The model a [`LentModel`] took, given back.
    pub fn return_lent_model(&mut self, model: Box<dyn Dmd>) {
        self.state.model = Some(model);
    }

    /// [`Self::assimilate`] with what a [`LentModel`] made of this epoch's first snapshots
    /// (the same model to the bit; what does not fit them is not taken).
    pub fn assimilate_prepared(&mut self, epoch: Vec<Vec<f64>>, prepared: Option<Prepared>) -> Result<(), TeamError> {
        if epoch.is_empty() {
            return Ok(());
        }
        let s = &mut self.state;
        let mut chain = vec![s.newest.clone().ok_or(TeamError::NotReady(Missing::Model))?];
        chain.extend(epoch.into_iter().map(|e| less(s.mean.as_deref(), self.setup.dry(e))));
        let z = to_mat(&chain);
        let m = chain.len() - 1;
        let model = s.model.as_mut().ok_or(TeamError::NotReady(Missing::Model))?;
        tracing::info_span!("dmd update")
            .in_scope(|| model.update_prepared(prepared, z.subcols(0, m), z.subcols(1, m)))?;
        s.newest = chain.pop();
        self.refit()?;
        self.move_filter()
    }

    fn refit(&mut self) -> Result<(), TeamError> {
        let s = &mut self.state;
        let model = s.model.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let newest = s.newest.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let (fitted, basis, dynamics) =
            tracing::info_span!("refit").in_scope(|| fit_with_dynamics(model.as_ref(), newest))?;
        s.fitted = Some((Arc::new(fitted), Arc::new(basis)));
        s.dynamics = dynamics;
        Ok(())
    }

    /// [`Fuser::Filter`]: carry the filter into the refitted model's basis and dynamics (or
    /// start it, at the newest snapshot, with the calibrated prediction variance per cell).
    /// Its state is then at the newest snapshot: the fused one of the last step, which is the
    /// filter's own posterior mean. A blend has no filter to carry.
    fn move_filter(&mut self) -> Result<(), TeamError> {
        if let Fuser::Blend(_) = self.setup.fuser {
            return Ok(());
        }
        let _span = tracing::info_span!("move filter").entered();
        let s = &mut self.state;
        let (pred, basis) = s.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let dynamics = match &s.dynamics {
            Some(d) => d.clone(),
            None => kalman::modal_dynamics(pred.modes.modes.as_ref(), &pred.modes.eigenvalues, Mat::as_ref(basis))?,
        };
        s.filter = Some(match s.filter.take() {
            Some((mut f, _)) => {
                f.reproject(basis.clone(), dynamics)?;
                (f, 0)
            }
            None => {
                let newest = s.newest.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
                let mean: Vec<f64> = (0..basis.ncols())
                    .map(|j| basis.col(j).iter().zip(newest).map(|(b, x)| b * x).sum())
                    .collect();
                // The start: the modal state as uncertain as the prediction is per cell; the
                // process noise a hundredth of it per step and the model error the
                // prediction's variance, both re-estimated from the boats' innovations.
                let q = basis.ncols();
                let cov = Mat::from_fn(q, q, |i, j| if i == j { s.pred_var } else { 0.0 });
                let f = ModalFilter::new(basis.clone(), dynamics, mean, cov, 0.01 * s.pred_var, s.pred_var)?;
                (f, 0)
            }
        });
        Ok(())
    }
}

/// The field the model's anomalies are about: the mean of `snapshots` over every wet cell and
/// snapshot, on every wet cell, and 0 on `land` (whose rows the model keeps at zero).
fn mean_of(snapshots: &[Vec<f64>], land: &[usize]) -> Vec<f64> {
    let n = snapshots.first().map_or(0, Vec::len);
    let mut dry = vec![false; n];
    land.iter().for_each(|&c| dry[c] = true);
    let (sum, count) = snapshots
        .iter()
        .flat_map(|s| s.iter().zip(&dry).filter(|(_, &d)| !d))
        .fold((0.0, 0usize), |(s, k), (x, _)| (s + x, k + 1));
    let level = sum / count.max(1) as f64;
    dry.iter().map(|&d| if d { 0.0 } else { level }).collect()
}

/// `x` less `mean` (as it is without one).
fn less(mean: Option<&Vec<f64>>, mut x: Vec<f64>) -> Vec<f64> {
    if let Some(m) = mean {
        x.iter_mut().zip(m.iter()).for_each(|(v, m)| *v -= m);
    }
    x
}

/// `x` plus `mean` (as it is without one).
fn plus(mean: Option<&Vec<f64>>, mut x: Vec<f64>) -> Vec<f64> {
    if let Some(m) = mean {
        x.iter_mut().zip(m.iter()).for_each(|(v, m)| *v += m);
    }
    x
}

impl Assimilator {
    /// A field as the model sees it: its anomaly about the initialisation's mean.
    fn less_mean(&self, x: Vec<f64>) -> Vec<f64> {
        less(self.state.mean.as_deref(), x)
    }

    /// A field the model made, in the field's own values.
    fn plus_mean(&self, x: Vec<f64>) -> Vec<f64> {
        plus(self.state.mean.as_deref(), x)
    }

    /// The initialisation's mean at each of `cells` (0 before the first model).
    fn mean_at(&self, cells: &[usize]) -> Vec<f64> {
        match self.state.mean.as_deref() {
            Some(m) => cells.iter().map(|&c| m[c]).collect(),
            None => vec![0.0; cells.len()],
        }
    }

    /// The field's mean level the model's anomalies are about (0 before the first model).
    pub fn field_level(&self) -> f64 {
        let land = &self.setup.land;
        let wet = (0..self.setup.grid.len()).find(|c| land.binary_search(c).is_err());
        match (self.state.mean.as_deref(), wet) {
            (Some(m), Some(c)) => m[c],
            _ => 0.0,
        }
    }
}

/// A model fitted to its newest snapshot (forecasts count from it), and an orthonormal real
/// basis of its modes (for gappy reconstruction and placement).
pub fn fit_to(model: &dyn Dmd, newest: &[f64]) -> Result<(DmdModel, Mat<f64>), TeamError> {
    fit_with_dynamics(model, newest).map(|(fitted, basis, _)| (fitted, basis))
}

/// A fitted model, its real basis, and (when the refit could make them cheaply) its dynamics
/// in that basis.
type Fitted = (DmdModel, Mat<f64>, Option<Mat<f64>>);

/// [`fit_to`], and the model's dynamics in that basis ([`kalman::modal_dynamics`]) when the
/// modes come factored as `Phi = Q M` with the basis `Q U`: then `Phi^H Phi = M^H M` and
/// `Phi^H B = M^H U`, r x r products, where the modes' N rows cost two N x r x r complex
/// products (most of the filter's move to a new model at 192 x 384).
fn fit_with_dynamics(model: &dyn Dmd, newest: &[f64]) -> Result<Fitted, TeamError> {
    let factored = tracing::info_span!("decompose").in_scope(|| model.factored())?;
    let Some(Factored { eigenvalues, factors }) = factored else {
        let modes = tracing::info_span!("decompose").in_scope(|| model.decompose())?;
        let basis = tracing::info_span!("basis").in_scope(|| real_basis(modes.modes.as_ref()))?;
        let fitted = tracing::info_span!("amplitudes").in_scope(|| modes.model(newest, 1.0))?;
        return Ok((fitted, basis, None));
    };
    // The modes (N x r complex) need only the factors, and so do the basis and the dynamics:
    // made side by side.
    let (modes, spanned) = crate::side_by_side::beside(
        || tracing::info_span!("modes").in_scope(|| factors.modes()),
        || -> Result<_, TeamError> {
            let orthogonal = tracing::info_span!("orthogonal factor").in_scope(|| factors.orthogonal());
            let _span = tracing::info_span!("basis").entered();
            let coordinates = real_basis_coordinates(&orthogonal)?;
            let dynamics = kalman::modal_dynamics(orthogonal.m.as_ref(), &eigenvalues, coordinates.as_ref())?;
            let basis = fleet_math::par::product(orthogonal.q.as_ref(), coordinates.as_ref());
            Ok((orthogonal, basis, dynamics))
        },
    );
    let (orthogonal, basis, dynamics) = spanned?;
    let modes = Modes { eigenvalues, modes };
    let fitted = tracing::info_span!("amplitudes").in_scope(|| modes.model_on(&orthogonal, newest, 1.0))?;
    Ok((fitted, basis, Some(dynamics)))
}

/// Every cell the samples cover, in their order.
fn cells_of(samples: &[crate::health::VehicleSample]) -> Vec<usize> {
    samples
        .iter()
        .flat_map(|t| t.sample.cells.iter().map(|&c| c as usize))
        .collect()
}

/// The model and the snapshots its next update starts from, taken to make that update's
/// first part on another thread ([`Assimilator::lend_model_for_update`]).
pub struct LentModel<'a> {
    model: Box<dyn Dmd>,
    setup: Arc<Setup>,
    mean: Option<Arc<Vec<f64>>>,
    newest: Vec<f64>,
    fused: &'a [Vec<f64>],
}

impl LentModel<'_> {
    /// The model, to be given back, and what it made ahead (`None` where its method makes
    /// nothing ahead, or refuses the snapshots: the update then does it all, or says why).
    pub fn run(self) -> (Box<dyn Dmd>, Option<Prepared>) {
        let mut columns = vec![self.newest];
        let mean = self.mean.as_deref();
        columns.extend(self.fused.iter().map(|e| less(mean, self.setup.dry(e.clone()))));
        let prepared = self.model.prepare(to_mat(&columns).as_ref());
        (self.model, prepared)
    }
}

/// Columns to a matrix.
pub fn to_mat(cols: &[Vec<f64>]) -> Mat<f64> {
    let n = cols.first().map_or(0, |c| c.len());
    Mat::from_fn(n, cols.len(), |i, j| cols[j][i])
}

/// The aerial estimate's error variance per cell as the filter's detail sees it: its noise,
/// the interpolation's error and, between the lattice, the calibrated extra (one definition for
/// the update and for the look ahead that plans on it). A lattice cell is the aerials' own value
/// there, with its noise and nothing else: the extra is the interpolation's misfit, which the
/// boats measure between the lattice, and added on the lattice it made the fused map follow the
/// aerials' own values less than the aerial-only map does.
fn aerial_detail_variance(noise: &[f64], interpolation: &[f64], extra: f64, on_lattice: &[bool]) -> Vec<f64> {
    noise
        .iter()
        .zip(interpolation)
        .zip(on_lattice)
        .map(|((v, i), &lattice)| (v + i + if lattice { 0.0 } else { extra }).max(1e-12))
        .collect()
}
#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Sample;
    use crate::vehicle::{sense_aerial, sense_boat, vehicle_rng};
    use fleet_math::fusion::AerialNoise;
    use fleet_math::process::synthetic::plume_field;
    use rand::seq::SliceRandom;

    /// A small mission: a plume at 24 x 48, 3 aerials on a lattice of stride 3, 4 boats, rank
    /// 6, 10 initial steps; the truth at step `k`.
    fn small_mission() -> (TeamConfig, Grid, impl Fn(usize) -> Vec<f64>) {
        let truth = plume_field(24, 48, 30, 0.0, 1);
        let cfg = TeamConfig {
            aerials: 3,
            boats: 4,
            radius: 3.0,
            rank: fleet_math::dmd::RankPolicy::Fixed(6),
            init_steps: 10,
            aerial_stride: 3,
            ..TeamConfig::default()
        };
        let x = move |k: usize| -> Vec<f64> { truth.snapshots.col(k).iter().copied().collect() };
        (cfg, Grid::new(24, 48, 1.0).unwrap(), x)
    }

    /// The aerials' samples of step `k` of the field `x`, each from its own stream.
    fn aerial_samples(server: &Assimilator, x: &[f64], k: usize, rngs: &mut [ChaCha8Rng]) -> Vec<Sample> {
        let (pos, grid) = (server.aerial_positions().to_vec(), *server.grid());
        (0..pos.len())
            .map(|a| sense_aerial(&grid, x, k as u64, 3, &pos, a, server.aerial_noise(), &mut rngs[a]).unwrap())
            .collect()
    }

    /// The boats' samples of step `k` of the field `x` on the disks `plan` gives them.
    fn boat_samples(plan: &Allocation, grid: &Grid, x: &[f64], k: usize, rngs: &mut [ChaCha8Rng]) -> Vec<Sample> {
        let aerials = rngs.len() - plan.boats.len();
        plan.boats
            .iter()
            .enumerate()
            .filter_map(|(b, d)| {
                let rng = &mut rngs[aerials + b];
                d.as_ref()
                    .map(|(c, _)| sense_boat(grid, x, k as u64, (0.0, 0.0), c, 0.01, rng).unwrap())
            })
            .collect()
    }

    #[test]
    fn arrival_order_does_not_change_the_estimates() {
        let (cfg, grid, x) = small_mission();
        let run = |shuffle: bool| -> (Vec<f64>, Vec<f64>) {
            let mut server = Assimilator::new(&cfg, grid, 30).unwrap();
            let mut rngs: Vec<ChaCha8Rng> = (0..7).map(|v| vehicle_rng(cfg.seed, v)).collect();
            let mut order = ChaCha8Rng::seed_from_u64(99);
            let mut init = vec![];
            for k in 0..10 {
                let mut s = aerial_samples(&server, &x(k), k, &mut rngs);
                if shuffle {
                    s.shuffle(&mut order);
                }
                init.push(server.aerial_estimate(&s).unwrap().estimate.values);
            }
            server.initialise(init).unwrap();
            let plan = server.allocate().unwrap();
            let mut boats = boat_samples(&plan, &grid, &x(10), 10, &mut rngs);
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

    /// The model server makes the next step's aerial sight on the other core while the filter
    /// steps, which is right only if the sight reads nothing the step changes: made beside a
    /// filter step and held after it, it is the sight made after the step, to the bit, and so
    /// is what a step without aerial samples then holds.
    #[test]
    fn an_aerial_sight_made_beside_a_filter_step_is_the_one_made_after_it() {
        let (cfg, grid, x) = small_mission();
        let mut server = Assimilator::new(&cfg, grid, 30).unwrap();
        let mut rngs: Vec<ChaCha8Rng> = (0..7).map(|v| vehicle_rng(cfg.seed, v)).collect();
        let init = (0..10)
            .map(|k| {
                let s = aerial_samples(&server, &x(k), k, &mut rngs);
                server.aerial_estimate(&s).unwrap().estimate.values
            })
            .collect();
        server.initialise(init).unwrap();
        let plan = server.allocate().unwrap();
        let boats = boat_samples(&plan, &grid, &x(10), 10, &mut rngs);
        let now = aerial_samples(&server, &x(10), 10, &mut rngs);
        let next = aerial_samples(&server, &x(11), 11, &mut rngs);
        let mut in_turn = server.clone();
        let aerial = in_turn.aerial_estimate(&now).unwrap();
        let fused = in_turn.fuse_step(1, &aerial, &boats).unwrap();
        let after = in_turn.aerial_estimate(&next).unwrap();
        let mut beside = server;
        let aerial = beside.aerial_estimate(&now).unwrap();
        let later = beside.aerial_sight_later(next);
        let (fused_beside, made) = rayon::join(|| beside.fuse_step(1, &aerial, &boats).unwrap(), later);
        let made = beside.hold_aerial(made.unwrap()).unwrap();
        assert_eq!(fused, fused_beside);
        assert_eq!(
            after, made,
            "the sight made beside the step differs from the one made after it"
        );
        assert_eq!(
            in_turn.aerial_estimate(&[]).unwrap(),
            beside.aerial_estimate(&[]).unwrap()
        );
    }

    /// The known answer behind "land leaves the model grid": land is zero in every snapshot,
    /// so zero rows of the snapshot matrices, and the DMD of the whole grid is the DMD of the
    /// wet cells (the same eigenvalues, the same forecast there, exactly zero on land). An exact
    /// rank-4 linear system (a damped rotation and two decays) on 30 wet cells of 40.
    #[test]
    fn land_as_zero_rows_is_the_dmd_of_the_wet_cells() {
        use fleet_math::dmd::{DmdConfig, Method, RankPolicy};
        let (n, t) = (40, 25);
        let wet: Vec<usize> = (0..n).filter(|i| i % 4 != 1).collect();
        let f = |k: usize, s: f64| {
            let (k, r) = (k as i32, 0.3 * k as f64);
            0.95f64.powi(k) * (r.cos() * (0.2 * s).sin() + r.sin() * (0.2 * s).cos())
                + 0.9f64.powi(k) * (0.05 * s).cos()
                + 0.8f64.powi(k) * (s / 30.0).powi(2)
        };
        let on_wet: Vec<Vec<f64>> = (0..t)
            .map(|k| (0..wet.len()).map(|j| f(k, j as f64)).collect())
            .collect();
        let on_grid: Vec<Vec<f64>> = on_wet
            .iter()
            .map(|c| {
                let mut v = vec![0.0; n];
                wet.iter().zip(c).for_each(|(&i, &x)| v[i] = x);
                v
            })
            .collect();
        for method in [Method::General, Method::Batch] {
            let cfg = DmdConfig {
                method,
                rank: RankPolicy::Fixed(4),
                debias: Default::default(),
                gamma: 1.0,
                forgetting: Default::default(),
            };
            let fit = |cols: &[Vec<f64>]| {
                let (z, m) = (to_mat(cols), cols.len() - 1);
                let d = cfg.init(z.subcols(0, m), z.subcols(1, m)).unwrap();
                fit_to(d.as_ref(), cols.last().unwrap()).unwrap().0
            };
            let (a, b) = (fit(&on_wet), fit(&on_grid));
            let eig = |m: &DmdModel| {
                let mut v: Vec<[f64; 2]> = m.modes.eigenvalues.iter().map(|z| [z.re, z.im]).collect();
                v.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
                v
            };
            for (x, y) in eig(&a).iter().zip(eig(&b)) {
                assert!(
                    (x[0] - y[0]).abs() < 1e-9 && (x[1] - y[1]).abs() < 1e-9,
                    "{method:?}: {x:?} vs {y:?}"
                );
            }
            let (pa, pb) = (a.predict(3.0), b.predict(3.0));
            for (j, &i) in wet.iter().enumerate() {
                assert!((pa[j] - pb[i]).abs() < 1e-9, "{method:?} forecast at cell {i}");
            }
            assert!((0..n).filter(|i| !wet.contains(i)).all(|i| pb[i].abs() < 1e-12));
        }
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
