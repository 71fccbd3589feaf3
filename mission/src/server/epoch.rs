//! One epoch into the model: epoch 0's aerial estimates fit the first model; each later
//! step's readings are screened and fused, the next step's aerial sight made beside the
//! filter step, and the model updated with the fused steps; then the next epoch is placed.

use super::{history_error, ServerCore};
use crate::health::VehicleSample;
use crate::protocol::{MeasurementBatch, Sample, VehicleKind};
use crate::team::{LearnFrom, TeamError};
use std::collections::BTreeMap;

impl ServerCore {
    pub(super) fn assimilate_epoch(&mut self, e: u64) -> Result<(), TeamError> {
        // The model published for the last epoch is stale from here on, and it holds the model
        // it was made of (its modes made only when a get asks): dropped before the refit makes
        // the new one, so the two are never in memory together (the server's peak).
        self.publication.published = None;
        self.checkpoint_at(e);
        let batches = self.intake.received.get(&e).cloned().unwrap_or_default();
        let steps = self.steps_of(e);
        match e {
            0 => self.assimilate_first(&batches, steps)?,
            _ => self.assimilate_steps(e, &batches, steps)?,
        }
        self.epoch = e + 1;
        self.version += 1;
        self.counters.epochs = self.epoch;
        if !self.all_assimilated() {
            if !self.planning.holds.contains_key(&self.epoch) {
                self.planning.holds.insert(self.epoch, self.planning.held.clone());
                self.journal.unjournalled.insert(self.epoch);
            }
            let plan = self.place_and_publish()?;
            self.planning.plans.insert(self.epoch, plan);
        }
        Ok(())
    }

    /// Epoch 0: the aerials' estimates of its steps fit the first model.
    pub(super) fn assimilate_first(
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
    /// ([`crate::assimilator::Assimilator::lend_model_for_update`]), so it is made beside the whole of
    /// the last step, on the other core, idle there (the update's projections, `H`'s factor and
    /// the new `U`: 12 of its 15 ms at 192 x 384); the last step's snapshot is then all the
    /// update waits for.
    pub(super) fn assimilate_steps(
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
                    let job = self.assim.lend_model_for_update(&learn);
                    let (done, ahead) = crate::side_by_side::beside(
                        || self.step_fused(batches, k, k0..end, next.take()),
                        || job.map(|j| tracing::info_span!("dmd update ahead").in_scope(|| j.run())),
                    );
                    if let Some((model, made)) = ahead {
                        self.assim.return_lent_model(model);
                        prepared = made;
                    }
                    done?
                }
            };
            next = sight;
            learn.push(learned);
        }
        if let Some(skill) = self.assim.take_skill(e) {
            self.ledger.skills.insert(e, skill);
        }
        tracing::info_span!("model update").in_scope(|| self.assim.assimilate_prepared(learn, prepared))?;
        Ok(())
    }

    /// Step `k` of the epoch's `steps`: its readings screened and fused (with `sight`, its
    /// aerial sight when made ahead), the fused step written; what the model learns of it, and
    /// the next step's aerial sight, made beside the filter step.
    pub(super) fn step_fused(
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
        let (boats, held) = crate::holdout::split(boats, self.ledger.holdout_share, self.cfg.boat_sigma);
        let later = (k + 1 < steps.end).then(|| {
            let samples = self.screened_aerials(batches, k + 1, ahead + 1);
            let later = self.assim.aerial_sight_later(samples);
            move || tracing::info_span!("aerial estimate").in_scope(later)
        });
        let (fused, next) = self.fuse_step_in_parallel_with(ahead, &aerial, &boats, later);
        let fused = fused?;
        if let Some(i) = self.assim.take_innovation() {
            self.ledger.innovations.insert(k, i);
        }
        if self.ledger.holdout_share > 0.0 {
            let scored = held
                .into_iter()
                .map(|(cell, value, noise_var)| crate::holdout::HeldOut {
                    cell,
                    value,
                    noise_var,
                    predicted: fused.values[cell],
                    variance: fused.variance[cell],
                });
            self.ledger.held_out.insert(k, scored.collect());
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

    /// Step `k`'s filter step, and beside it, on the other core, `job`: the aerial sight of
    /// the next step (it reads the mission's settings and its own samples only, and the
    /// filter's step takes about three times as long: 9 against 3 ms at 192 x 384).
    pub(super) fn fuse_step_in_parallel_with<T: Send>(
        &mut self,
        ahead: u64,
        aerial: &crate::assimilator::AerialSight,
        boats: &[Sample],
        job: Option<impl FnOnce() -> T + Send>,
    ) -> (Result<fleet_math::fusion::Estimate, TeamError>, Option<T>) {
        let assim = &mut self.assim;
        crate::side_by_side::beside(
            || tracing::info_span!("fuse").in_scope(|| assim.fuse_step(ahead, aerial, boats)),
            || Some(job?()),
        )
    }

    /// Samples of every vehicle of a kind at step `k`, in vehicle order.
    pub(super) fn samples_at(batches: &BTreeMap<usize, MeasurementBatch>, kind: VehicleKind, k: usize) -> Vec<Sample> {
        Self::vehicle_samples_at(batches, kind, k)
            .into_iter()
            .map(|t| t.sample)
            .collect()
    }

    /// [`Self::samples_at`] with each sample's vehicle index (for the health tests).
    pub(super) fn vehicle_samples_at(
        batches: &BTreeMap<usize, MeasurementBatch>,
        kind: VehicleKind,
        k: usize,
    ) -> Vec<VehicleSample> {
        batches
            .iter()
            .filter(|(_, b)| b.kind == kind)
            .flat_map(|(&v, b)| {
                b.samples
                    .iter()
                    .filter(|s| s.step as usize == k)
                    .map(move |s| VehicleSample {
                        vehicle: v,
                        sample: s.clone(),
                    })
            })
            .collect()
    }
}

/// A step's aerial sight made apart (`None`: the step had no aerial samples).
type Sight = Result<Option<crate::assimilator::AerialSight>, TeamError>;
