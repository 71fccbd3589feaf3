//! What the server decided that its batches alone do not say (the vehicles held out of each
//! epoch's allocation, the epochs forced without some batch, the operator's overrides), handed
//! to the node as journal records and read back at a restart, so a restarted server makes the
//! same plans and reaches the same epoch.

use super::intake::BatchFault;
use super::ServerCore;
use crate::protocol::{self, MeasurementBatch, VehicleId};
use crate::team::TeamError;
use std::collections::BTreeSet;

/// The journal's metadata key prefix of the operator's sensor overrides
/// (`sensor/<vehicle>/<step>`, zero-padded: key order is step order per vehicle).
pub const OVERRIDE_PREFIX: &str = "sensor/";

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

/// The decisions not yet handed to the journal, and the epochs forced.
#[derive(Clone, Default)]
pub(super) struct Journal {
    /// Epochs assimilated without some batch (by [`ServerCore::force`]).
    pub(super) forced: BTreeSet<u64>,
    /// Epochs whose [`EpochRecord`] changed since the node last journalled them.
    pub(super) unjournalled: BTreeSet<u64>,
    /// The operator's overrides (vehicle, step) not yet journalled.
    pub(super) unjournalled_overrides: BTreeSet<(usize, u64)>,
}

impl ServerCore {
    /// The records of the epochs whose decisions changed since the last call, as the journal's
    /// metadata (key, CBOR): the node commits them with the batch that caused them, before any
    /// plan of those epochs is handed out.
    pub fn take_journal_records(&mut self) -> Vec<(String, Vec<u8>)> {
        let overrides = std::mem::take(&mut self.journal.unjournalled_overrides)
            .into_iter()
            .map(|(v, step)| {
                let o = protocol::SensorOverride {
                    vehicle: self.vehicles.at(v).id.clone(),
                    from_step: step,
                    set: self.sensors.overrides[&v][&step],
                };
                let mut bytes = vec![];
                ciborium::into_writer(&o, &mut bytes).expect("a record serialises");
                (format!("{OVERRIDE_PREFIX}{}/{step:010}", o.vehicle), bytes)
            });
        let overrides: Vec<(String, Vec<u8>)> = overrides.collect();
        std::mem::take(&mut self.journal.unjournalled)
            .into_iter()
            .map(|e| {
                let held = self.planning.holds.get(&e).map_or_else(Vec::new, |h| {
                    h.iter().map(|&i| self.vehicles.at(i).id.clone()).collect()
                });
                let mut bytes = vec![];
                ciborium::into_writer(
                    &EpochRecord {
                        held,
                        forced: self.journal.forced.contains(&e),
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
            self.planning.holds.insert(e, held);
            if r.forced {
                self.journal.forced.insert(e);
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
                    self.intake.received.entry(e).or_default().insert(index, b);
                }
                Ok(None) => return Err(why("twice in the journal".into())),
                Err(BatchFault::Unknown) => return Err(why("not a vehicle of the mission".into())),
                Err(BatchFault::Invalid(w)) => return Err(why(w)),
            }
        }
        self.counters.batches += n;
        self.counters.restored = n;
        while self.epoch_complete(self.epoch)
            || (self.epoch > 0 && self.journal.forced.contains(&self.epoch) && !self.steps_of(self.epoch).is_empty())
        {
            if !self.epoch_complete(self.epoch) {
                self.counters.forced += 1;
            }
            self.assimilate_epoch(self.epoch)?;
            self.readmit()?;
        }
        self.planning.held = self.planning.holds.get(&self.epoch).cloned().unwrap_or_default();
        self.journal.unjournalled.clear();
        self.journal.unjournalled_overrides.clear();
        (self.intake.stale, self.intake.stale_from) = (false, u64::MAX);
        Ok(n)
    }
}
