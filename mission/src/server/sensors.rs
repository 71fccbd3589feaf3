//! The sensors' verdicts decided outside the tests, pinned per step: the operator's overrides,
//! and the re-admissions of boats whose tests found them reading true again; each step's
//! readings screened with them ([`crate::health`]).

use super::ServerCore;
use crate::health::{Health, Pin, CLEAN_STEPS};
use crate::protocol::{self, MeasurementBatch, Sample, VehicleId, VehicleKind};
use crate::team::TeamError;
use std::collections::BTreeMap;

/// The operator's overrides and the tests' re-admissions.
#[derive(Clone, Default)]
pub(super) struct SensorDecisions {
    /// The operator's overrides by vehicle, then the step each takes effect from (`None`: the
    /// tests decide again); journalled.
    pub(super) overrides: BTreeMap<usize, BTreeMap<u64, Option<Health>>>,
    /// Boats re-admitted from `excluded` by their tests: by vehicle, the first and last of the
    /// clean steps that re-admitted it (pinned `ok` when re-fitted: their values count as they
    /// came). Derived from the batches, so a re-fit from before one forgets it and finds it
    /// again.
    pub(super) readmissions: BTreeMap<usize, BTreeMap<u64, u64>>,
    /// The earliest step a re-admission found since the last re-fit re-fits from.
    pub(super) readmit_from: Option<u64>,
}

impl ServerCore {
    /// The verdicts decided outside the tests at step `k`: re-admissions, then the operator's.
    pub(super) fn pins_at(&self, k: u64) -> BTreeMap<usize, Pin> {
        let mut pins = BTreeMap::new();
        for (&v, r) in &self.sensors.readmissions {
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
        for (&v, o) in &self.sensors.overrides {
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
        self.sensors.overrides.entry(v).or_default().insert(o.from_step, o.set);
        self.journal.unjournalled_overrides.insert((v, o.from_step));
        self.counters.overrides += 1;
        let e = self.schedule.epoch_of_step(o.from_step as usize);
        if e < self.epoch {
            self.intake.stale = true;
            self.intake.stale_from = self.intake.stale_from.min(e);
        }
        Ok(())
    }

    /// Step `k`'s aerial readings tested ([`crate::health`]), with the verdicts decided outside
    /// the tests pinned: the samples the step's aerial sight is made of.
    pub(super) fn screened_aerials(
        &mut self,
        batches: &BTreeMap<usize, MeasurementBatch>,
        k: usize,
        ahead: u64,
    ) -> Vec<Sample> {
        let _span = tracing::info_span!("screen").entered();
        let pins = self.pins_at(k as u64);
        self.assim.screen().pin(pins);
        let silent = self.silent_sensors(batches, k);
        self.assim.screen_silent(k as u64, &silent);
        let aerials = Self::vehicle_samples_at(batches, VehicleKind::Aerial, k);
        self.assim.screen_aerials(k as u64, ahead, aerials)
    }

    /// Step `k`'s boat readings tested against what the fleet knows of the step without them
    /// (the aerials' sight of it, and the filter): the samples the fusion may use. Notes the
    /// step's verdicts that changed, the aerials' with them, and the re-admissions.
    pub(super) fn screened_boats(
        &mut self,
        batches: &BTreeMap<usize, MeasurementBatch>,
        k: usize,
        ahead: u64,
        aerial: &crate::assimilator::AerialSight,
    ) -> Result<Vec<Sample>, TeamError> {
        let _span = tracing::info_span!("screen").entered();
        let boats = Self::vehicle_samples_at(batches, VehicleKind::Boat, k);
        let boats = self.assim.screen_boats(k as u64, ahead, boats, aerial)?;
        for (v, since) in self.assim.screen().take_readmissions() {
            self.sensors.readmissions.entry(v).or_default().insert(since, k as u64);
            self.sensors.readmit_from = Some(self.sensors.readmit_from.map_or(since, |r| r.min(since)));
        }
        let verdicts = self.assim.screen().take_verdicts();
        match verdicts.is_empty() {
            true => self.ledger.verdicts.remove(&k),
            false => self.ledger.verdicts.insert(k, verdicts),
        };
        Ok(boats)
    }

    /// The vehicles sent to sense (a boat's disk, an aerial's region; not held) that said
    /// nothing: at an epoch's first boat step `k`, the boats whose batch holds no reading at all
    /// (a boat's instrument may report at any step of its epoch); at a frame step `k`, the
    /// aerials whose batch holds no reading of it (a frame is of its step, and a camera dark
    /// from mid-epoch is then covered from the next epoch, not the one after: +393% -> +87% on
    /// the 500 hPa height). A batch not yet in is not silence (a vehicle out of range sends its
    /// backlog later).
    pub(super) fn silent_sensors(&self, batches: &BTreeMap<usize, MeasurementBatch>, k: usize) -> Vec<usize> {
        let e = self.schedule.epoch_of_step(k);
        let first_boat = self.schedule.sample_steps(VehicleKind::Boat, e).first() == Some(&k);
        let frame = self.schedule.sample_steps(VehicleKind::Aerial, e).contains(&k);
        // Borrowed, not `allocation`'s copy (its disks' cells); epoch 0 has no plan.
        let Some(alloc) = self.planning.plans.get(&e).filter(|_| first_boat || frame) else {
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
}
