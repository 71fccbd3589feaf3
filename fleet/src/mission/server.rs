//! The model server's core, without the network: measurement batches in (any order, any
//! number of times), each assimilated exactly once, epochs folded into the model in step order
//! as soon as they are complete, acks, plans and model updates out. The Zenoh node wraps this.
//!
//! The epoch contract ([`Schedule`]): every vehicle sends one batch per epoch it takes part
//! in, and its `seq` counts those batches from 0 without gaps. Aerials take part from epoch 0
//! (the aerial-only initialisation); boats in every full epoch from epoch 1 (a boat left
//! without a disk sends an empty batch). An epoch is complete when every batch for it is in.

use super::{schedule::Schedule, Allocation, Assimilator};
use crate::experiment::team::{TeamConfig, TeamError};
use crate::grid::Grid;
use crate::protocol::{self, Ack, MeasurementBatch, ModelUpdate, Plan, Sample, Target, VehicleKind};
use std::collections::{BTreeMap, BTreeSet};

/// A vehicle of the mission: its id and kind; its index is its place in the list (aerials
/// first), which also picks its random stream.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleSpec {
    pub id: String,
    pub kind: VehicleKind,
}

/// The vehicles of a team: `av-1..` then `boat-1..`.
pub fn team_vehicles(cfg: &TeamConfig) -> Vec<VehicleSpec> {
    (1..=cfg.aerials)
        .map(|i| VehicleSpec { id: format!("av-{i}"), kind: VehicleKind::Aerial })
        .chain((1..=cfg.boats).map(|i| VehicleSpec { id: format!("boat-{i}"), kind: VehicleKind::Boat }))
        .collect()
}

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

#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error(transparent)]
    Protocol(#[from] protocol::ProtocolError),
    #[error("batch from {vehicle}: {why}")]
    Rejected { vehicle: String, why: String },
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
}

pub struct ServerCore {
    cfg: TeamConfig,
    schedule: Schedule,
    vehicles: Vec<VehicleSpec>,
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
    /// Fused snapshots of every step assimilated so far (for metrics).
    pub snapshots: Vec<Vec<f64>>,
    /// Late batches taken by [`Self::ingest_deferred`] and not yet re-fitted.
    stale: bool,
}

impl ServerCore {
    pub fn new(cfg: &TeamConfig, grid: Grid, frames: usize) -> Result<Self, TeamError> {
        Ok(Self {
            assim: Assimilator::new(cfg, grid, frames)?,
            cfg: cfg.clone(),
            schedule: Schedule::new(cfg, frames),
            vehicles: team_vehicles(cfg),
            epoch: 0,
            received: BTreeMap::new(),
            plans: BTreeMap::new(),
            held: BTreeSet::new(),
            holds: BTreeMap::new(),
            counters: Counters::default(),
            version: 0,
            snapshots: vec![],
            stale: false,
        })
    }

    pub fn vehicles(&self) -> &[VehicleSpec] {
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
    pub fn missing_at(&self, e: u64) -> Vec<String> {
        self.missing(e).map(|i| self.vehicles[i].id.clone()).collect()
    }

    /// Vehicles whose batch for the next epoch, or for an epoch assimilated without it, has
    /// not come in.
    pub fn waiting_for(&self) -> Vec<String> {
        let mut ids: Vec<usize> = (0..=self.epoch).flat_map(|e| self.missing(e).collect::<Vec<_>>()).collect();
        ids.sort_unstable();
        ids.dedup();
        ids.into_iter().map(|i| self.vehicles[i].id.clone()).collect()
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
        self.counters.forced += 1;
        self.assimilate_complete()?;
        Ok(true)
    }

    /// Assimilate every epoch from the next on that has all its batches.
    fn assimilate_complete(&mut self) -> Result<(), TeamError> {
        while self.epoch_complete(self.epoch) {
            self.assimilate_epoch(self.epoch)?;
        }
        Ok(())
    }

    /// Rebuild the model from the first epoch with every batch now in (the general method's
    /// snapshots are a function of the batches, so this is the re-fit from the earliest
    /// affected step, done from the start for simplicity). Plans already handed out stay as
    /// history; the next epoch's plan is the re-fitted model's.
    fn refit(&mut self) -> Result<(), TeamError> {
        let upto = self.epoch;
        let version = self.version;
        let history = std::mem::take(&mut self.plans);
        self.assim = Assimilator::new(&self.cfg, *self.assim.grid(), self.schedule.frames)?;
        self.snapshots.clear();
        self.epoch = 0;
        while self.epoch < upto {
            self.assimilate_epoch(self.epoch)?;
        }
        let next = self.plans.remove(&upto);
        self.plans = history;
        if let Some(p) = next {
            self.plans.insert(upto, p);
        }
        self.version = version + 1;
        self.counters.refits += 1;
        Ok(())
    }

    /// Whether the planner may allocate a vehicle (from its telemetry); takes effect at the next
    /// allocation. Returns whether it changed.
    pub fn set_available(&mut self, vehicle: &str, available: bool) -> bool {
        let Some(index) = self.vehicles.iter().position(|v| v.id == vehicle) else { return false };
        if available {
            self.held.remove(&index)
        } else {
            self.held.insert(index)
        }
    }

    /// Vehicles left out of the next allocation.
    pub fn held(&self) -> Vec<String> {
        self.held.iter().map(|&i| self.vehicles[i].id.clone()).collect()
    }

    /// Vehicles left out of epoch `e`'s allocation.
    pub fn held_at(&self, e: u64) -> Vec<String> {
        self.holds.get(&e).map_or_else(Vec::new, |h| h.iter().map(|&i| self.vehicles[i].id.clone()).collect())
    }

    fn reject(&mut self, vehicle: &str, why: String) -> IngestError {
        *self.counters.rejected.entry("invalid_batch".into()).or_default() += 1;
        IngestError::Rejected { vehicle: vehicle.into(), why }
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
        self.refit()?;
        self.stale = false;
        self.assimilate_complete()?;
        Ok(true)
    }

    /// [`Self::ingest`] without the re-fit a late batch needs: a boat's backlog arrives as a
    /// burst of late batches, and one [`Self::settle`] after the burst re-fits once instead of
    /// once per batch. Until `settle`, the model and plans do not yet include the late batches
    /// (a batch that completes the next epoch settles first).
    pub fn ingest_deferred(&mut self, batch: MeasurementBatch) -> Result<Ingested, IngestError> {
        self.counters.batches += 1;
        let Some(index) = self.vehicles.iter().position(|v| v.id == batch.vehicle) else {
            *self.counters.rejected.entry("unknown_vehicle".into()).or_default() += 1;
            return Err(protocol::ProtocolError::UnknownVehicle(batch.vehicle).into());
        };
        if self.vehicles[index].kind != batch.kind {
            return Err(self.reject(&batch.vehicle, format!("declared {:?}, registered {:?}", batch.kind, self.vehicles[index].kind)));
        }
        let e = Schedule::epoch_of(batch.kind, batch.seq);
        if self.received.get(&e).is_some_and(|m| m.contains_key(&index)) {
            self.counters.duplicates += 1;
            return Ok(Ingested::Duplicate);
        }
        let steps = self.steps_of(e);
        if steps.is_empty() {
            return Err(self.reject(&batch.vehicle, format!("seq {} is past the end of the mission", batch.seq)));
        }
        let want = self.schedule.sample_steps(batch.kind, e);
        let got: Vec<usize> = batch.samples.iter().map(|s| s.step as usize).collect();
        // A boat the plan left without a disk, or a vehicle on hold, sends an empty batch.
        let idle = got.is_empty()
            && self.plans.get(&e).is_some_and(|p| p.held.contains(&index) || (batch.kind == VehicleKind::Boat && p.boats[index - self.cfg.aerials].is_none()));
        if got != want && !idle {
            return Err(self.reject(&batch.vehicle, format!("epoch {e} wants samples at steps {want:?}, got {got:?}")));
        }
        self.received.entry(e).or_default().insert(index, batch);
        if e < self.epoch {
            self.stale = true;
            return Ok(Ingested::Refitted(e));
        }
        let before = self.epoch;
        // An epoch completed on top of a model still missing late batches: re-fit first.
        if self.stale && self.epoch_complete(before) {
            self.settle()?;
        } else {
            self.assimilate_complete()?;
        }
        Ok(if self.epoch == before { Ingested::Buffered } else { Ingested::Assimilated((before..self.epoch).collect()) })
    }

    /// Aerials take part in every epoch; boats in every full epoch after the first (a last,
    /// shorter epoch has no boat step).
    fn takes_part(&self, index: usize, e: u64) -> bool {
        !self.schedule.sample_steps(self.vehicles[index].kind, e).is_empty()
    }

    fn epoch_complete(&self, e: u64) -> bool {
        if self.steps_of(e).is_empty() {
            return false;
        }
        self.missing(e).next().is_none()
    }

    /// Samples of every vehicle of a kind at step `k`, in vehicle order.
    fn samples_at(batches: &BTreeMap<usize, MeasurementBatch>, kind: VehicleKind, k: usize) -> Vec<Sample> {
        batches.values().filter(|b| b.kind == kind).flat_map(|b| b.samples.iter().filter(|s| s.step as usize == k).cloned()).collect()
    }

    fn assimilate_epoch(&mut self, e: u64) -> Result<(), TeamError> {
        let batches = self.received.get(&e).cloned().unwrap_or_default();
        let steps = self.steps_of(e);
        if e == 0 {
            let mut init = vec![];
            for k in steps {
                let est = self.assim.aerial_estimate(&Self::samples_at(&batches, VehicleKind::Aerial, k))?;
                init.push(est.values);
            }
            self.snapshots.extend(init.iter().cloned());
            self.assim.initialise(init)?;
        } else {
            let k0 = steps.start;
            let mut epoch = vec![];
            for k in steps {
                let aerial = self.assim.aerial_estimate(&Self::samples_at(&batches, VehicleKind::Aerial, k))?;
                let boats = Self::samples_at(&batches, VehicleKind::Boat, k);
                epoch.push(self.assim.fuse_step((k + 1 - k0) as u64, &aerial, &boats)?.values);
            }
            self.snapshots.extend(epoch.iter().cloned());
            self.assim.assimilate(epoch)?;
        }
        self.epoch = e + 1;
        self.version += 1;
        self.counters.epochs = self.epoch;
        if !self.all_assimilated() {
            let held = self.holds.entry(self.epoch).or_insert_with(|| self.held.clone()).clone();
            let plan = self.assim.allocate_without(&held)?;
            self.plans.insert(self.epoch, plan);
        }
        Ok(())
    }

    /// The allocation vehicles sense epoch `e` under (`None` before it is computed). Epoch 0
    /// is the uniform formation.
    pub fn allocation(&self, e: u64) -> Option<Allocation> {
        if e == 0 {
            return Some(Allocation { boats: vec![None; self.cfg.boats], aerials: self.assim.aerial_positions().to_vec(), held: BTreeSet::new() });
        }
        self.plans.get(&e).cloned()
    }

    /// The plan of one vehicle from epoch `e` on: where to be and what to sense at each of
    /// its sampling steps of epochs `e .. e + horizon`, all under epoch `e`'s allocation (the
    /// model's spatial modes, and so the disks, stay until the next update; a vehicle cut off
    /// from the server keeps following the later targets).
    pub fn plan(&self, vehicle: &str, e: u64, horizon: u64) -> Option<Plan> {
        let index = self.vehicles.iter().position(|v| v.id == vehicle)?;
        let alloc = self.allocation(e)?;
        let grid = self.assim.grid();
        let kind = self.vehicles[index].kind;
        let (position, radius, cells) = match kind {
            // Left out: stays where it is, senses nothing.
            VehicleKind::Aerial if alloc.held.contains(&index) => (alloc.aerials[index], 0.0, vec![]),
            VehicleKind::Boat if alloc.held.contains(&index) => (self.assim.boat_positions()[index - self.cfg.aerials], 0.0, vec![]),
            VehicleKind::Aerial => {
                let (ids, positions) = alloc.active_aerials();
                let me = ids.iter().position(|&a| a == index)?;
                let region = crate::fusion::aerial_region(grid, self.cfg.aerial_stride, &positions, me).ok()?;
                (alloc.aerials[index], 0.0, region)
            }
            VehicleKind::Boat => {
                let b = index - self.cfg.aerials;
                match &alloc.boats[b] {
                    Some((cells, (r, c))) => (grid.centre_m(crate::grid::Cell::new(*r, *c)), self.cfg.radius, cells.clone()),
                    None => (self.assim.boat_positions()[b], 0.0, vec![]),
                }
            }
        };
        let cells: Vec<u32> = cells.into_iter().map(|c| c as u32).collect();
        let targets = (e..e.saturating_add(horizon.max(1)))
            .flat_map(|ep| self.schedule.sample_steps(kind, ep).into_iter().map(move |k| (ep, k)))
            .map(|(ep, k)| Target { epoch: ep, step: k as u64, position: [position.0, position.1], radius, cells: cells.clone() })
            .collect();
        Some(Plan { vehicle: vehicle.into(), model_version: self.version, epoch: e, targets })
    }

    /// The ack of a vehicle: the highest seq up to which all of its batches are in the model
    /// (`None` before its first).
    pub fn ack(&self, vehicle: &str) -> Option<Ack> {
        let index = self.vehicles.iter().position(|v| v.id == vehicle)?;
        let kind = self.vehicles[index].kind;
        let mut seq = None;
        for e in 0..self.epoch {
            let Some(s) = self.schedule.seq_of(kind, e) else { continue };
            if !self.received.get(&e).is_some_and(|m| m.contains_key(&index)) {
                break;
            }
            seq = Some(s);
        }
        Some(Ack { vehicle: vehicle.into(), seq: seq? })
    }

    /// The model as published on `model/latest` (`None` before the first fit). The variance
    /// is the model's calibrated prediction error per cell.
    pub fn model_update(&self) -> Option<ModelUpdate> {
        let m = self.assim.model()?;
        let (n, r) = (m.modes.modes.nrows(), m.modes.modes.ncols());
        let mut modes_re = Vec::with_capacity(n * r);
        let mut modes_im = Vec::with_capacity(n * r);
        for i in 0..n {
            for j in 0..r {
                modes_re.push(m.modes.modes[(i, j)].re);
                modes_im.push(m.modes.modes[(i, j)].im);
            }
        }
        Some(ModelUpdate {
            version: self.version,
            epoch: self.epoch.saturating_sub(1),
            step: self.snapshots.len().saturating_sub(1) as u64,
            grid: *self.assim.grid(),
            dt: m.dt,
            eigenvalues: m.modes.eigenvalues.iter().map(|l| [l.re, l.im]).collect(),
            modes_re,
            modes_im,
            amplitudes: m.amplitudes.iter().map(|a| [a.re, a.im]).collect(),
            variance: vec![self.assim.prediction_variance(); n],
        })
    }

    pub fn assimilator(&self) -> &Assimilator {
        &self.assim
    }
}
