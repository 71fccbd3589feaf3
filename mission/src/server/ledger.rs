//! What the server records of each step and epoch as it assimilates (a re-fit writes its
//! steps again): the held-out boat readings' scores, the boats' innovations, the model's skill
//! and the sensors' verdicts that changed.

use super::ServerCore;
use crate::health::Verdict;
use crate::protocol;
use std::collections::BTreeMap;

/// Per step (or epoch), what the assimilation found.
#[derive(Clone, Default)]
pub(super) struct Ledger {
    /// The share of boat readings held out of the fusion to score it ([`crate::holdout`]; 0:
    /// none), and what the estimate said of each, by step.
    pub(super) holdout_share: f64,
    pub(super) held_out: BTreeMap<usize, Vec<crate::holdout::HeldOut>>,
    /// The boats' innovations against the forecast, by step.
    pub(super) innovations: BTreeMap<usize, fleet_math::kalman::Innovation>,
    /// The model's skill by epoch.
    pub(super) skills: BTreeMap<u64, crate::protocol::EpochSkill>,
    /// The sensors' verdicts that changed, by step.
    pub(super) verdicts: BTreeMap<usize, Vec<Verdict>>,
}

impl ServerCore {
    /// Hold `share` of the boats' readings out of the fusion and score the estimate on them
    /// ([`crate::holdout`]): how a run without a truth is measured.
    pub fn with_holdout(mut self, share: f64) -> Self {
        self.ledger.holdout_share = share;
        self
    }

    /// The hold-out's figures so far (`None`: nothing held out).
    pub fn holdout(&self) -> Option<crate::protocol::HoldoutScore> {
        crate::holdout::score(self.ledger.held_out.values().flatten())
    }

    /// Every change of a sensor's verdict, in step order.
    pub fn verdicts(&self) -> Vec<Verdict> {
        self.ledger.verdicts.values().flatten().cloned().collect()
    }

    /// The changes of a sensor's verdict at `steps`, by vehicle id.
    pub fn verdicts_at(&self, steps: std::ops::Range<usize>) -> Vec<protocol::SensorVerdict> {
        self.ledger
            .verdicts
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

    /// The model's skill at each epoch assimilated with the filter, in epoch order.
    pub fn skills(&self) -> Vec<crate::protocol::EpochSkill> {
        self.ledger.skills.values().copied().collect()
    }

    /// The boats' normalised innovations against the forecast at each step that fused boat
    /// values (epochs assimilated so far), with their epoch and step.
    pub fn innovations(&self) -> Vec<crate::holdout::StepInnovation> {
        self.ledger
            .innovations
            .range(..self.history.len())
            .map(|(&k, i)| crate::holdout::StepInnovation {
                epoch: self.schedule.epoch_of_step(k),
                step: k as u64,
                nis: i.nis,
                values: i.values,
            })
            .collect()
    }
}
