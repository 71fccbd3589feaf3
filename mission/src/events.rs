//! What the model server tells whoever started it (`fleet up`, a test, a field operator's
//! script): one JSON event per line on stdout as the mission goes, and a summary at the end.

use crate::protocol::VehicleId;
use crate::server::Counters;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// One line of the server's `--events` stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum ServerEvent {
    /// Listening; the mission has this many epochs and vehicles.
    Ready {
        mission: String,
        epochs: u64,
        vehicles: Vec<VehicleId>,
        /// Where the first epoch's formation sends each vehicle (grid metres).
        #[serde(default)]
        places: std::collections::BTreeMap<VehicleId, [f64; 2]>,
    },
    /// A liveliness token appeared (`alive`) or went away.
    Link { vehicle: VehicleId, alive: bool },
    /// An epoch entered the model.
    Epoch {
        epoch: u64,
        version: u64,
        /// Mean squared error of the epoch's fused snapshots against the truth (mixed reality).
        mse: Option<f64>,
        latency_ms: f64,
        alive: usize,
        batches: u64,
        /// Vehicles left out of the next epoch's allocation (operator hold, autopilot lost).
        #[serde(default)]
        held: Vec<VehicleId>,
        /// Where the next epoch's allocation sends each vehicle that senses (grid metres).
        #[serde(default)]
        places: std::collections::BTreeMap<VehicleId, [f64; 2]>,
        /// Vehicles it was assimilated without (late: their batches will re-fit it).
        #[serde(default)]
        missing: Vec<VehicleId>,
    },
    /// A sensor's verdict changed ([`crate::health`]): from what to what, at which step, why.
    Sensor(crate::protocol::SensorVerdict),
    /// The operator's verdict on a sensor, taken (the model re-fitted from its step when that
    /// was in it already).
    Override(crate::protocol::SensorOverride),
    /// A late batch (of an epoch assimilated without it) is in the model: re-fitted and
    /// published as `version`.
    Late {
        vehicle: VehicleId,
        epoch: u64,
        version: u64,
    },
    /// A vehicle left the allocation (its autopilot is on operator hold or lost) or came back.
    Hold {
        vehicle: VehicleId,
        held: bool,
        mode: String,
    },
    /// A batch of a mission vehicle was refused: its epoch cannot complete with it (the
    /// vehicle re-sends the same batch), so a mission waiting for it will not finish.
    Refused {
        vehicle: VehicleId,
        seq: u64,
        reason: String,
        detail: String,
    },
    /// A vehicle says the server acknowledged batches the journal does not hold (a journal
    /// deleted, replaced or rolled back): they are lost, and the epochs that need them wait.
    Lost { vehicle: VehicleId, seqs: Vec<u64> },
    /// The next epoch has waited `waited_s` for these vehicles' batches; why each is behind.
    Waiting {
        epoch: u64,
        waited_s: f64,
        behind: BTreeMap<VehicleId, String>,
    },
    /// Every step is in the model.
    Finished { summary: Box<ServerSummary> },
}

/// Percentiles of a set of durations (ms).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Percentiles {
    pub count: usize,
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

impl Percentiles {
    /// Nearest-rank percentiles (0 for an empty set).
    pub fn of(values: &[f64]) -> Self {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        let at = |q: f64| {
            if v.is_empty() {
                0.0
            } else {
                v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1]
            }
        };
        Self {
            count: v.len(),
            p50: at(0.5),
            p99: at(0.99),
            max: v.last().copied().unwrap_or(0.0),
        }
    }
}

/// The server's account of a mission.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ServerSummary {
    pub mission: String,
    pub vehicles: Vec<VehicleId>,
    pub epochs: u64,
    pub model_version: u64,
    pub rank: usize,
    pub counters: Counters,
    /// Last batch of an epoch in to its model update out.
    pub latency_ms: Percentiles,
    /// Per step, the fused snapshot's mean squared error against the truth (mixed reality); NaN
    /// (`null` in JSON) at a step whose truth has no value, which is not scored.
    #[serde(deserialize_with = "null_as_nan")]
    pub mse: Vec<f64>,
    pub mean_mse: Option<f64>,
    /// The final model's discrete-time eigenvalues `[re, im]`.
    pub eigenvalues: Vec<[f64; 2]>,
    /// Times each vehicle's liveliness token appeared (1: never lost).
    pub link_ups: BTreeMap<VehicleId, u64>,
    pub wall_s: f64,
    /// The server process's peak resident size (MiB, Linux's `VmHWM`), the mixed-reality truth
    /// it scores against included.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peak_resident_mib: Option<f64>,
    /// Seconds of the field's own time between steps (the time axis of `estimate.npy`).
    #[serde(default)]
    pub dt: f64,
    /// The boats' held-out readings against the estimate (`[scoring] holdout`; a run without
    /// a truth is scored this way).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout: Option<crate::protocol::HoldoutScore>,
    /// The boats' normalised innovation squared against the forecast at each boat step: the
    /// filter's own check of its reported variance, truth or not (`fusion = "kalman"`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub innovations: Vec<crate::holdout::StepInnovation>,
    /// Each vehicle's link traffic, as its last telemetry said (payload bytes by key).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub traffic: BTreeMap<VehicleId, crate::protocol::LinkTraffic>,
    /// Cells the truth has no value at in any frame (land): off the model grid, not scored.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub land_cells: usize,
    /// The model's skill by epoch (`fusion = "kalman"`): the forecast's against the aerials'
    /// lattice, and how far the map between the lattice follows the filter.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub skill: Vec<crate::protocol::EpochSkill>,
    /// Each instrument-fed vehicle's readings as its last telemetry said them (received,
    /// accepted, refused by kind, frames with no value).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub readings: BTreeMap<VehicleId, crate::protocol::ReadingCounts>,
    /// Every change of a sensor's verdict, and what the health tests did to the readings.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sensor_verdicts: Vec<crate::protocol::SensorVerdict>,
    #[serde(default)]
    pub screened: crate::health::Screened,
}

/// The mean of a run's per-step MSE over its scored steps (`None`: no step was scored).
pub fn mean_mse(mse: &[f64]) -> Option<f64> {
    (fleet_math::fusion::unscored(mse) < mse.len()).then(|| fleet_math::fusion::mean_scored(mse))
}

/// JSON's `null` as NaN: what serde_json writes for a NaN, read back as one.
fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    let v: Vec<Option<f64>> = serde::Deserialize::deserialize(d)?;
    Ok(v.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect())
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// The plans the server published, as `plans.json` keeps them (the boats' and aerials' places,
/// without the cells: what a ground station needs to draw or fly them).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PublishedPlans {
    /// Epochs each plan looks ahead.
    pub horizon: u64,
    pub plans: Vec<PlanPlaces>,
}

/// One vehicle's plan as published at `epoch`: where it senses at each sampling step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanPlaces {
    pub vehicle: crate::protocol::VehicleId,
    pub kind: crate::protocol::VehicleKind,
    pub epoch: u64,
    /// `(epoch, step, [x, y] grid metres, radius in cells)`; a radius of 0 senses nothing.
    pub targets: Vec<(u64, u64, [f64; 2], f64)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_by_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        let p = Percentiles::of(&v);
        assert_eq!((p.count, p.p50, p.p99, p.max), (100, 50.0, 99.0, 100.0));
        assert_eq!(Percentiles::of(&[]).p99, 0.0);
        assert_eq!(Percentiles::of(&[3.0]).p50, 3.0);
    }

    #[test]
    fn events_are_one_json_object_each() {
        let e = ServerEvent::Link {
            vehicle: "boat-1".parse::<VehicleId>().unwrap(),
            alive: true,
        };
        let line = serde_json::to_string(&e).unwrap();
        assert_eq!(line, r#"{"event":"link","vehicle":"boat-1","alive":true}"#);
        assert_eq!(serde_json::from_str::<ServerEvent>(&line).unwrap(), e);
    }
}
