//! A vehicle's own loop, without the network: keep the newest plan, move toward its targets
//! at a bounded speed, sense what the plan says at each sampling step, and number the batches.
//! The Zenoh vehicle node wraps this; the server tests drive it directly.
//!
//! A vehicle that has not reached its target by the sampling step senses from where it is:
//! an aerial its planned region (with the noise of the longer distance), a boat the disk
//! around its own cell. With speeds that let every vehicle arrive (the default mission) the
//! samples are exactly the offline experiment's.

use crate::protocol::{MeasurementBatch, Plan, Sample, Target, VehicleId, VehicleKind};
use crate::schedule::Schedule;
use fleet_math::fusion::{draw, AerialNoise, FusionError};
use fleet_math::grid::Grid;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// A vehicle's own random stream: the same seed and vehicle give the same noise whichever
/// process the vehicle runs in. Aerials are vehicles `0..aerials`, boats follow.
pub fn vehicle_rng(seed: u64, vehicle: usize) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(1 + vehicle as u64);
    rng
}

/// The cells aerial `me` senses (the sensor model lives with the fusion that inverts it).
pub use fleet_math::fusion::aerial_region;

/// What a sensor at `pos` (metres) measures of `truth` at `cells` at one `step`, with
/// `noise` ([`draw`]), as a sample for the wire. A cell where the truth has no value (NaN:
/// land, cloud, no data) is not measured: a boat's disk is clipped by the coast, an aerial
/// frame has a hole.
pub fn sense_cells<R: rand::Rng + ?Sized>(
    grid: &Grid,
    truth: &[f64],
    step: u64,
    pos: (f64, f64),
    cells: &[usize],
    noise: AerialNoise,
    rng: &mut R,
) -> Result<Sample, FusionError> {
    let there: Vec<usize>;
    let cells = if cells.iter().any(|&c| truth.get(c).is_some_and(|v| v.is_nan())) {
        there = cells.iter().copied().filter(|&c| !truth[c].is_nan()).collect();
        &there
    } else {
        cells
    };
    Ok(Sample {
        step,
        position: [pos.0, pos.1],
        cells: cells.iter().map(|&c| c as u32).collect(),
        values: draw(grid, truth, pos, cells, noise, rng)?,
        sigma: None,
    })
}

/// What aerial `me` sees of `truth` at one step: its region ([`aerial_region`]) sensed from
/// where it is ([`sense_cells`]).
#[allow(clippy::too_many_arguments)]
pub fn sense_aerial<R: rand::Rng + ?Sized>(
    grid: &Grid,
    truth: &[f64],
    step: u64,
    stride: usize,
    aerials: &[(f64, f64)],
    me: usize,
    noise: AerialNoise,
    rng: &mut R,
) -> Result<Sample, FusionError> {
    let region = aerial_region(grid, stride, aerials, me)?;
    sense_cells(grid, truth, step, aerials[me], &region, noise, rng)
}

/// What a boat measures at one step: every cell of its disk, with noise `sigma`.
pub fn sense_boat(
    grid: &Grid,
    truth: &[f64],
    step: u64,
    position: (f64, f64),
    cells: &[usize],
    sigma: f64,
    rng: &mut ChaCha8Rng,
) -> Result<Sample, FusionError> {
    let noise = crate::protocol::Noise {
        sigma0: sigma,
        growth_per_m: 0.0,
    };
    sense_cells(grid, truth, step, position, cells, noise, rng)
}

/// What a vehicle must keep across a crash to carry on exactly where it was: the next epoch
/// to sense, its random stream's position, its plan and where it is. Committed with each batch
/// (in the same transaction), so a restart neither repeats nor skips a draw.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BrainState {
    pub next_epoch: u64,
    /// The random stream's word position, high and low halves.
    rng_word_pos: [u64; 2],
    plan: Option<Plan>,
    position: Option<(f64, f64)>,
    last_step: Option<usize>,
    off_target: u64,
}

/// Where an autopilot put the vehicle for a sampling step: its reported position (grid
/// metres) and whether that is within the acceptance distance of the target (then the
/// vehicle senses exactly its planned place, as the offline experiment does).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fix {
    pub position: (f64, f64),
    pub arrived: bool,
}

#[derive(Clone)]
pub struct VehicleBrain {
    pub id: VehicleId,
    pub kind: VehicleKind,
    grid: Grid,
    schedule: Schedule,
    noise: AerialNoise,
    rng: ChaCha8Rng,
    /// Metres per step.
    speed: f64,
    plan: Option<Plan>,
    position: Option<(f64, f64)>,
    last_step: Option<usize>,
    /// Samples taken away from their planned place.
    pub off_target: u64,
}

impl VehicleBrain {
    pub fn new(
        id: &VehicleId,
        kind: VehicleKind,
        grid: Grid,
        schedule: Schedule,
        noise: AerialNoise,
        rng: ChaCha8Rng,
        speed: f64,
    ) -> Self {
        Self {
            id: id.clone(),
            kind,
            grid,
            schedule,
            noise,
            rng,
            speed,
            plan: None,
            position: None,
            last_step: None,
            off_target: 0,
        }
    }

    pub fn schedule(&self) -> &Schedule {
        &self.schedule
    }

    /// Where the vehicle is (`None` before its first target).
    pub fn position(&self) -> Option<(f64, f64)> {
        self.position
    }

    pub fn plan(&self) -> Option<&Plan> {
        self.plan.as_ref()
    }

    /// The state to commit once everything before `next_epoch` is sensed.
    pub fn state(&self, next_epoch: u64) -> BrainState {
        let w = self.rng.get_word_pos();
        BrainState {
            next_epoch,
            rng_word_pos: [(w >> 64) as u64, w as u64],
            plan: self.plan.clone(),
            position: self.position,
            last_step: self.last_step,
            off_target: self.off_target,
        }
    }

    /// Carry on from a committed state.
    pub fn restore(&mut self, s: BrainState) {
        self.rng
            .set_word_pos(((s.rng_word_pos[0] as u128) << 64) | s.rng_word_pos[1] as u128);
        (self.plan, self.position, self.last_step, self.off_target) = (s.plan, s.position, s.last_step, s.off_target);
    }

    /// Take a plan unless it is older than the one held.
    pub fn set_plan(&mut self, plan: Plan) {
        let newer = self
            .plan
            .as_ref()
            .is_none_or(|p| (plan.epoch, plan.model_version) >= (p.epoch, p.model_version));
        if plan.vehicle == self.id && newer {
            self.plan = Some(plan);
        }
    }

    /// Whether the held plan covers epoch `e` (the vehicle can sense it without the server).
    pub fn covers(&self, e: u64) -> bool {
        self.plan
            .as_ref()
            .is_some_and(|p| p.epoch <= e && p.targets.iter().any(|t| t.epoch == e))
    }

    /// Move toward `target` for the steps since the last sample.
    fn move_to(&mut self, target: &Target) -> (f64, f64) {
        let goal = (target.position[0], target.position[1]);
        let pos = match (self.position, self.last_step) {
            (Some(p), Some(last)) => {
                let reach = self.speed * (target.step as usize).saturating_sub(last) as f64;
                let (dx, dy) = (goal.0 - p.0, goal.1 - p.1);
                let d = dx.hypot(dy);
                if d <= reach {
                    goal
                } else {
                    (p.0 + dx * reach / d, p.1 + dy * reach / d)
                }
            }
            // Launched at its first target.
            _ => goal,
        };
        self.position = Some(pos);
        self.last_step = Some(target.step as usize);
        pos
    }

    /// Sense epoch `e` under the held plan: its batch (`None`: this vehicle sends none for
    /// `e`). `truth_at(k)` is the field at step `k` (mixed reality: a dataset or simulator).
    pub fn sense_epoch(
        &mut self,
        e: u64,
        truth_at: impl Fn(usize) -> Vec<f64>,
    ) -> Result<Option<MeasurementBatch>, FusionError> {
        self.sense_epoch_at(e, truth_at, &std::collections::BTreeMap::new())
    }

    /// The targets of epoch `e`'s sampling steps under the held plan (empty without one).
    pub fn targets_of(&self, e: u64) -> Vec<Target> {
        let steps = self.schedule.sample_steps(self.kind, e);
        match &self.plan {
            Some(p) => steps
                .iter()
                .filter_map(|&k| p.targets.iter().find(|t| t.step as usize == k).cloned())
                .collect(),
            None => vec![],
        }
    }

    /// Epoch `e`'s batch of an instrument's `samples` (`None`: this vehicle sends none for
    /// `e`), in place of [`Self::sense_epoch_at`]'s draws from a truth.
    pub fn batch_of(&self, e: u64, samples: Vec<Sample>) -> Option<MeasurementBatch> {
        Some(MeasurementBatch {
            vehicle: self.id.clone(),
            kind: self.kind,
            seq: self.schedule.seq_of(self.kind, e)?,
            noise: self.noise,
            samples,
        })
    }

    /// An aerial camera's frames of epoch `e` as its batch's samples: at each sampling step
    /// with a frame, the cells of the step's target (its region's lattice) that the frame has a
    /// value for, seen from where the aerial was (its fix, else the target), each with the noise
    /// of its distance. Frames of other steps are not the schedule's and are left out.
    pub fn seen_from_targets(
        &self,
        e: u64,
        frames: Vec<Sample>,
        fixes: &std::collections::BTreeMap<u64, Fix>,
    ) -> Vec<Sample> {
        let targets = self.targets_of(e);
        frames
            .into_iter()
            .filter_map(|f| {
                let t = targets.iter().find(|t| t.step == f.step && !t.cells.is_empty())?;
                let pos = fixes.get(&t.step).map_or(t.position, |x| [x.position.0, x.position.1]);
                let (cells, values): (Vec<u32>, Vec<f64>) = f
                    .cells
                    .iter()
                    .zip(&f.values)
                    .filter(|(c, _)| t.cells.contains(c))
                    .map(|(&c, &v)| (c, v))
                    .unzip();
                let sigma = cells
                    .iter()
                    .map(|&c| {
                        let (x, y) = self.grid.centre_m(self.grid.cell(c as usize));
                        self.noise.std_at((pos[0] - x).hypot(pos[1] - y)).max(1e-12)
                    })
                    .collect();
                (!cells.is_empty()).then_some(Sample {
                    step: f.step,
                    position: pos,
                    cells,
                    values,
                    sigma: Some(sigma),
                })
            })
            .collect()
    }

    /// The first step of the first epoch this vehicle senses (its instrument's readings
    /// before it have no batch to go in).
    pub fn first_sensed_step(&self) -> u64 {
        let s = &self.schedule;
        (0..s.epochs())
            .find(|&e| s.seq_of(self.kind, e).is_some())
            .map_or(s.frames as u64, |e| s.steps_of(e).start as u64)
    }

    /// [`Self::sense_epoch`] with the positions an autopilot reported, by step; steps without a
    /// fix use the vehicle's own kinematics.
    pub fn sense_epoch_at(
        &mut self,
        e: u64,
        truth_at: impl Fn(usize) -> Vec<f64>,
        fixes: &std::collections::BTreeMap<u64, Fix>,
    ) -> Result<Option<MeasurementBatch>, FusionError> {
        let Some(seq) = self.schedule.seq_of(self.kind, e) else {
            return Ok(None);
        };
        let steps = self.schedule.sample_steps(self.kind, e);
        let targets = self.targets_of(e);
        if targets.len() != steps.len() {
            return Err(FusionError::Input(format!("{}: no plan covers epoch {e}", self.id)));
        }
        let mut samples: Vec<Sample> = vec![];
        for t in &targets {
            // A vehicle left out of the allocation (a boat without a disk, or one on operator
            // hold) reports the epoch with nothing in it.
            if t.cells.is_empty() {
                continue;
            }
            let pos = match fixes.get(&t.step) {
                Some(f) => {
                    let pos = if f.arrived {
                        (t.position[0], t.position[1])
                    } else {
                        f.position
                    };
                    (self.position, self.last_step) = (Some(pos), Some(t.step as usize));
                    pos
                }
                None => self.move_to(t),
            };
            let arrived = pos == (t.position[0], t.position[1]);
            let cells: Vec<usize> = match (self.kind, arrived) {
                (VehicleKind::Boat, false) => {
                    let here = self
                        .grid
                        .cell_at(pos.0, pos.1)
                        .ok_or_else(|| FusionError::Input(format!("{}: position {pos:?} off the grid", self.id)))?;
                    self.grid.disk(here, t.radius)
                }
                _ => t.cells.iter().map(|&c| c as usize).collect(),
            };
            if !arrived {
                self.off_target += 1;
            }
            samples.push(sense_cells(
                &self.grid,
                &truth_at(t.step as usize),
                t.step,
                pos,
                &cells,
                self.noise,
                &mut self.rng,
            )?);
        }
        Ok(Some(MeasurementBatch {
            vehicle: self.id.clone(),
            kind: self.kind,
            seq,
            noise: self.noise,
            samples,
        }))
    }
}
