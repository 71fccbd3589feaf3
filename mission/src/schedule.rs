//! The epoch schedule every node agrees on, from the team configuration and the mission's
//! length alone (no messages needed to know it).
//!
//! Epoch 0 is the aerial-only initialisation (steps `0..init`). Epoch `e >= 1` covers steps
//! `init + (e-1) * boat_period ..` (the last may be shorter). Aerials sample every
//! `aerial_period` steps and send one batch per epoch (`seq = e`); boats sample at the last
//! step of a full epoch and send one batch for it (`seq = e - 1`).

use crate::protocol::VehicleKind;
use crate::team::TeamConfig;
use std::ops::Range;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Schedule {
    pub init: usize,
    pub boat_period: usize,
    pub aerial_period: usize,
    pub frames: usize,
}

impl Schedule {
    pub fn new(cfg: &TeamConfig, frames: usize) -> Self {
        Self {
            init: cfg.init_steps,
            boat_period: cfg.boat_period.max(1),
            aerial_period: cfg.aerial_period.max(1),
            frames,
        }
    }

    /// Steps of epoch `e` (empty past the end of the mission).
    pub fn steps_of(&self, e: u64) -> Range<usize> {
        if e == 0 {
            return 0..self.init.min(self.frames);
        }
        let a = self
            .init
            .saturating_add((e as usize - 1).saturating_mul(self.boat_period));
        a.min(self.frames)..a.saturating_add(self.boat_period).min(self.frames)
    }

    /// The epoch step `k` belongs to.
    pub fn epoch_of_step(&self, k: usize) -> u64 {
        if k < self.init {
            return 0;
        }
        1 + ((k - self.init) / self.boat_period) as u64
    }

    /// How many epochs the mission has.
    pub fn epochs(&self) -> u64 {
        let rest = self.frames.saturating_sub(self.init);
        1 + rest.div_ceil(self.boat_period) as u64
    }

    /// Whether epoch `e` is a full one (boats sample in full epochs only).
    pub fn is_full(&self, e: u64) -> bool {
        e >= 1 && self.steps_of(e).len() == self.boat_period
    }

    /// Steps at which a vehicle of `kind` samples in epoch `e` (empty: it sends no batch).
    pub fn sample_steps(&self, kind: VehicleKind, e: u64) -> Vec<usize> {
        let steps = self.steps_of(e);
        match kind {
            VehicleKind::Aerial => steps.filter(|k| k % self.aerial_period == 0).collect(),
            VehicleKind::Boat if self.is_full(e) => vec![steps.end - 1],
            VehicleKind::Boat => vec![],
        }
    }

    /// The epoch a vehicle's batch `seq` belongs to.
    pub fn epoch_of(kind: VehicleKind, seq: u64) -> u64 {
        match kind {
            VehicleKind::Aerial => seq,
            VehicleKind::Boat => seq.saturating_add(1),
        }
    }

    /// The seq of a vehicle's batch for epoch `e` (`None`: it sends none).
    pub fn seq_of(&self, kind: VehicleKind, e: u64) -> Option<u64> {
        if self.sample_steps(kind, e).is_empty() {
            return None;
        }
        Some(match kind {
            VehicleKind::Aerial => e,
            VehicleKind::Boat => e - 1,
        })
    }

    /// The last seq a vehicle of `kind` sends (`None`: none at all).
    pub fn last_seq(&self, kind: VehicleKind) -> Option<u64> {
        (0..self.epochs()).rev().find_map(|e| self.seq_of(kind, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn epochs_cover_every_step_once() {
        let s = Schedule {
            init: 10,
            boat_period: 5,
            aerial_period: 2,
            frames: 32,
        };
        assert_eq!(s.epochs(), 6);
        let all: Vec<usize> = (0..s.epochs()).flat_map(|e| s.steps_of(e)).collect();
        assert_eq!(all, (0..32).collect::<Vec<_>>());
        assert!(s.steps_of(6).is_empty());
        assert_eq!(s.sample_steps(VehicleKind::Boat, 1), vec![14]);
        assert_eq!(
            s.sample_steps(VehicleKind::Boat, 5),
            Vec::<usize>::new(),
            "last epoch 30..32 is short"
        );
        assert_eq!(s.sample_steps(VehicleKind::Aerial, 5), vec![30]);
        assert_eq!(s.last_seq(VehicleKind::Boat), Some(3));
        assert_eq!(s.last_seq(VehicleKind::Aerial), Some(5));
        for e in 0..s.epochs() {
            assert!(s.steps_of(e).all(|k| s.epoch_of_step(k) == e), "epoch {e}");
            for kind in [VehicleKind::Aerial, VehicleKind::Boat] {
                if let Some(seq) = s.seq_of(kind, e) {
                    assert_eq!(Schedule::epoch_of(kind, seq), e);
                }
            }
        }
    }
}
