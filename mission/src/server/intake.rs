//! Batches in: each checked against the mission (its vehicle, its epoch, the steps it must
//! hold), a duplicate dropped, the rest buffered by epoch until the epoch is complete (or
//! forced); what each vehicle's ack says, and what is still missing.

use super::{IngestError, Ingested, ServerCore};
use crate::protocol::{self, Ack, MeasurementBatch, VehicleId, VehicleKind};
use crate::schedule::Schedule;
use std::collections::BTreeMap;

/// Every batch accepted, and whether some came late.
#[derive(Clone)]
pub(super) struct Intake {
    /// Every batch accepted, by epoch then vehicle index: the model is a function of this
    /// set, so late batches re-fit it from their epoch on.
    pub(super) received: BTreeMap<u64, BTreeMap<usize, MeasurementBatch>>,
    /// Late batches taken by [`ServerCore::ingest_deferred`] (or overrides of steps already
    /// in the model) not yet re-fitted.
    pub(super) stale: bool,
    /// The earliest epoch those late batches belong to: the re-fit starts there.
    pub(super) stale_from: u64,
}

impl Default for Intake {
    fn default() -> Self {
        Self {
            received: BTreeMap::new(),
            stale: false,
            stale_from: u64::MAX,
        }
    }
}

/// Why [`ServerCore::check`] refuses a batch.
pub(super) enum BatchFault {
    Unknown,
    Invalid(String),
}

impl ServerCore {
    /// Vehicles whose batch for epoch `e` has not come in.
    pub(super) fn missing(&self, e: u64) -> impl Iterator<Item = usize> + '_ {
        let have = self.intake.received.get(&e);
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
        self.intake.received.range(self.epoch..).count() as u64
    }

    pub(super) fn reject(&mut self, vehicle: &VehicleId, why: String) -> IngestError {
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
        self.intake.received.entry(e).or_default().insert(index, batch);
        if e < self.epoch {
            self.intake.stale = true;
            self.intake.stale_from = self.intake.stale_from.min(e);
            return Ok(Ingested::Refitted(e));
        }
        let before = self.epoch;
        // An epoch completed on top of a model still missing late batches: re-fit first.
        if self.intake.stale && self.epoch_complete(before) {
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
    pub(super) fn check(&self, batch: &MeasurementBatch) -> Result<Option<(usize, u64)>, BatchFault> {
        let index = self.vehicles.index_of(&batch.vehicle).ok_or(BatchFault::Unknown)?;
        if self.vehicles.at(index).kind != batch.kind {
            return Err(BatchFault::Invalid(format!(
                "declared {:?}, registered {:?}",
                batch.kind,
                self.vehicles.at(index).kind
            )));
        }
        let e = Schedule::epoch_of(batch.kind, batch.seq);
        if self.intake.received.get(&e).is_some_and(|m| m.contains_key(&index)) {
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
    pub(super) fn instrument_steps(&self, batch: &MeasurementBatch, e: u64) -> bool {
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

    /// Aerials take part in every epoch; boats in every full epoch after the first (a last,
    /// shorter epoch has no boat step).
    pub(super) fn takes_part(&self, index: usize, e: u64) -> bool {
        !self.schedule.sample_steps(self.vehicles.at(index).kind, e).is_empty()
    }

    pub(super) fn epoch_complete(&self, e: u64) -> bool {
        if self.steps_of(e).is_empty() {
            return false;
        }
        self.missing(e).next().is_none()
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
            .filter(|(e, _)| !self.intake.received.get(e).is_some_and(|m| m.contains_key(&index)))
            .map(|(_, s)| s)
            .collect()
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
            if !self.intake.received.get(&e).is_some_and(|m| m.contains_key(&index)) {
                break;
            }
            seq = Some(s);
        }
        let sensor = (self.assim.screen_state().verdict_unless_ok(index))
            .map(|(state, reason)| protocol::SensorHealth { state, reason });
        Some(Ack {
            vehicle: vehicle.clone(),
            seq: seq?,
            sensor,
        })
    }
}
