//! Sensors that fail, for the sensor-health study (`faults = [...]` in an experiment file):
//! one vehicle's readings altered from mid-mission the way a failing instrument alters them,
//! applied to its batches after it senses and before the server hears them (what a driver
//! feeding the vehicle would send), and the fleet run with and without the health tests
//! ([`mission::health`]) on the same truth and noise.

use super::stats::Interval;
use super::team::{self, TeamOutcome};
use crate::mission::health::Health;
use crate::mission::team::{TeamConfig, TeamError};
use crate::process::FieldSeries;
use crate::protocol::{MeasurementBatch, VehicleKind};
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// A sensor's failure. Sizes are in the vehicle's noise standard deviations (the row's).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, strum::Display, strum::EnumString,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case")]
pub enum FaultKind {
    /// A boat's calibration error: every value 3 noise standard deviations high.
    Bias,
    /// A boat's probe stuck: every value of a reading the first one of it (the disk reads one
    /// value throughout).
    Stuck,
    /// A fouled boat sensor: 2% of the values 50 standard deviations off (either sign).
    Spikes,
    /// A boat's sonde drifting: an offset growing linearly to 5 standard deviations by the end.
    Drift,
    /// An aerial camera over-exposed in 10% of its frames: every value of such a frame 20 of
    /// its noise standard deviations high.
    Overexposed,
    /// An aerial camera gone dark: from mid-mission each of its frames arrives with no cell (the
    /// vehicle flies on and reports, its camera sends nothing).
    Silent,
}

impl FaultKind {
    pub const ALL: [FaultKind; 6] = [
        Self::Bias,
        Self::Stuck,
        Self::Spikes,
        Self::Drift,
        Self::Overexposed,
        Self::Silent,
    ];

    /// The kind of vehicle that carries it (the first of that kind fails).
    pub fn kind(self) -> VehicleKind {
        match self {
            Self::Overexposed | Self::Silent => VehicleKind::Aerial,
            _ => VehicleKind::Boat,
        }
    }
}

/// One vehicle's failure from `from` (a step) to the last step `last`, with the vehicle's
/// noise `sigma`.
#[derive(Debug, Clone, Copy)]
pub struct Fault {
    pub kind: FaultKind,
    pub vehicle: usize,
    pub from: u64,
    pub last: u64,
    pub sigma: f64,
    pub seed: u64,
}

impl Fault {
    /// The first vehicle of the fault's kind fails from the middle of the mission.
    pub fn mid_mission(kind: FaultKind, cfg: &TeamConfig, frames: usize) -> Self {
        let (vehicle, sigma) = match kind.kind() {
            VehicleKind::Aerial => (0, cfg.aerial_sigma0),
            VehicleKind::Boat => (cfg.aerials, cfg.boat_sigma),
        };
        Self {
            kind,
            vehicle,
            from: frames as u64 / 2,
            last: frames.saturating_sub(1) as u64,
            sigma,
            seed: cfg.seed,
        }
    }

    /// The vehicle's batches as its failing instrument would have reported them; or, with
    /// `withhold`, without the readings the fault alters (what a health test that knew which
    /// readings were bad could at best do: the information the fault takes away).
    pub fn apply(
        &self,
        batches: &mut [MeasurementBatch],
        withhold: bool,
        vehicle_of: impl Fn(&MeasurementBatch) -> usize,
    ) {
        for b in batches.iter_mut().filter(|b| vehicle_of(b) == self.vehicle) {
            for s in b.samples.iter_mut() {
                match withhold || self.kind == FaultKind::Silent {
                    // The reading of no cell a vehicle off the site sends (a batch holds every step).
                    true if self.alters(s.step) => (s.cells, s.values, s.sigma) = (vec![], vec![], None),
                    true => {}
                    false => self.alter(s.step, &mut s.values),
                }
            }
        }
    }

    /// Whether the instrument sends nothing at `step` (a camera gone dark).
    pub fn silences(&self, step: u64) -> bool {
        self.kind == FaultKind::Silent && step >= self.from
    }

    /// Whether the fault alters the reading of `step` (an over-exposure only some frames).
    fn alters(&self, step: u64) -> bool {
        step >= self.from && (self.kind != FaultKind::Overexposed || self.rng(step).random_bool(0.1))
    }

    /// The fault's draws at `step` (the same in every run of the seed).
    fn rng(&self, step: u64) -> rand_chacha::ChaCha8Rng {
        rand_chacha::ChaCha8Rng::seed_from_u64(self.seed ^ step.wrapping_mul(0x9e37_79b9))
    }

    /// One reading's values at `step` as the failing instrument reports them (as they are
    /// before the fault's step): what [`Self::apply`] does to each sample of a batch, and what
    /// the tests' instrument emulator sends through a sensor's own interface (UDP, a camera's
    /// GeoTIFF, MAVLink). A stuck probe repeats the reading's first value; a dark camera's
    /// values are left alone (it sends nothing: [`Self::silences`]).
    pub fn alter(&self, step: u64, values: &mut [f64]) {
        if step < self.from {
            return;
        }
        let mut rng = self.rng(step);
        let sd = self.sigma;
        match self.kind {
            FaultKind::Bias => values.iter_mut().for_each(|v| *v += 3.0 * sd),
            FaultKind::Stuck => {
                let first = values.first().copied().unwrap_or(0.0);
                values.iter_mut().for_each(|v| *v = first);
            }
            FaultKind::Spikes => values.iter_mut().for_each(|v| {
                if rng.random_bool(0.02) {
                    *v += if rng.random_bool(0.5) { 50.0 } else { -50.0 } * sd;
                }
            }),
            FaultKind::Drift => {
                let span = (self.last.saturating_sub(self.from)).max(1) as f64;
                let offset = 5.0 * sd * (step - self.from) as f64 / span;
                values.iter_mut().for_each(|v| *v += offset);
            }
            FaultKind::Overexposed => {
                if rng.random_bool(0.1) {
                    values.iter_mut().for_each(|v| *v += 20.0 * sd);
                }
            }
            FaultKind::Silent => {}
        }
    }
}

/// One fault's runs of one seed: the fused MSE with the health tests, without them, and with
/// the altered readings withheld (the floor a test can reach), and how many boat epochs after
/// the fault's start the faulty sensor was first marked (`None`: never).
#[derive(Debug, Clone, Serialize)]
pub struct FaultRun {
    pub with_health: f64,
    pub without_health: f64,
    pub withheld: f64,
    pub marked_after_epochs: Option<f64>,
}

/// Every fault of `kinds` on the QR team `cfg` (whose healthy run is the caller's).
pub fn run_faults(
    cfg: &TeamConfig,
    truth: &FieldSeries,
    kinds: &[FaultKind],
) -> Result<Vec<(FaultKind, FaultRun)>, TeamError> {
    kinds
        .iter()
        .map(|&kind| {
            let fault = Fault::mid_mission(kind, cfg, truth.frames());
            let with = team::run_with_fault(cfg, truth, &fault, false)?;
            let without = team::run_with_fault(
                &TeamConfig {
                    sensor_health: false,
                    ..cfg.clone()
                },
                truth,
                &fault,
                false,
            )?;
            let withheld = team::run_with_fault(cfg, truth, &fault, true)?;
            let marked = first_marked(&with, &fault, cfg);
            Ok((
                kind,
                FaultRun {
                    with_health: with.mean_heterogeneous,
                    without_health: without.mean_heterogeneous,
                    withheld: withheld.mean_heterogeneous,
                    marked_after_epochs: marked,
                },
            ))
        })
        .collect()
}

/// Epochs (of `boat_period` steps) from the fault's start to the first verdict on its vehicle.
fn first_marked(out: &TeamOutcome, fault: &Fault, cfg: &TeamConfig) -> Option<f64> {
    out.verdicts
        .iter()
        .find(|v| v.vehicle == fault.vehicle && v.step >= fault.from && v.to != Health::Ok)
        .map(|v| (v.step - fault.from) as f64 / cfg.boat_period.max(1) as f64)
}

/// One fault over a row's seeds: the fused MSE with the health tests and without them as a
/// ratio to the healthy fleet's (per seed, on the same truth and noise: mean with its 95%
/// interval), and when the faulty sensor was marked.
#[derive(Debug, Clone, Serialize)]
pub struct FaultSummary {
    pub fault: FaultKind,
    pub with_health: Interval,
    pub without_health: Interval,
    /// (with - healthy) / healthy, (without - healthy) / healthy and (withheld - healthy) /
    /// healthy, per seed.
    pub cost_with: Interval,
    pub cost_without: Interval,
    pub cost_withheld: Interval,
    /// Seeds where the faulty sensor was marked within 3 boat epochs of the fault's start, of
    /// all seeds; and the median epochs to the mark over the seeds it was marked in.
    pub marked_within_3: usize,
    pub seeds: usize,
    pub median_epochs_to_mark: Option<f64>,
}

/// Every fault of a row, from its seeds' runs and the healthy QR team's MSE per seed.
pub fn summarise(healthy: &[f64], runs: &[&BTreeMap<FaultKind, FaultRun>]) -> Vec<FaultSummary> {
    let Some(first) = runs.first() else { return vec![] };
    first
        .keys()
        .map(|&fault| {
            let of = |f: fn(&FaultRun) -> f64| runs.iter().map(|r| f(&r[&fault])).collect::<Vec<f64>>();
            let (with, without) = (of(|r| r.with_health), of(|r| r.without_health));
            let cost = |v: &[f64]| Interval::of(&v.iter().zip(healthy).map(|(x, h)| (x - h) / h).collect::<Vec<_>>());
            let mut marks: Vec<f64> = runs.iter().filter_map(|r| r[&fault].marked_after_epochs).collect();
            marks.sort_by(f64::total_cmp);
            FaultSummary {
                fault,
                with_health: Interval::of(&with),
                without_health: Interval::of(&without),
                cost_with: cost(&with),
                cost_without: cost(&without),
                cost_withheld: cost(&of(|r| r.withheld)),
                marked_within_3: marks.iter().filter(|&&m| m <= 3.0).count(),
                seeds: runs.len(),
                median_epochs_to_mark: marks.get(marks.len() / 2).copied(),
            }
        })
        .collect()
}

/// The report's table of one row's faults.
pub fn table(md: &mut String, row: &str, faults: &[FaultSummary]) -> std::fmt::Result {
    use std::fmt::Write as _;
    for f in faults {
        let pct = |i: &Interval| format!("{:+.1}% [{:+.1}, {:+.1}]", 100.0 * i.mean, 100.0 * i.lo, 100.0 * i.hi);
        writeln!(
            md,
            "| {row} | {} | {:.3e} | {} | {:.3e} | {} | {} | {}/{} | {} |",
            f.fault,
            f.with_health.mean,
            pct(&f.cost_with),
            f.without_health.mean,
            pct(&f.cost_without),
            pct(&f.cost_withheld),
            f.marked_within_3,
            f.seeds,
            f.median_epochs_to_mark.map_or("never".into(), |m| format!("{m:.1}")),
        )?;
    }
    Ok(())
}
