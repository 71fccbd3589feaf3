//! The model made again: from the newest checkpoint at or before the earliest late epoch (a
//! late batch, an operator's override of a past step) or a re-admission's first clean step,
//! with everything now in. Checkpoints are kept every [`CHECKPOINT_EVERY`] epochs and thinned
//! with age ([`keep_checkpoint`]).

use super::{history_error, ServerCore};
use crate::assimilator::Assimilator;
use crate::team::TeamError;
use std::collections::BTreeMap;

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

/// The assimilator's state before every `CHECKPOINT_EVERY`-th epoch, older ones thinned
/// ([`keep_checkpoint`]): a re-fit starts from the newest one at or before the earliest late
/// epoch, so its cost grows with how late the batch is, not with the mission's length.
#[derive(Clone)]
pub(super) struct Checkpoints {
    /// By epoch, the state and the steps in the history then (`None`: checkpoints off, every
    /// re-fit from epoch 0).
    pub(super) kept: Option<BTreeMap<u64, (crate::assimilator::AssimilatorCheckpoint, usize)>>,
}

impl Default for Checkpoints {
    fn default() -> Self {
        Self {
            kept: Some(BTreeMap::new()),
        }
    }
}

impl ServerCore {
    /// Re-fit with the late batches [`Self::ingest_deferred`] took, if any (then assimilate
    /// every epoch that is complete). Returns whether it re-fitted.
    pub fn settle(&mut self) -> Result<bool, TeamError> {
        if !self.intake.stale {
            return Ok(false);
        }
        // Re-admissions found after the late epoch's start were found without its batches.
        let first = self.steps_of(self.intake.stale_from.min(self.epoch)).start as u64;
        self.sensors
            .readmissions
            .values_mut()
            .for_each(|r| r.retain(|_, until| *until < first));
        self.refit()?;
        self.counters.refits += 1;
        self.intake.stale = false;
        self.readmit()?;
        self.assimilate_complete()?;
        Ok(true)
    }

    /// Re-fit from the clean steps of each boat its tests re-admitted since the last call, with
    /// the boat pinned `ok` over them: a sensor that reads true again owes the model nothing
    /// (the model is then the one a fleet whose sensor never failed makes of the same values).
    pub(super) fn readmit(&mut self) -> Result<(), TeamError> {
        while let Some(step) = self.sensors.readmit_from.take() {
            self.intake.stale_from = self.intake.stale_from.min(self.schedule.epoch_of_step(step as usize));
            self.refit()?;
            self.counters.readmissions += 1;
        }
        Ok(())
    }

    /// Rebuild the model with every batch now in, from the newest checkpoint at or before the
    /// earliest late epoch (the model of the epochs before it is the same: their batches did
    /// not change), or from the start without one. Plans already handed out stay as history;
    /// the next epoch's plan is the re-fitted model's. The replay sees the plans handed out
    /// until it makes its own (the first epoch it replays judges its silent boats by them).
    pub(super) fn refit(&mut self) -> Result<(), TeamError> {
        // The epochs made again are not news: none of their models goes out (the model after
        // the re-fit is published as any asked for).
        let publisher = self.publication.publisher.take();
        let refitted = self.refit_quietly();
        self.publication.publisher = publisher;
        refitted
    }

    pub(super) fn refit_quietly(&mut self) -> Result<(), TeamError> {
        let upto = self.epoch;
        let version = self.version;
        let history = self.planning.plans.clone();
        let unjournalled = std::mem::take(&mut self.journal.unjournalled);
        let from = std::mem::replace(&mut self.intake.stale_from, u64::MAX);
        let start = self.checkpoints.kept.as_mut().and_then(|c| {
            // Checkpoints after the late epoch describe a model without its batch: gone.
            c.retain(|&e, _| e <= from);
            c.range(..=from).next_back().map(|(&e, _)| e)
        });
        match start {
            Some(e) => {
                let (cp, steps) = &self.checkpoints.kept.as_ref().expect("checkpoints on")[&e];
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
        let next = self.planning.plans.remove(&upto);
        self.planning.plans = history;
        self.journal.unjournalled = unjournalled;
        if let Some(p) = next {
            self.planning.plans.insert(upto, p);
        }
        self.version = version + 1;
        Ok(())
    }

    /// Every [`CHECKPOINT_EVERY`] epochs, the assimilator's state before epoch `e` (what a
    /// re-fit from there starts from), thinned as [`keep_checkpoint`] says.
    pub(super) fn checkpoint_at(&mut self, e: u64) {
        if e > 0 && e.is_multiple_of(CHECKPOINT_EVERY) {
            let steps = self.history.len();
            if let Some(c) = self.checkpoints.kept.as_mut() {
                let at = tracing::info_span!("checkpoint").in_scope(|| self.assim.checkpoint());
                c.insert(e, (at, steps));
                c.retain(|&at, _| keep_checkpoint(at, e));
            }
        }
    }

    /// Turn the checkpoints off (every re-fit then starts from epoch 0): for benchmarks.
    pub fn without_checkpoints(mut self) -> Self {
        self.checkpoints.kept = None;
        self
    }
}

#[cfg(test)]
mod checkpoint_tests {
    use super::*;
    use std::collections::BTreeSet;

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
