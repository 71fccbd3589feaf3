//! Sensors that fail, for the sensor-health study (`faults = [...]` in an experiment file):
//! one vehicle's readings altered from mid-mission the way a failing instrument alters them,
//! applied to its batches after it senses and before the server hears them (what a driver
//! feeding the vehicle would send), and the fleet run with and without the health tests
//! ([`fleet_mission::health`]) on the same truth and noise.

use super::stats::Interval;
use super::team::{self, TeamOutcome};
use fleet_math::process::FieldSeries;
use fleet_mission::health::Health;
use fleet_mission::protocol::{MeasurementBatch, VehicleKind};
use fleet_mission::team::{TeamConfig, TeamError};
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

/// A sensor's failure. Sizes are in the vehicle's noise standard deviations (the row's).
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
    strum::Display,
    strum::EnumString,
    schemars::JsonSchema,
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
    /// readings were bad could at best do: the information the fault takes away). The steps
    /// whose readings it changed or took away.
    pub fn apply(
        &self,
        batches: &mut [MeasurementBatch],
        withhold: bool,
        vehicle_of: impl Fn(&MeasurementBatch) -> usize,
    ) -> BTreeSet<u64> {
        let mut altered = BTreeSet::new();
        for b in batches.iter_mut().filter(|b| vehicle_of(b) == self.vehicle) {
            for s in b.samples.iter_mut() {
                let changed = match withhold || self.kind == FaultKind::Silent {
                    // The reading of no cell a vehicle off the site sends (a batch holds every step).
                    true if self.alters(s.step) => {
                        let had = !s.cells.is_empty();
                        (s.cells, s.values, s.sigma) = (vec![], vec![], None);
                        had
                    }
                    true => false,
                    false => {
                        let before = s.values.clone();
                        self.alter(s.step, &mut s.values);
                        s.values != before
                    }
                };
                if changed {
                    altered.insert(s.step);
                }
            }
        }
        altered
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
            FaultKind::Bias | FaultKind::Drift => {
                let offset = self.offset(step);
                values.iter_mut().for_each(|v| *v += offset);
            }
            FaultKind::Stuck => {
                let first = values.first().copied().unwrap_or(0.0);
                values.iter_mut().for_each(|v| *v = first);
            }
            FaultKind::Spikes => values.iter_mut().for_each(|v| {
                if rng.random_bool(0.02) {
                    *v += if rng.random_bool(0.5) { 50.0 } else { -50.0 } * sd;
                }
            }),
            FaultKind::Overexposed => {
                if rng.random_bool(0.1) {
                    values.iter_mut().for_each(|v| *v += 20.0 * sd);
                }
            }
            FaultKind::Silent => {}
        }
    }
}

impl Fault {
    /// The offset a bias or a drift adds to every value at `step` (0 before the fault, and for
    /// the other kinds).
    fn offset(&self, step: u64) -> f64 {
        let after = step.saturating_sub(self.from) as f64;
        match (self.kind, step >= self.from) {
            (FaultKind::Bias, true) => 3.0 * self.sigma,
            (FaultKind::Drift, true) => 5.0 * self.sigma * after / (self.last.saturating_sub(self.from)).max(1) as f64,
            _ => 0.0,
        }
    }

    /// The chance that a test that knew the fault (its kind, size, sign and start) would have
    /// marked the sensor by step `by`, from what the readings `out` received held of it: an
    /// upper bound on any test's chance at [`ALPHA`] false alarms a look. An offset (bias,
    /// drift) is seen only through the boat's differences from the aerials at the lattice cells
    /// both measured (the field unknown elsewhere): with `W_t` the information of the
    /// difference's weighted mean at step `t` and `mu_t` the offset, the best test (Neyman-
    /// Pearson, one look at `by`, sign known) has power `Phi(sqrt(sum mu_t^2 W_t) - z_ALPHA)`.
    /// A stuck probe, a spike, an over-exposed frame or a dark camera is unmistakable once it
    /// happens, and indistinguishable from a healthy sensor before: 1 if a reading it altered
    /// arrived by `by`, else 0.
    pub fn knowable(&self, out: &TeamOutcome, by: u64) -> f64 {
        match self.kind {
            FaultKind::Bias | FaultKind::Drift => {
                let lambda: f64 = out
                    .information
                    .range((self.vehicle, self.from)..=(self.vehicle, by))
                    .map(|(&(_, t), &w)| self.offset(t).powi(2) * w)
                    .sum();
                normal_cdf(lambda.sqrt() - Z_ALPHA)
            }
            _ if out.altered.range(self.from..=by).next().is_some() => 1.0,
            _ => 0.0,
        }
    }
}

/// False alarms a look of [`Fault::knowable`]'s test: the healthy fleets' rate a sensor-step
/// (3.6e-4) over the 3 boat steps of its window, about.
pub const ALPHA: f64 = 1e-3;
/// The one-sided normal quantile of `1 - ALPHA`.
const Z_ALPHA: f64 = 3.090_232_306_167_813;

/// The standard normal's distribution function.
fn normal_cdf(x: f64) -> f64 {
    0.5 * libm::erfc(-x / std::f64::consts::SQRT_2)
}

/// [`team::run`] with `fault`'s sensor failing; with `withhold`, its altered readings withheld
/// instead.
fn run_with(cfg: &TeamConfig, truth: &FieldSeries, fault: &Fault, withhold: bool) -> Result<TeamOutcome, TeamError> {
    team::run_altered(cfg, truth, &|batches, vehicle_of| {
        fault.apply(batches, withhold, vehicle_of)
    })
}

/// Boat epochs after a fault's start within which its sensor counts as marked in time.
pub const WITHIN: u64 = 3;

/// One fault's runs of one seed: the fused MSE with the health tests, without them, and with
/// the altered readings withheld (the floor a test can reach), and how many boat epochs after
/// the fault's start the faulty sensor was first marked (`None`: never).
#[derive(Debug, Clone, Serialize)]
pub struct FaultRun {
    pub with_health: f64,
    pub without_health: f64,
    pub withheld: f64,
    pub marked_after_epochs: Option<f64>,
    /// The chance a test that knew the fault could have marked it within [`WITHIN`] boat epochs
    /// ([`Fault::knowable`]).
    pub knowable_in_time: f64,
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
            let with = run_with(cfg, truth, &fault, false)?;
            let without = run_with(
                &TeamConfig {
                    sensor_health: false,
                    ..cfg.clone()
                },
                truth,
                &fault,
                false,
            )?;
            let withheld = run_with(cfg, truth, &fault, true)?;
            let marked = first_marked(&with, &fault, cfg);
            let knowable = fault.knowable(&with, fault.from + WITHIN * cfg.boat_period.max(1) as u64);
            Ok((
                kind,
                FaultRun {
                    with_health: with.mean_heterogeneous,
                    without_health: without.mean_heterogeneous,
                    withheld: withheld.mean_heterogeneous,
                    marked_after_epochs: marked,
                    knowable_in_time: knowable,
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
    /// The seeds a test that knew the fault could have marked it in, expected ([`Fault::knowable`]).
    pub knowable_within_3: f64,
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
                marked_within_3: marks.iter().filter(|&&m| m <= WITHIN as f64).count(),
                knowable_within_3: of(|r| r.knowable_in_time).iter().sum(),
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
            "| {row} | {} | {:.3e} | {} | {:.3e} | {} | {} | {}/{} | {:.1} | {} |",
            f.fault,
            f.with_health.mean,
            pct(&f.cost_with),
            f.without_health.mean,
            pct(&f.cost_without),
            pct(&f.cost_withheld),
            f.marked_within_3,
            f.seeds,
            f.knowable_within_3,
            f.median_epochs_to_mark.map_or("never".into(), |m| format!("{m:.1}")),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fault(kind: FaultKind) -> Fault {
        Fault {
            kind,
            vehicle: 2,
            from: 10,
            last: 20,
            sigma: 0.5,
            seed: 1,
        }
    }

    /// Known answers: a bias whose offsets' information is exactly `z_ALPHA^2` is found by the
    /// best test half the time (and one twice as informative more often, a steady sensor's
    /// information before the fault or another vehicle's counting nothing); a drift's offset
    /// grows from 0, so its first step after the start tells nothing; a spike is knowable once
    /// a reading it altered has arrived, not before.
    #[test]
    fn what_a_test_that_knew_the_fault_could_see() {
        let mut out = TeamOutcome::default();
        let bias = fault(FaultKind::Bias);
        // mu = 1.5: mu^2 W = z^2 at W = (z / 1.5)^2, the information at step 12.
        out.information.insert((2, 12), (Z_ALPHA / 1.5).powi(2));
        out.information.insert((2, 9), 1e6);
        out.information.insert((3, 12), 1e6);
        assert!((bias.knowable(&out, 15) - 0.5).abs() < 1e-12);
        assert_eq!(bias.knowable(&out, 11), normal_cdf(-Z_ALPHA));
        assert!((normal_cdf(-Z_ALPHA) - ALPHA).abs() < 1e-15);
        out.information.insert((2, 13), (Z_ALPHA / 1.5).powi(2));
        assert!((bias.knowable(&out, 15) - normal_cdf((2.0f64.sqrt() - 1.0) * Z_ALPHA)).abs() < 1e-12);
        let drift = fault(FaultKind::Drift);
        let mut out = TeamOutcome::default();
        out.information.insert((2, 10), 1e6);
        assert_eq!(drift.knowable(&out, 10), normal_cdf(-Z_ALPHA));
        out.information.insert((2, 20), 1.0);
        // At the last step the drift is 5 sd = 2.5: lambda = 6.25.
        assert!((drift.knowable(&out, 20) - normal_cdf(2.5 - Z_ALPHA)).abs() < 1e-12);
        let spikes = fault(FaultKind::Spikes);
        let mut out = TeamOutcome::default();
        out.altered.insert(14);
        assert_eq!((spikes.knowable(&out, 13), spikes.knowable(&out, 14)), (0.0, 1.0));
    }

    /// The steps [`Fault::apply`] reports are those whose readings it changed: a bias every
    /// step from the start, an over-exposure only its frames.
    #[test]
    fn apply_reports_the_steps_it_altered() {
        use fleet_mission::protocol::{Noise, Sample, VehicleId};
        let batch = |vehicle: &str| MeasurementBatch {
            vehicle: vehicle.parse::<VehicleId>().unwrap(),
            kind: VehicleKind::Boat,
            seq: 0,
            noise: Noise {
                sigma0: 0.5,
                growth_per_m: 0.0,
            },
            samples: (0..20)
                .map(|step| Sample {
                    step,
                    position: [0.0, 0.0],
                    cells: vec![1, 2, 3],
                    values: vec![0.1, 0.2, 0.3],
                    sigma: None,
                })
                .collect(),
        };
        let mut batches = vec![batch("boat-0"), batch("boat-1")];
        let vehicle_of = |b: &MeasurementBatch| usize::from(b.vehicle == *"boat-0") + 1;
        let altered = fault(FaultKind::Bias).apply(&mut batches, false, vehicle_of);
        assert_eq!(altered, (10..20).collect());
        assert_eq!(batches[1].samples[15].values, vec![0.1, 0.2, 0.3]);
        let over = Fault {
            kind: FaultKind::Overexposed,
            ..fault(FaultKind::Bias)
        };
        let altered = over.apply(&mut batches, false, vehicle_of);
        assert!(altered.len() < 10 && altered.iter().all(|&s| s >= 10));
    }
}
