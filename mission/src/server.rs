//! The model server's core, without the network: measurement batches in (any order, any
//! number of times), each assimilated exactly once, epochs folded into the model in step order
//! as soon as they are complete, acks, plans and model updates out. The Zenoh node wraps this.
//!
//! The epoch contract ([`Schedule`]): every vehicle sends one batch per epoch it takes part
//! in, and its `seq` counts those batches from 0 without gaps. Aerials take part from epoch 0
//! (the aerial-only initialisation); boats in every full epoch from epoch 1 (a boat left
//! without a disk sends an empty batch). An epoch is complete when every batch for it is in.

use crate::grid::Grid;
use crate::health::{Health, Pin, Tagged, Verdict, CLEAN_STEPS};
use crate::history::History;
use crate::protocol::{self, Ack, MeasurementBatch, ModelUpdate, Plan, Sample, Target, VehicleId, VehicleKind};
use crate::published::{Made, ModelParts, Published};
use crate::team::{LearnFrom, TeamConfig, TeamError};
use crate::{schedule::Schedule, Allocation, Assimilator};
use std::collections::{BTreeMap, BTreeSet};

/// Epochs between checkpoints of the model state (each holds the model's factors and the
/// aerial estimate, about 0.8 MB at 48 x 96 and rank 10, 50-70 MB at 384 x 768); older ones
/// are thinned ([`keep_checkpoint`]).
pub const CHECKPOINT_EVERY: u64 = 4;

/// Whether the checkpoint at epoch `at` is kept once the newest is at `newest`: the nearest
/// ones all, older ones ever sparser, each spaced by the largest power of two (in checkpoint
/// intervals) not above its age. So a mission of E epochs keeps at most 2 log2(E / 4 + 1) of
/// them, not E / 4 (memory that does not grow with the mission), and a batch late by A epochs
/// re-fits at most 3 A + 4 epochs (tested). The rule only tightens with age, so a checkpoint
/// dropped would never have been kept later; which one a re-fit starts from never changes the
/// model (a re-fit equals the fresh run, tested).
pub fn keep_checkpoint(at: u64, newest: u64) -> bool {
    let index = at / CHECKPOINT_EVERY;
    let age = newest.saturating_sub(at) / CHECKPOINT_EVERY;
    let spacing_log2 = age.checked_ilog2().unwrap_or(0);
    index.is_multiple_of(1 << spacing_log2)
}

pub use crate::roster::{Roster, VehicleSpec};

/// What happened to one batch.
#[derive(Debug, Clone, PartialEq)]
pub enum Ingested {
    /// Already assimilated or already waiting: dropped (and acked again).
    Duplicate,
    /// Kept until its epoch is complete.
    Buffered,
    /// Completed these epochs, which are now in the model.
    Assimilated(Vec<u64>),
    /// Arrived for an epoch already assimilated without it (forced by a timeout): the model
    /// was re-fitted from that epoch on, with everything now in (by `ingest`; after
    /// `ingest_deferred`, once `settle` has run).
    Refitted(u64),
}

/// The journal's metadata key prefix of the operator's sensor overrides
/// (`sensor/<vehicle>/<step>`, zero-padded: key order is step order per vehicle).
pub const OVERRIDE_PREFIX: &str = "sensor/";

/// Why [`ServerCore::check`] refuses a batch.
enum BatchFault {
    Unknown,
    Invalid(String),
}

#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error(transparent)]
    Protocol(#[from] protocol::ProtocolError),
    #[error("batch from {vehicle}: {why}")]
    Rejected { vehicle: VehicleId, why: String },
    #[error(transparent)]
    Model(#[from] TeamError),
}

/// What the server decided about one epoch that its batches alone do not say: the vehicles
/// left out of the epoch's allocation (from telemetry: operator hold, autopilot lost), and
/// whether it was assimilated without some batch (a late vehicle). Journalled with the
/// batches, so a restarted server makes the same plans and reaches the same epoch.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpochRecord {
    pub held: Vec<VehicleId>,
    pub forced: bool,
}

impl EpochRecord {
    /// The journal's metadata key of epoch `e`'s record (zero-padded: key order is epoch order).
    pub fn key(e: u64) -> String {
        format!("{}{e:010}", Self::PREFIX)
    }
    pub const PREFIX: &'static str = "epoch/";
}

#[derive(Debug, thiserror::Error)]
pub enum RestoreError {
    #[error("record {key:?} is unreadable: {why}")]
    Record { key: String, why: String },
    #[error("record {key:?} names {vehicle:?}, which is not in the mission")]
    UnknownVehicle { key: String, vehicle: String },
    #[error("batch {seq} of {vehicle}: {why}")]
    Batch { vehicle: VehicleId, seq: u64, why: String },
    #[error(transparent)]
    Model(#[from] TeamError),
}

/// Counters a node reports.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Counters {
    pub batches: u64,
    pub duplicates: u64,
    pub rejected: BTreeMap<String, u64>,
    pub epochs: u64,
    /// Batches replayed from the journal at a restart (included in `batches`).
    #[serde(default)]
    pub restored: u64,
    /// Epochs assimilated without every batch (a timeout), and re-fits when the rest came.
    #[serde(default)]
    pub forced: u64,
    #[serde(default)]
    pub refits: u64,
    /// Epochs assimilated again by those re-fits (from the newest checkpoint before the
    /// earliest late epoch).
    #[serde(default)]
    pub refit_epochs: u64,
    /// Batches vehicles say were acknowledged but the journal does not hold (lost with it).
    #[serde(default)]
    pub lost: u64,
    /// Zenoh sessions the router refused at the handshake (wrong or missing credentials).
    #[serde(default)]
    pub sessions_refused: u64,
    /// Sensors re-admitted from `excluded` by their tests (each re-fits from its clean steps), and the
    /// operator's overrides taken.
    #[serde(default)]
    pub readmissions: u64,
    #[serde(default)]
    pub overrides: u64,
}

#[derive(Clone)]
pub struct ServerCore {
    cfg: TeamConfig,
    schedule: Schedule,
    vehicles: Roster,
    assim: Assimilator,
    /// Next epoch to assimilate.
    epoch: u64,
    /// Every batch accepted, by epoch then vehicle index: the model is a function of this
    /// set, so late batches re-fit it from their epoch on.
    received: BTreeMap<u64, BTreeMap<usize, MeasurementBatch>>,
    /// The plan each epoch was sensed under (to check boats measured their disks).
    plans: BTreeMap<u64, Allocation>,
    /// Vehicles (by index) the operator holds or whose autopilot is lost, as telemetry says.
    held: BTreeSet<usize>,
    /// The held set each epoch's allocation was made with (a re-fit makes the same plans).
    holds: BTreeMap<u64, BTreeSet<usize>>,
    pub counters: Counters,
    /// Model version: bumped at every assimilated epoch.
    pub version: u64,
    /// The fused estimate and its reported variance at every step assimilated so far (in
    /// memory, or in the run's files: [`Self::with_history_in`]).
    history: History,
    /// The aerial estimate of every step assimilated so far (the aerial-only team's map),
    /// kept only when asked for ([`Self::with_aerial_history`]: the experiments' baseline): a
    /// full field a step, 2.4 MB at 384 x 768, that the model server never reads.
    pub aerial_estimates: Vec<Vec<f64>>,
    keep_aerial_estimates: bool,
    /// Late batches taken by [`Self::ingest_deferred`] and not yet re-fitted.
    stale: bool,
    /// The earliest epoch those late batches belong to: the re-fit starts there.
    stale_from: u64,
    /// The state before every `CHECKPOINT_EVERY`-th epoch, older ones thinned
    /// ([`keep_checkpoint`]): a re-fit starts from the newest one at or before the earliest
    /// late epoch, so its cost grows with how late the batch is, not with the mission's length.
    /// (`None`: checkpoints off, every re-fit from epoch 0.)
    checkpoints: Option<BTreeMap<u64, (crate::AssimilatorCheckpoint, usize)>>,
    /// Epochs assimilated without some batch (by [`Self::force`]).
    forced: BTreeSet<u64>,
    /// Epochs whose [`EpochRecord`] changed since the node last journalled them.
    unjournalled: BTreeSet<u64>,
    /// The share of boat readings held out of the fusion to score it ([`crate::holdout`]; 0:
    /// none), and what the estimate said of each, by step (a re-fit writes its step again).
    holdout_share: f64,
    held_out: BTreeMap<usize, Vec<crate::holdout::HeldOut>>,
    /// The boats' innovations against the forecast, by step (a re-fit writes its steps again).
    innovations: BTreeMap<usize, crate::kalman::Innovation>,
    /// The model's skill by epoch (a re-fit writes its epochs again).
    skills: BTreeMap<u64, crate::protocol::EpochSkill>,
    /// The sensors' verdicts that changed, by step (a re-fit writes its steps again).
    verdicts: BTreeMap<usize, Vec<Verdict>>,
    /// The operator's overrides by vehicle, then the step each takes effect from (`None`: the
    /// tests decide again); journalled, and those not yet journalled.
    overrides: BTreeMap<usize, BTreeMap<u64, Option<Health>>>,
    unjournalled_overrides: BTreeSet<(usize, u64)>,
    /// Boats re-admitted from `excluded` by their tests: by vehicle, the first and last of the clean steps that
    /// re-admitted it (pinned `ok` when re-fitted: their values count as they came). Derived
    /// from the batches, so a re-fit from before one forgets it and finds it again.
    readmissions: BTreeMap<usize, BTreeMap<u64, u64>>,
    /// The earliest step a re-admission found since the last re-fit re-fits from.
    readmit_from: Option<u64>,
    /// The model as published and its encoding, made beside the epoch's placement (or when
    /// asked for, if the model changed since).
    published: Option<Published>,
    /// Where an epoch's model goes the moment it is made, beside the placement
    /// ([`Self::with_publisher`]; `None`: it waits for the caller).
    publisher: Option<Publisher>,
}

/// Takes an epoch's model the moment it is made, on the thread that made it (the node's hands
/// it to its Zenoh publisher): observers need not wait for the placement, which takes longer
/// (30 of 120 ms at 192 x 384) and which they do not read. It must not block.
pub type Publisher = std::sync::Arc<dyn Fn(&Published) + Send + Sync>;

impl ServerCore {
    pub fn new(cfg: &TeamConfig, grid: Grid, frames: usize) -> Result<Self, TeamError> {
        Ok(Self {
            assim: Assimilator::new(cfg, grid, frames)?,
            cfg: cfg.clone(),
            schedule: Schedule::new(cfg, frames),
            vehicles: Roster::of(cfg),
            epoch: 0,
            received: BTreeMap::new(),
            plans: BTreeMap::new(),
            held: BTreeSet::new(),
            holds: BTreeMap::new(),
            counters: Counters::default(),
            version: 0,
            history: History::default(),
            aerial_estimates: vec![],
            keep_aerial_estimates: false,
            stale: false,
            stale_from: u64::MAX,
            checkpoints: Some(BTreeMap::new()),
            holdout_share: 0.0,
            held_out: BTreeMap::new(),
            innovations: BTreeMap::new(),
            skills: BTreeMap::new(),
            verdicts: BTreeMap::new(),
            overrides: BTreeMap::new(),
            unjournalled_overrides: BTreeSet::new(),
            readmissions: BTreeMap::new(),
            readmit_from: None,
            published: None,
            publisher: None,
            forced: BTreeSet::new(),
            unjournalled: BTreeSet::new(),
        })
    }

    pub fn vehicles(&self) -> &[VehicleSpec] {
        self.vehicles.all()
    }

    pub fn roster(&self) -> &Roster {
        &self.vehicles
    }

    /// The epoch the server waits for next.
    pub fn next_epoch(&self) -> u64 {
        self.epoch
    }

    pub fn schedule(&self) -> &Schedule {
        &self.schedule
    }

    /// Steps of epoch `e` (empty past the end of the mission).
    pub fn steps_of(&self, e: u64) -> std::ops::Range<usize> {
        self.schedule.steps_of(e)
    }

    /// Vehicles whose batch for epoch `e` has not come in.
    fn missing(&self, e: u64) -> impl Iterator<Item = usize> + '_ {
        let have = self.received.get(&e);
        (0..self.vehicles.len()).filter(move |&i| self.takes_part(i, e) && !have.is_some_and(|m| m.contains_key(&i)))
    }

    /// Vehicles whose batch for epoch `e` has not come in (for an assimilated epoch: the ones it
    /// was assimilated without).
    pub fn missing_at(&self, e: u64) -> Vec<VehicleId> {
        self.missing(e).map(|i| self.vehicles.at(i).id.clone()).collect()
    }

    /// Vehicles whose batch for the next epoch, or for an epoch assimilated without it, has
    /// not come in.
    pub fn waiting_for(&self) -> Vec<VehicleId> {
        let mut ids: Vec<usize> = (0..=self.epoch)
            .flat_map(|e| self.missing(e).collect::<Vec<_>>())
            .collect();
        ids.sort_unstable();
        ids.dedup();
        ids.into_iter().map(|i| self.vehicles.at(i).id.clone()).collect()
    }

    /// Epochs beyond the model with some batches in, waiting for the rest.
    pub fn pending_epochs(&self) -> u64 {
        self.received.range(self.epoch..).count() as u64
    }

    /// Whether every step of the mission is in the model, with every batch.
    pub fn finished(&self) -> bool {
        !self.stale && self.all_assimilated() && (0..self.epoch).all(|e| self.missing(e).next().is_none())
    }

    fn all_assimilated(&self) -> bool {
        self.steps_of(self.epoch).is_empty() && self.epoch > 0
    }

    /// Assimilate the next epoch with the batches it has (a vehicle is late); its missing
    /// batches re-fit the model when they come. Epoch 0 (the first model) is never forced.
    pub fn force(&mut self) -> Result<bool, TeamError> {
        self.settle()?;
        let e = self.epoch;
        if e == 0 || self.steps_of(e).is_empty() || self.missing(e).next().is_none() {
            return Ok(false);
        }
        self.assimilate_epoch(e)?;
        self.readmit()?;
        self.counters.forced += 1;
        self.forced.insert(e);
        self.unjournalled.insert(e);
        self.assimilate_complete()?;
        Ok(true)
    }

    /// Assimilate every epoch from the next on that has all its batches.
    fn assimilate_complete(&mut self) -> Result<(), TeamError> {
        while self.epoch_complete(self.epoch) {
            self.assimilate_epoch(self.epoch)?;
            self.readmit()?;
        }
        Ok(())
    }

    /// Re-fit from the clean steps of each boat its tests re-admitted since the last call, with
    /// the boat pinned `ok` over them: a sensor that reads true again owes the model nothing
    /// (the model is then the one a fleet whose sensor never failed makes of the same values).
    fn readmit(&mut self) -> Result<(), TeamError> {
        while let Some(step) = self.readmit_from.take() {
            self.stale_from = self.stale_from.min(self.schedule.epoch_of_step(step as usize));
            self.refit()?;
            self.counters.readmissions += 1;
        }
        Ok(())
    }

    /// The verdicts decided outside the tests at step `k`: re-admissions, then the operator's.
    fn pins_at(&self, k: u64) -> BTreeMap<usize, Pin> {
        let mut pins = BTreeMap::new();
        for (&v, r) in &self.readmissions {
            if r.range(..=k).next_back().is_some_and(|(_, &until)| k <= until) {
                let reason = format!("reads true again ({CLEAN_STEPS} clean steps)");
                pins.insert(
                    v,
                    Pin {
                        health: Health::Ok,
                        reason,
                    },
                );
            }
        }
        for (&v, o) in &self.overrides {
            if let Some((_, Some(health))) = o.range(..=k).next_back() {
                let reason = match health {
                    Health::Ok => "trusted by the operator",
                    _ => "excluded by the operator",
                };
                pins.insert(
                    v,
                    Pin {
                        health: *health,
                        reason: reason.into(),
                    },
                );
            }
        }
        pins
    }

    /// The operator's verdict on `vehicle`'s sensor from step `from_step` on (`None`: the tests
    /// decide again). Journalled ([`Self::take_journal_records`]); a step already in the model
    /// re-fits it from there at the next [`Self::settle`]. Refused (with why) for a vehicle not
    /// in the mission, a step past its end, or `suspect` (a sensor is trusted or not).
    pub fn override_sensor(&mut self, o: &protocol::SensorOverride) -> Result<(), String> {
        let v = self
            .vehicles
            .index_of(&o.vehicle)
            .ok_or_else(|| format!("{} is not a vehicle of the mission", o.vehicle))?;
        if o.from_step as usize >= self.schedule.frames {
            return Err(format!(
                "step {} is past the mission's end ({} steps)",
                o.from_step, self.schedule.frames
            ));
        }
        if o.set == Some(Health::Suspect) {
            return Err("an operator sets a sensor ok or excluded, or hands it back to the tests".into());
        }
        self.overrides.entry(v).or_default().insert(o.from_step, o.set);
        self.unjournalled_overrides.insert((v, o.from_step));
        self.counters.overrides += 1;
        let e = self.schedule.epoch_of_step(o.from_step as usize);
        if e < self.epoch {
            self.stale = true;
            self.stale_from = self.stale_from.min(e);
        }
        Ok(())
    }

    /// Rebuild the model with every batch now in, from the newest checkpoint at or before the
    /// earliest late epoch (the model of the epochs before it is the same: their batches did
    /// not change), or from the start without one. Plans already handed out stay as history;
    /// the next epoch's plan is the re-fitted model's. The replay sees the plans handed out
    /// until it makes its own (the first epoch it replays judges its silent boats by them).
    fn refit(&mut self) -> Result<(), TeamError> {
        // The epochs made again are not news: none of their models goes out (the model after
        // the re-fit is published as any asked for).
        let publisher = self.publisher.take();
        let refitted = self.refit_quietly();
        self.publisher = publisher;
        refitted
    }

    fn refit_quietly(&mut self) -> Result<(), TeamError> {
        let upto = self.epoch;
        let version = self.version;
        let history = self.plans.clone();
        let unjournalled = std::mem::take(&mut self.unjournalled);
        let from = std::mem::replace(&mut self.stale_from, u64::MAX);
        let start = self.checkpoints.as_mut().and_then(|c| {
            // Checkpoints after the late epoch describe a model without its batch: gone.
            c.retain(|&e, _| e <= from);
            c.range(..=from).next_back().map(|(&e, _)| e)
        });
        match start {
            Some(e) => {
                let (cp, steps) = &self.checkpoints.as_ref().expect("checkpoints on")[&e];
                self.assim.rewind(cp)?;
                self.history.truncate(*steps).map_err(history_error)?;
                self.aerial_estimates.truncate(*steps);
                self.epoch = e;
            }
            None => {
                let speed = self.assim.boat_speed();
                self.assim = Assimilator::new(&self.cfg, *self.assim.grid(), self.schedule.frames)?;
                self.assim.set_boat_speed(speed);
                self.history.truncate(0).map_err(history_error)?;
                self.aerial_estimates.clear();
                self.epoch = 0;
            }
        }
        self.counters.refit_epochs += upto - self.epoch;
        while self.epoch < upto {
            self.assimilate_epoch(self.epoch)?;
        }
        let next = self.plans.remove(&upto);
        self.plans = history;
        self.unjournalled = unjournalled;
        if let Some(p) = next {
            self.plans.insert(upto, p);
        }
        self.version = version + 1;
        Ok(())
    }

    /// Write every step's fused estimate and variance to `dir`'s `estimate.npy` and
    /// `variance.npy` as they are made, instead of holding them in memory (the model server's
    /// memory then does not grow with the mission). Before the first step only.
    pub fn with_history_in(mut self, dir: &std::path::Path) -> Result<Self, TeamError> {
        if !self.history.is_empty() {
            return Err(TeamError::Config(
                "the history moves to files before the first step only".into(),
            ));
        }
        let grid = *self.assim.grid();
        self.history = History::in_files(dir, grid.rows, grid.cols, self.assim.land())
            .map_err(|e| TeamError::History(format!("{}: {e}", dir.display())))?;
        Ok(self)
    }

    /// The fused estimate and its reported variance at every step assimilated so far.
    pub fn history(&self) -> &History {
        &self.history
    }

    /// Keep the aerial estimate of every step in [`Self::aerial_estimates`].
    pub fn with_aerial_history(mut self) -> Self {
        self.keep_aerial_estimates = true;
        self
    }

    /// Keep each boat test's information on an offset ([`crate::health::Screen::information`]):
    /// for the fault study.
    pub fn with_screen_information(mut self) -> Self {
        self.assim.screen().keep_information();
        self
    }

    /// Turn the checkpoints off (every re-fit then starts from epoch 0): for benchmarks.
    pub fn without_checkpoints(mut self) -> Self {
        self.checkpoints = None;
        self
    }

    /// Whether the planner may allocate a vehicle (from its telemetry); takes effect at the next
    /// allocation. Returns whether it changed.
    pub fn set_available(&mut self, vehicle: &VehicleId, available: bool) -> bool {
        let Some(index) = self.vehicles.index_of(vehicle) else {
            return false;
        };
        if available {
            self.held.remove(&index)
        } else {
            self.held.insert(index)
        }
    }

    /// Vehicles left out of the next allocation.
    pub fn held(&self) -> Vec<VehicleId> {
        self.held.iter().map(|&i| self.vehicles.at(i).id.clone()).collect()
    }

    /// Vehicles left out of epoch `e`'s allocation.
    pub fn held_at(&self, e: u64) -> Vec<VehicleId> {
        self.holds.get(&e).map_or_else(Vec::new, |h| {
            h.iter().map(|&i| self.vehicles.at(i).id.clone()).collect()
        })
    }

    fn reject(&mut self, vehicle: &VehicleId, why: String) -> IngestError {
        *self.counters.rejected.entry("invalid_batch".into()).or_default() += 1;
        IngestError::Rejected {
            vehicle: vehicle.clone(),
            why,
        }
    }

    /// Take one batch (already decoded and validated against the grid).
    pub fn ingest(&mut self, batch: MeasurementBatch) -> Result<Ingested, IngestError> {
        let taken = self.ingest_deferred(batch)?;
        self.settle()?;
        Ok(taken)
    }

    /// Re-fit with the late batches [`Self::ingest_deferred`] took, if any (then assimilate
    /// every epoch that is complete). Returns whether it re-fitted.
    pub fn settle(&mut self) -> Result<bool, TeamError> {
        if !self.stale {
            return Ok(false);
        }
        // Re-admissions found after the late epoch's start were found without its batches.
        let first = self.steps_of(self.stale_from.min(self.epoch)).start as u64;
        self.readmissions
            .values_mut()
            .for_each(|r| r.retain(|_, until| *until < first));
        self.refit()?;
        self.counters.refits += 1;
        self.stale = false;
        self.readmit()?;
        self.assimilate_complete()?;
        Ok(true)
    }

    /// [`Self::ingest`] without the re-fit a late batch needs: a boat's backlog arrives as a
    /// burst of late batches, and one [`Self::settle`] after the burst re-fits once instead of
    /// once per batch. Until `settle`, the model and plans do not yet include the late batches
    /// (a batch that completes the next epoch settles first).
    pub fn ingest_deferred(&mut self, batch: MeasurementBatch) -> Result<Ingested, IngestError> {
        self.counters.batches += 1;
        let (index, e) = match self.check(&batch) {
            Ok(Some(found)) => found,
            Ok(None) => {
                self.counters.duplicates += 1;
                return Ok(Ingested::Duplicate);
            }
            Err(BatchFault::Unknown) => {
                *self.counters.rejected.entry("unknown_vehicle".into()).or_default() += 1;
                return Err(protocol::ProtocolError::UnknownVehicle(batch.vehicle.to_string()).into());
            }
            Err(BatchFault::Invalid(why)) => return Err(self.reject(&batch.vehicle, why)),
        };
        self.received.entry(e).or_default().insert(index, batch);
        if e < self.epoch {
            self.stale = true;
            self.stale_from = self.stale_from.min(e);
            return Ok(Ingested::Refitted(e));
        }
        let before = self.epoch;
        // An epoch completed on top of a model still missing late batches: re-fit first.
        if self.stale && self.epoch_complete(before) {
            self.settle()?;
        } else {
            self.assimilate_complete()?;
        }
        Ok(if self.epoch == before {
            Ingested::Buffered
        } else {
            Ingested::Assimilated((before..self.epoch).collect())
        })
    }

    /// Where a batch belongs (its vehicle's index and its epoch), `None` for a duplicate, or
    /// why it is refused. What decides it is the mission alone (the schedule, and epoch 0's
    /// formation), never the server's later decisions, so a restarted server accepts exactly
    /// what the live one did. An empty batch is a vehicle reporting that it sensed nothing
    /// (left out of the allocation, a boat without a disk, an aerial whose region has no
    /// lattice cell, a vehicle that followed an older plan's horizon): always accepted, except
    /// an aerial's at epoch 0 when the formation gave it cells (the first model needs the whole
    /// lattice).
    fn check(&self, batch: &MeasurementBatch) -> Result<Option<(usize, u64)>, BatchFault> {
        let index = self.vehicles.index_of(&batch.vehicle).ok_or(BatchFault::Unknown)?;
        if self.vehicles.at(index).kind != batch.kind {
            return Err(BatchFault::Invalid(format!(
                "declared {:?}, registered {:?}",
                batch.kind,
                self.vehicles.at(index).kind
            )));
        }
        let e = Schedule::epoch_of(batch.kind, batch.seq);
        if self.received.get(&e).is_some_and(|m| m.contains_key(&index)) {
            return Ok(None);
        }
        if self.steps_of(e).is_empty() {
            return Err(BatchFault::Invalid(format!(
                "seq {} is past the end of the mission",
                batch.seq
            )));
        }
        let want = self.schedule.sample_steps(batch.kind, e);
        let got: Vec<usize> = batch.samples.iter().map(|s| s.step as usize).collect();
        let idle_allowed = e > 0
            || self
                .plan(&batch.vehicle, 0, 1)
                .is_some_and(|p| p.targets.iter().all(|t| t.cells.is_empty()));
        if got != want && !(got.is_empty() && idle_allowed) && !self.instrument_steps(batch, e) {
            return Err(BatchFault::Invalid(format!(
                "epoch {e} wants samples at steps {want:?}, got {got:?}"
            )));
        }
        Ok(Some((index, e)))
    }

    /// Whether `batch` is an instrument's readings for epoch `e`: each sample with its own
    /// sigma, in increasing order of step; a boat's at any steps of the epoch (a reading counts
    /// in the step of its time, [`crate::instrument`]), an aerial camera's at those of its
    /// sampling steps it has a frame for.
    fn instrument_steps(&self, batch: &MeasurementBatch, e: u64) -> bool {
        let (steps, want) = (self.steps_of(e), self.schedule.sample_steps(batch.kind, e));
        let allowed = |k: usize| match batch.kind {
            VehicleKind::Boat => steps.contains(&k),
            VehicleKind::Aerial => want.contains(&k),
        };
        !batch.samples.is_empty()
            && batch
                .samples
                .iter()
                .all(|s| s.sigma.is_some() && allowed(s.step as usize))
            && batch.samples.windows(2).all(|w| w[0].step < w[1].step)
    }

    /// The records of the epochs whose decisions changed since the last call, as the journal's
    /// metadata (key, CBOR): the node commits them with the batch that caused them, before any
    /// plan of those epochs is handed out.
    pub fn take_journal_records(&mut self) -> Vec<(String, Vec<u8>)> {
        let overrides = std::mem::take(&mut self.unjournalled_overrides)
            .into_iter()
            .map(|(v, step)| {
                let o = protocol::SensorOverride {
                    vehicle: self.vehicles.at(v).id.clone(),
                    from_step: step,
                    set: self.overrides[&v][&step],
                };
                let mut bytes = vec![];
                ciborium::into_writer(&o, &mut bytes).expect("a record serialises");
                (format!("{OVERRIDE_PREFIX}{}/{step:010}", o.vehicle), bytes)
            });
        let overrides: Vec<(String, Vec<u8>)> = overrides.collect();
        std::mem::take(&mut self.unjournalled)
            .into_iter()
            .map(|e| {
                let held = self.holds.get(&e).map_or_else(Vec::new, |h| {
                    h.iter().map(|&i| self.vehicles.at(i).id.clone()).collect()
                });
                let mut bytes = vec![];
                ciborium::into_writer(
                    &EpochRecord {
                        held,
                        forced: self.forced.contains(&e),
                    },
                    &mut bytes,
                )
                .expect("a record serialises");
                (EpochRecord::key(e), bytes)
            })
            .chain(overrides)
            .collect()
    }

    /// A restarted server's state from its journal: the batches it had accepted (any order) and
    /// its epoch records. Every epoch that was complete or forced is assimilated again, in step
    /// order, with the holds it was allocated under; the held set goes on as the newest
    /// epoch's. Returns how many batches.
    pub fn restore(
        &mut self,
        batches: Vec<MeasurementBatch>,
        records: &[(String, Vec<u8>)],
    ) -> Result<u64, RestoreError> {
        for (key, bytes) in records {
            let bad = |why: String| RestoreError::Record { key: key.clone(), why };
            if key.starts_with(OVERRIDE_PREFIX) {
                let o: protocol::SensorOverride = ciborium::from_reader(&bytes[..]).map_err(|e| bad(e.to_string()))?;
                self.override_sensor(&o).map_err(bad)?;
                continue;
            }
            let e: u64 = key
                .strip_prefix(EpochRecord::PREFIX)
                .and_then(|n| n.parse().ok())
                .ok_or_else(|| bad("not an epoch record".into()))?;
            let r: EpochRecord = ciborium::from_reader(&bytes[..]).map_err(|err| bad(err.to_string()))?;
            let mut held = BTreeSet::new();
            for id in r.held {
                let i = self
                    .vehicles
                    .index_of(&id)
                    .ok_or_else(|| RestoreError::UnknownVehicle {
                        key: key.clone(),
                        vehicle: id.to_string(),
                    })?;
                held.insert(i);
            }
            self.holds.insert(e, held);
            if r.forced {
                self.forced.insert(e);
            }
        }
        let n = batches.len() as u64;
        for b in batches {
            let (vehicle, seq) = (b.vehicle.clone(), b.seq);
            let why = |why: String| RestoreError::Batch {
                vehicle: vehicle.clone(),
                seq,
                why,
            };
            match self.check(&b) {
                Ok(Some((index, e))) => {
                    self.received.entry(e).or_default().insert(index, b);
                }
                Ok(None) => return Err(why("twice in the journal".into())),
                Err(BatchFault::Unknown) => return Err(why("not a vehicle of the mission".into())),
                Err(BatchFault::Invalid(w)) => return Err(why(w)),
            }
        }
        self.counters.batches += n;
        self.counters.restored = n;
        while self.epoch_complete(self.epoch)
            || (self.epoch > 0 && self.forced.contains(&self.epoch) && !self.steps_of(self.epoch).is_empty())
        {
            if !self.epoch_complete(self.epoch) {
                self.counters.forced += 1;
            }
            self.assimilate_epoch(self.epoch)?;
            self.readmit()?;
        }
        self.held = self.holds.get(&self.epoch).cloned().unwrap_or_default();
        self.unjournalled.clear();
        self.unjournalled_overrides.clear();
        (self.stale, self.stale_from) = (false, u64::MAX);
        Ok(n)
    }

    /// Aerials take part in every epoch; boats in every full epoch after the first (a last,
    /// shorter epoch has no boat step).
    fn takes_part(&self, index: usize, e: u64) -> bool {
        !self.schedule.sample_steps(self.vehicles.at(index).kind, e).is_empty()
    }

    fn epoch_complete(&self, e: u64) -> bool {
        if self.steps_of(e).is_empty() {
            return false;
        }
        self.missing(e).next().is_none()
    }

    /// Samples of every vehicle of a kind at step `k`, in vehicle order.
    fn samples_at(batches: &BTreeMap<usize, MeasurementBatch>, kind: VehicleKind, k: usize) -> Vec<Sample> {
        Self::tagged_at(batches, kind, k).into_iter().map(|(_, s)| s).collect()
    }

    /// [`Self::samples_at`] with each sample's vehicle index (for the health tests).
    fn tagged_at(batches: &BTreeMap<usize, MeasurementBatch>, kind: VehicleKind, k: usize) -> Vec<Tagged> {
        batches
            .iter()
            .filter(|(_, b)| b.kind == kind)
            .flat_map(|(&v, b)| {
                b.samples
                    .iter()
                    .filter(|s| s.step as usize == k)
                    .map(move |s| (v, s.clone()))
            })
            .collect()
    }

    /// Step `k`'s aerial readings tested ([`crate::health`]), with the verdicts decided outside
    /// the tests pinned: the samples the step's aerial sight is made of.
    fn screened_aerials(&mut self, batches: &BTreeMap<usize, MeasurementBatch>, k: usize, ahead: u64) -> Vec<Sample> {
        let _span = tracing::info_span!("screen").entered();
        let pins = self.pins_at(k as u64);
        self.assim.screen().pin(pins);
        let silent = self.silent_sensors(batches, k);
        self.assim.screen_silent(k as u64, &silent);
        let aerials = Self::tagged_at(batches, VehicleKind::Aerial, k);
        self.assim.screen_aerials(k as u64, ahead, aerials)
    }

    /// Step `k`'s boat readings tested against what the fleet knows of the step without them
    /// (the aerials' sight of it, and the filter): the samples the fusion may use. Notes the
    /// step's verdicts that changed, the aerials' with them, and the re-admissions.
    fn screened_boats(
        &mut self,
        batches: &BTreeMap<usize, MeasurementBatch>,
        k: usize,
        ahead: u64,
        aerial: &crate::AerialSight,
    ) -> Result<Vec<Sample>, TeamError> {
        let _span = tracing::info_span!("screen").entered();
        let boats = Self::tagged_at(batches, VehicleKind::Boat, k);
        let boats = self.assim.screen_boats(k as u64, ahead, boats, aerial)?;
        for (v, since) in self.assim.screen().take_readmissions() {
            self.readmissions.entry(v).or_default().insert(since, k as u64);
            self.readmit_from = Some(self.readmit_from.map_or(since, |r| r.min(since)));
        }
        let verdicts = self.assim.screen().take_verdicts();
        match verdicts.is_empty() {
            true => self.verdicts.remove(&k),
            false => self.verdicts.insert(k, verdicts),
        };
        Ok(boats)
    }

    /// Step `k`'s filter step, and beside it, on the other core, `job`: the aerial sight of
    /// the next step (it reads the mission's settings and its own samples only, and the
    /// filter's step takes about three times as long: 9 against 3 ms at 192 x 384).
    fn fuse_beside<T: Send>(
        &mut self,
        ahead: u64,
        aerial: &crate::AerialSight,
        boats: &[Sample],
        job: Option<impl FnOnce() -> T + Send>,
    ) -> (Result<crate::fusion::Estimate, TeamError>, Option<T>) {
        let assim = &mut self.assim;
        crate::side_by_side::beside(
            || tracing::info_span!("fuse").in_scope(|| assim.fuse_step(ahead, aerial, boats)),
            || Some(job?()),
        )
    }

    /// The vehicles sent to sense (a boat's disk, an aerial's region; not held) that said
    /// nothing: at an epoch's first boat step `k`, the boats whose batch holds no reading at all
    /// (a boat's instrument may report at any step of its epoch); at a frame step `k`, the
    /// aerials whose batch holds no reading of it (a frame is of its step, and a camera dark
    /// from mid-epoch is then covered from the next epoch, not the one after: +393% -> +87% on
    /// the 500 hPa height). A batch not yet in is not silence (a vehicle out of range sends its
    /// backlog later).
    fn silent_sensors(&self, batches: &BTreeMap<usize, MeasurementBatch>, k: usize) -> Vec<usize> {
        let e = self.schedule.epoch_of_step(k);
        let first_boat = self.schedule.sample_steps(VehicleKind::Boat, e).first() == Some(&k);
        let frame = self.schedule.sample_steps(VehicleKind::Aerial, e).contains(&k);
        // Borrowed, not `allocation`'s copy (its disks' cells); epoch 0 has no plan.
        let Some(alloc) = self.plans.get(&e).filter(|_| first_boat || frame) else {
            return vec![];
        };
        let disk = |slot: usize| alloc.boats[slot].as_ref().is_some_and(|(cells, _)| !cells.is_empty());
        let boats = (0..alloc.boats.len())
            .filter(|&slot| first_boat && disk(slot))
            .map(|slot| self.vehicles.boat_index(slot));
        let stride = self.cfg.aerial_stride;
        let region = |a: usize| {
            alloc
                .aerial_region(self.assim.grid(), stride, a)
                .is_some_and(|r| !r.is_empty())
        };
        let aerials = (0..alloc.aerials.len()).filter(|&a| frame && region(a));
        let is_boat = |v: usize| v >= alloc.aerials.len();
        let said_nothing = |v: &usize| {
            batches.get(v).is_some_and(|b| {
                b.samples
                    .iter()
                    .filter(|s| is_boat(*v) || s.step as usize == k)
                    .all(|s| s.cells.is_empty())
            })
        };
        aerials
            .chain(boats)
            .filter(|v| !alloc.held.contains(v))
            .filter(said_nothing)
            .collect()
    }

    /// Every [`CHECKPOINT_EVERY`] epochs, the assimilator's state before epoch `e` (what a
    /// re-fit from there starts from), thinned as [`keep_checkpoint`] says.
    fn checkpoint_at(&mut self, e: u64) {
        if e > 0 && e.is_multiple_of(CHECKPOINT_EVERY) {
            let steps = self.history.len();
            if let Some(c) = self.checkpoints.as_mut() {
                let at = tracing::info_span!("checkpoint").in_scope(|| self.assim.checkpoint());
                c.insert(e, (at, steps));
                c.retain(|&at, _| keep_checkpoint(at, e));
            }
        }
    }

    fn assimilate_epoch(&mut self, e: u64) -> Result<(), TeamError> {
        // The model published for the last epoch is stale from here on, and it holds the model
        // it was made of (its modes made only when a get asks): dropped before the refit makes
        // the new one, so the two are never in memory together (the server's peak).
        self.published = None;
        self.checkpoint_at(e);
        let batches = self.received.get(&e).cloned().unwrap_or_default();
        let steps = self.steps_of(e);
        match e {
            0 => self.assimilate_first(&batches, steps)?,
            _ => self.assimilate_steps(e, &batches, steps)?,
        }
        self.epoch = e + 1;
        self.version += 1;
        self.counters.epochs = self.epoch;
        if !self.all_assimilated() {
            if !self.holds.contains_key(&self.epoch) {
                self.holds.insert(self.epoch, self.held.clone());
                self.unjournalled.insert(self.epoch);
            }
            let plan = self.place_and_publish()?;
            self.plans.insert(self.epoch, plan);
        }
        Ok(())
    }

    /// Epoch 0: the aerials' estimates of its steps fit the first model.
    fn assimilate_first(
        &mut self,
        batches: &BTreeMap<usize, MeasurementBatch>,
        steps: std::ops::Range<usize>,
    ) -> Result<(), TeamError> {
        let mut init = vec![];
        for k in steps {
            let est = self
                .assim
                .aerial_estimate(&Self::samples_at(batches, VehicleKind::Aerial, k))?;
            if self.keep_aerial_estimates {
                self.aerial_estimates.push(est.estimate.values.clone());
            }
            let values = est.estimate.values;
            self.history
                .push(values.clone(), est.estimate.variance)
                .map_err(history_error)?;
            init.push(values);
        }
        self.assim.initialise(init)?;
        Ok(())
    }

    /// A later epoch `e`: each step's readings screened and fused, the next step's aerial
    /// sight made beside each filter step, then the model updated with the fused steps. The
    /// update's first part needs only the steps before the last
    /// ([`crate::assimilator::Assimilator::update_ahead`]), so it is made beside the whole of
    /// the last step, on the other core, idle there (the update's projections, `H`'s factor and
    /// the new `U`: 12 of its 15 ms at 192 x 384); the last step's snapshot is then all the
    /// update waits for.
    fn assimilate_steps(
        &mut self,
        e: u64,
        batches: &BTreeMap<usize, MeasurementBatch>,
        steps: std::ops::Range<usize>,
    ) -> Result<(), TeamError> {
        let (k0, end) = (steps.start, steps.end);
        let (mut learn, mut next, mut prepared) = (vec![], None, None);
        for k in steps {
            let (learned, sight) = match k + 1 < end {
                true => self.step_fused(batches, k, k0..end, next.take())?,
                false => {
                    let job = self.assim.update_ahead(&learn);
                    let (done, ahead) = crate::side_by_side::beside(
                        || self.step_fused(batches, k, k0..end, next.take()),
                        || job.map(|j| tracing::info_span!("dmd update ahead").in_scope(|| j.run())),
                    );
                    if let Some((model, made)) = ahead {
                        self.assim.model_back(model);
                        prepared = made;
                    }
                    done?
                }
            };
            next = sight;
            learn.push(learned);
        }
        if let Some(skill) = self.assim.take_skill(e) {
            self.skills.insert(e, skill);
        }
        tracing::info_span!("model update").in_scope(|| self.assim.assimilate_prepared(learn, prepared))?;
        Ok(())
    }

    /// Step `k` of the epoch's `steps`: its readings screened and fused (with `sight`, its
    /// aerial sight when made ahead), the fused step written; what the model learns of it, and
    /// the next step's aerial sight, made beside the filter step.
    fn step_fused(
        &mut self,
        batches: &BTreeMap<usize, MeasurementBatch>,
        k: usize,
        steps: std::ops::Range<usize>,
        sight: Option<Sight>,
    ) -> Result<(Vec<f64>, Option<Sight>), TeamError> {
        let ahead = (k + 1 - steps.start) as u64;
        let sight = match sight {
            Some(sight) => sight,
            None => {
                let samples = self.screened_aerials(batches, k, ahead);
                tracing::info_span!("aerial estimate").in_scope(self.assim.aerial_sight_later(samples))
            }
        };
        let aerial = self.assim.hold_aerial(sight?)?;
        let boats = self.screened_boats(batches, k, ahead, &aerial)?;
        if self.keep_aerial_estimates {
            self.aerial_estimates.push(aerial.estimate.values.clone());
        }
        let (boats, held) = crate::holdout::split(boats, self.holdout_share, self.cfg.boat_sigma);
        let later = (k + 1 < steps.end).then(|| {
            let samples = self.screened_aerials(batches, k + 1, ahead + 1);
            let later = self.assim.aerial_sight_later(samples);
            move || tracing::info_span!("aerial estimate").in_scope(later)
        });
        let (fused, next) = self.fuse_beside(ahead, &aerial, &boats, later);
        let fused = fused?;
        if let Some(i) = self.assim.take_innovation() {
            self.innovations.insert(k, i);
        }
        if self.holdout_share > 0.0 {
            let scored = held
                .into_iter()
                .map(|(cell, value, noise_var)| crate::holdout::HeldOut {
                    cell,
                    value,
                    noise_var,
                    predicted: fused.values[cell],
                    variance: fused.variance[cell],
                });
            self.held_out.insert(k, scored.collect());
        }
        let learned = match self.cfg.learn_from {
            LearnFrom::Posterior => fused.values.clone(),
            LearnFrom::Aerial => aerial.estimate.values,
        };
        tracing::info_span!("history written")
            .in_scope(|| self.history.push(fused.values, fused.variance))
            .map_err(history_error)?;
        Ok((learned, next))
    }

    /// The allocation vehicles sense epoch `e` under (`None` before it is computed). Epoch 0
    /// is the uniform formation.
    pub fn allocation(&self, e: u64) -> Option<Allocation> {
        if e == 0 {
            return Some(Allocation {
                boats: vec![None; self.cfg.boats],
                aerials: self.assim.aerial_positions().to_vec(),
                held: BTreeSet::new(),
                doubted: BTreeSet::new(),
            });
        }
        self.plans.get(&e).cloned()
    }

    /// Send the boats somewhere else in epoch `e` (planned, not yet assimilated): `boats[slot]`
    /// is a disk's cells and centre `(row, col)`, or `None` for a boat that stays and senses
    /// nothing. The vehicles' plans for `e` follow. For offline experiments that place the
    /// boats themselves (the oracle of `fleet experiment`): a re-fit from an earlier epoch
    /// (a late batch) re-plans `e` and forgets this.
    pub fn redirect_boats(
        &mut self,
        e: u64,
        boats: Vec<Option<crate::assimilator::BoatDisk>>,
    ) -> Result<(), TeamError> {
        let grid = *self.assim.grid();
        if boats.len() != self.cfg.boats {
            return Err(TeamError::Config(format!(
                "redirect_boats: {} disks for {} boats",
                boats.len(),
                self.cfg.boats
            )));
        }
        if let Some((_, (r, c))) = boats.iter().flatten().find(|(cells, (r, c))| {
            cells.iter().any(|&i| i >= grid.len()) || !grid.contains(crate::grid::Cell::new(*r, *c))
        }) {
            return Err(TeamError::Config(format!(
                "redirect_boats: the disk at ({r}, {c}) leaves the {} x {} grid",
                grid.rows, grid.cols
            )));
        }
        if e < self.epoch || e == 0 {
            return Err(TeamError::Config(format!(
                "redirect_boats: epoch {e} is not planned and open (next to assimilate: {})",
                self.epoch
            )));
        }
        let plan = self
            .plans
            .get_mut(&e)
            .ok_or_else(|| TeamError::Config(format!("redirect_boats: epoch {e} has no plan yet")))?;
        for (slot, b) in boats.iter().enumerate() {
            if let Some((_, (r, c))) = b {
                self.assim
                    .set_boat_position(slot, grid.centre_m(crate::grid::Cell::new(*r, *c)));
            }
        }
        plan.boats = boats;
        Ok(())
    }

    /// The plan of one vehicle from epoch `e` on: where to be and what to sense at each of
    /// its sampling steps of epochs `e .. e + horizon`, all under epoch `e`'s allocation (the
    /// model's spatial modes, and so the disks, stay until the next update; a vehicle cut off
    /// from the server keeps following the later targets).
    pub fn plan(&self, vehicle: &VehicleId, e: u64, horizon: u64) -> Option<Plan> {
        let &VehicleSpec { index, kind, slot, .. } = self.vehicles.get(vehicle)?;
        let alloc = self.allocation(e)?;
        let grid = self.assim.grid();
        let (position, radius, cells) = match kind {
            // Left out: stays where it is, senses nothing.
            VehicleKind::Aerial if alloc.held.contains(&index) => (alloc.aerials[index], 0.0, vec![]),
            VehicleKind::Boat if alloc.held.contains(&index) => (self.assim.boat_positions()[slot], 0.0, vec![]),
            VehicleKind::Aerial => {
                let region = alloc.aerial_region(grid, self.cfg.aerial_stride, index)?;
                (alloc.aerials[index], 0.0, region)
            }
            VehicleKind::Boat => match &alloc.boats[slot] {
                Some((cells, (r, c))) => (
                    grid.centre_m(crate::grid::Cell::new(*r, *c)),
                    self.cfg.radius,
                    cells.clone(),
                ),
                None => (self.assim.boat_positions()[slot], 0.0, vec![]),
            },
        };
        let cells: Vec<u32> = cells.into_iter().map(|c| c as u32).collect();
        let targets = (e..e.saturating_add(horizon.max(1)))
            .flat_map(|ep| self.schedule.sample_steps(kind, ep).into_iter().map(move |k| (ep, k)))
            .map(|(ep, k)| Target {
                epoch: ep,
                step: k as u64,
                position: [position.0, position.1],
                radius,
                cells: cells.clone(),
            })
            .collect();
        Some(Plan {
            vehicle: vehicle.clone(),
            model_version: self.version,
            epoch: e,
            targets,
        })
    }

    /// The seqs `0..=through` of `vehicle` this server does not hold (empty for an unknown
    /// vehicle). A vehicle has dropped every batch the server acknowledged, so after a restart
    /// any of them missing means the journal lost data.
    pub fn lacks_through(&self, vehicle: &VehicleId, through: u64) -> Vec<u64> {
        let Some(index) = self.vehicles.index_of(vehicle) else {
            return vec![];
        };
        let kind = self.vehicles.at(index).kind;
        (0..self.schedule.epochs())
            .filter_map(|e| self.schedule.seq_of(kind, e).map(|s| (e, s)))
            .take_while(|&(_, s)| s <= through)
            .filter(|(e, _)| !self.received.get(e).is_some_and(|m| m.contains_key(&index)))
            .map(|(_, s)| s)
            .collect()
    }

    /// A fingerprint of what the journal's batches mean: the team, the grid and the mission's
    /// length. A journal written under another one is refused, not replayed.
    pub fn fingerprint(&self) -> String {
        let g = self.assim.grid();
        format!(
            "{} grid {}x{} frames {}",
            serde_json::to_string(&self.cfg).expect("the team serialises"),
            g.rows,
            g.cols,
            self.schedule.frames
        )
    }

    /// The ack of a vehicle: the highest seq up to which all of its batches are here (`None`
    /// before its first).
    pub fn ack(&self, vehicle: &VehicleId) -> Option<Ack> {
        let index = self.vehicles.index_of(vehicle)?;
        let kind = self.vehicles.at(index).kind;
        let mut seq = None;
        // Every batch taken is in the journal (the node journals before it acknowledges), so the
        // vehicle may drop it once it is here, assimilated or not: a boat whose epoch waits for
        // a slower one does not send its batch again and again over the radio meanwhile.
        for e in 0..self.schedule.epochs() {
            let Some(s) = self.schedule.seq_of(kind, e) else {
                continue;
            };
            if !self.received.get(&e).is_some_and(|m| m.contains_key(&index)) {
                break;
            }
            seq = Some(s);
        }
        let sensor =
            (self.assim.screen_state().doubted(index)).map(|(state, reason)| protocol::SensorHealth { state, reason });
        Some(Ack {
            vehicle: vehicle.clone(),
            seq: seq?,
            sensor,
        })
    }

    /// The model as published on `model/latest` (`None` before the first fit), with the
    /// newest estimate's reported variance per cell and the forecast's to the next boat step.
    pub fn model_update(&self) -> Option<ModelUpdate> {
        Some(self.model_parts()?.assemble(self.history.last()))
    }

    /// What the published model is made of (`None` before the first fit).
    fn model_parts(&self) -> Option<ModelParts> {
        let shell = ModelUpdate {
            version: self.version,
            epoch: self.epoch.saturating_sub(1),
            step: self.history.len().saturating_sub(1) as u64,
            grid: *self.assim.grid(),
            dt: 0.0,
            eigenvalues: vec![],
            modes_re: vec![],
            modes_im: vec![],
            amplitudes: vec![],
            estimate: vec![],
            variance: vec![],
            forecast_steps: self.cfg.boat_period as u64,
            forecast_variance: vec![],
            land: self.assim.land().iter().map(|&c| c as u32).collect(),
            level: self.assim.field_level(),
        };
        Some(ModelParts {
            shell,
            model: self.assim.model_shared()?,
            forecast_variance: Box::new(self.assim.forecast_variance_later(self.cfg.boat_period as u64)),
            prior_variance: self.assim.prediction_variance(),
        })
    }

    fn made(&self) -> Made {
        Made {
            version: self.version,
            next_epoch: self.epoch,
            steps: self.history.len(),
        }
    }

    /// The model as published on `model/latest` and its encoding, taken out to send: the one
    /// made beside the epoch's placement, or made now if the model changed since (`None` before
    /// the first fit). Give it back with [`Self::keep_published`] for the next reader.
    pub fn take_published(&mut self) -> Option<Published> {
        let made = self.made();
        // A stale one is dropped here, its memory (54 MB at 384 x 768) freed before the new one.
        if let Some(p) = self.published.take().filter(|p| p.of == made) {
            return Some(p);
        }
        self.model_update().map(|m| Published::of(m, made))
    }

    pub fn keep_published(&mut self, p: Published) {
        self.published = Some(p);
    }

    /// The published model made for the model as it is now, if one was (a reader that cannot
    /// wait for one to be made uses [`Self::model_update`]).
    pub fn published(&self) -> Option<&Published> {
        self.published.as_ref().filter(|p| p.of == self.made())
    }

    /// The next epoch's allocation, and beside it (on the other core) the model to publish:
    /// neither needs the other, and the placement leaves the model as it is.
    ///
    /// The model goes to the publisher as soon as it is made, unless a re-admission's re-fit
    /// follows (that one publishes the model it makes).
    fn place_and_publish(&mut self) -> Result<Allocation, TeamError> {
        let holds = self.holds[&self.epoch].clone();
        let (parts, made) = (self.model_parts(), self.made());
        self.published = None;
        let publisher = self.publisher.clone().filter(|_| self.readmit_from.is_none());
        let (assim, history) = (&mut self.assim, &self.history);
        let (plan, published) = crate::side_by_side::beside(
            || tracing::info_span!("placement").in_scope(|| assim.allocate_without(&holds)),
            || {
                let mut p = Published::of_lean(parts?.assemble_lean(history.last()), made);
                if let Some(publish) = &publisher {
                    publish(&p);
                    p.handed_out = Some(std::time::Instant::now());
                }
                Some(p)
            },
        );
        self.published = published;
        plan
    }

    /// Hand every epoch's model to `publisher` the moment it is made ([`Publisher`]).
    pub fn with_publisher(mut self, publisher: Publisher) -> Self {
        self.publisher = Some(publisher);
        self
    }

    /// Hold `share` of the boats' readings out of the fusion and score the estimate on them
    /// ([`crate::holdout`]): how a run without a truth is measured.
    pub fn with_holdout(mut self, share: f64) -> Self {
        self.holdout_share = share;
        self
    }

    /// The hold-out's figures so far (`None`: nothing held out).
    pub fn holdout(&self) -> Option<crate::protocol::HoldoutScore> {
        crate::holdout::score(self.held_out.values().flatten())
    }

    /// Every change of a sensor's verdict, in step order.
    pub fn verdicts(&self) -> Vec<Verdict> {
        self.verdicts.values().flatten().cloned().collect()
    }

    /// The changes of a sensor's verdict at `steps`, by vehicle id.
    pub fn verdicts_at(&self, steps: std::ops::Range<usize>) -> Vec<protocol::SensorVerdict> {
        self.verdicts
            .range(steps)
            .flat_map(|(_, v)| v)
            .map(|v| protocol::SensorVerdict {
                vehicle: self.vehicles.at(v.vehicle).id.clone(),
                step: v.step,
                from: v.from,
                to: v.to,
                reason: v.reason.clone(),
            })
            .collect()
    }

    /// Every tested sensor's verdict now, by vehicle id.
    pub fn sensor_health(&self) -> BTreeMap<VehicleId, protocol::SensorHealth> {
        self.health()
            .0
            .into_iter()
            .map(|(v, (state, reason))| (self.vehicles.at(v).id.clone(), protocol::SensorHealth { state, reason }))
            .collect()
    }

    /// Every tested sensor's verdict now and why, by vehicle index, and what the tests did to
    /// the readings.
    pub fn health(&self) -> (BTreeMap<usize, (Health, String)>, crate::health::Screened) {
        let s = self.assim.screen_state();
        (s.health(), s.counts)
    }

    /// The model's skill at each epoch assimilated with the filter, in epoch order.
    pub fn skills(&self) -> Vec<crate::protocol::EpochSkill> {
        self.skills.values().copied().collect()
    }

    /// The boats' normalised innovations against the forecast at each step that fused boat
    /// values (epochs assimilated so far), with their epoch and step.
    pub fn innovations(&self) -> Vec<crate::holdout::StepInnovation> {
        self.innovations
            .range(..self.history.len())
            .map(|(&k, i)| crate::holdout::StepInnovation {
                epoch: self.schedule.epoch_of_step(k),
                step: k as u64,
                nis: i.nis,
                values: i.values,
            })
            .collect()
    }

    /// Boats go at most `speed` metres per step (the mission's `[motion]`): horizon placement
    /// plans only disks they reach in time. Set before the first epoch.
    pub fn with_boat_speed(mut self, speed: f64) -> Self {
        self.assim.set_boat_speed(speed);
        self
    }

    pub fn assimilator(&self) -> &Assimilator {
        &self.assim
    }
}

/// A step's aerial sight made apart (`None`: the step had no aerial samples).
type Sight = Result<Option<crate::AerialSight>, TeamError>;

/// The run's estimate files could not be written or read back.
fn history_error(e: std::io::Error) -> TeamError {
    TeamError::History(e.to_string())
}

#[cfg(test)]
mod checkpoint_tests {
    use super::*;

    /// Over missions of 1 to 300 checkpoints: at most 2 log2(n + 1) kept, and a batch late by
    /// A epochs re-fits from a kept checkpoint (or epoch 0) at most 3 A + CHECKPOINT_EVERY
    /// epochs back; a dropped checkpoint is never kept again as the mission goes on.
    #[test]
    fn thinned_checkpoints_stay_few_and_near_the_late_epoch() {
        let mut dropped = BTreeSet::new();
        for n in 1..=300u64 {
            let newest = n * CHECKPOINT_EVERY;
            let kept: Vec<u64> = (1..=n)
                .map(|i| i * CHECKPOINT_EVERY)
                .filter(|&at| keep_checkpoint(at, newest))
                .collect();
            assert!(kept.len() as f64 <= 2.0 * ((n + 1) as f64).log2(), "{n}: {kept:?}");
            assert!(kept.iter().all(|at| !dropped.contains(at)), "{n}: dropped, then kept");
            dropped.extend((1..=n).map(|i| i * CHECKPOINT_EVERY).filter(|at| !kept.contains(at)));
            for late in 0..=newest {
                let start = kept.iter().copied().filter(|&c| c <= late).max().unwrap_or(0);
                assert!(
                    newest - start <= 3 * (newest - late) + CHECKPOINT_EVERY,
                    "{n}: late {late} from {start}"
                );
            }
        }
    }
}
