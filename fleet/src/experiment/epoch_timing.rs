//! The model server's epoch at scale, without the network: the core driven by the vehicles
//! as the vehicle node runs them on a moving plume, and each epoch timed from the batch that
//! completes it to the published model handed out (beside the placement, as the node's is), and
//! to every vehicle's next plan answered too (the critical paths of issue 40, less Zenoh and
//! the files but for the fused map's, which the server writes step by step). Timings for
//! `fleet bench epoch`.

use super::team::{TeamConfig, TeamError};
use fleet_math::grid::Grid;
use fleet_math::process::synthetic::plume_frame;
use fleet_mission::protocol::{self, Body};
use fleet_mission::server::{Ingested, ServerCore};
use serde::Serialize;
use std::time::Instant;

#[derive(Debug, Clone, Serialize)]
pub struct EpochTiming {
    pub grid: [usize; 2],
    pub aerials: usize,
    pub boats: usize,
    /// Epochs timed (the first, the initial fit, is reported apart).
    pub epochs: usize,
    pub first_fit_ms: f64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    /// Each timed epoch's milliseconds, in order (where a slow one falls).
    pub epoch_ms: Vec<f64>,
    /// From the same batch to the model handed to the publisher (as the node's is: beside the
    /// placement, so before the plans): what observers wait, and the latency.
    pub model_p50_ms: f64,
    pub model_p99_ms: f64,
    pub model_epoch_ms: Vec<f64>,
    /// Each timed epoch's minor page faults (the whole process: memory first touched).
    pub epoch_faults: Vec<u64>,
    /// Bytes of the model put every epoch (without its modes), of the whole model a get
    /// answers, and of every batch of an epoch (mean), on the wire.
    pub model_bytes: usize,
    pub model_full_bytes: usize,
    pub batch_bytes_per_epoch: f64,
    /// The process's peak resident size so far (kB, Linux's VmHWM; no truth is held, as in the
    /// model server: each frame is made when it is sampled).
    pub peak_resident_kb: Option<u64>,
    /// Mean milliseconds an epoch in each phase (the core's `tracing` spans, nested spans
    /// counted in their parents too), over the timed epochs.
    pub phases_ms: Vec<(String, f64)>,
}

/// The team scaled with the grid as `fleet up` missions are (`radius` and the default
/// mission's aerial stride at 48 x 96, times rows / 48).
fn team(rows: usize, aerials: usize, boats: usize, radius: f64) -> TeamConfig {
    let scale = (rows as f64 / 48.0).max(1.0);
    TeamConfig {
        aerials,
        boats,
        radius: radius * scale,
        aerial_stride: (5.0 * scale).round() as usize,
        ..TeamConfig::default()
    }
}

/// How big a team, and its boats' radius at 48 x 96 (the default mission's is 10).
#[derive(Debug, Clone, Copy)]
pub struct Fleet {
    pub aerials: usize,
    pub boats: usize,
    pub radius: f64,
}

/// Run `epochs` boat epochs at `rows x cols` and time each, and each phase of each.
pub fn run(rows: usize, cols: usize, fleet: Fleet, epochs: usize) -> Result<EpochTiming, TeamError> {
    let phases = super::phases::Phases::default();
    let mut timing =
        tracing::subscriber::with_default(phases.subscriber(), || timed(rows, cols, fleet, epochs, &phases))?;
    let per_epoch = timing.epochs.max(1) as f64;
    timing.phases_ms = phases
        .totals()
        .into_iter()
        .map(|(name, d)| (name, d.as_secs_f64() * 1e3 / per_epoch))
        .collect();
    Ok(timing)
}

fn timed(
    rows: usize,
    cols: usize,
    fleet: Fleet,
    epochs: usize,
    phases: &super::phases::Phases,
) -> Result<EpochTiming, TeamError> {
    let Fleet { aerials, boats, radius } = fleet;
    let cfg = team(rows, aerials, boats, radius);
    let frames = cfg.init_steps + epochs * cfg.boat_period + 1;
    // Each frame made when it is first sampled and kept for the epoch's other vehicles (the
    // newest steps only), as the model server holds no truth of its own (a node reads its truth
    // a frame at a time): the peak resident size is the core's.
    let grid = Grid::new(rows, cols, 1.0)?;
    let made = std::cell::RefCell::new(std::collections::BTreeMap::new());
    let x = |k: usize| -> Vec<f64> {
        let mut made = made.borrow_mut();
        let newest = made.keys().next_back().map_or(k, |&j: &usize| j.max(k));
        made.retain(|&j, _| j + cfg.boat_period >= newest);
        made.entry(k)
            .or_insert_with(|| plume_frame(rows, cols, frames, k))
            .clone()
    };
    // As the model server keeps it: every step's fused map in files, not in memory.
    let dir = run_dir();
    // As the node's: each epoch's model handed over the moment it is made (here to nobody).
    let mut server = ServerCore::new(&cfg, grid, frames)?
        .with_history_in(&dir)?
        .with_publisher(std::sync::Arc::new(|_| ()));
    let mut brains = super::team::brains_of(&server, &cfg, grid);
    let (mut timed, mut batch_bytes) = (vec![], 0usize);
    for e in 0..server.schedule().epochs() {
        let mut batches = vec![];
        for brain in brains.iter_mut() {
            let plan = server.plan(&brain.id, e, 2);
            brain.set_plan(plan.ok_or(TeamError::NotReady(fleet_mission::team::Missing::Plan { epoch: e }))?);
            batches.extend(brain.sense_epoch(e, x)?);
        }
        batch_bytes += batches
            .iter()
            .map(|b| protocol::encode(&Body::Batch(b.clone())).len())
            .sum::<usize>();
        timed.push(time_epoch(&mut server, batches, e)?);
        if e == 0 {
            phases.reset();
        }
    }
    // The whole model, its modes in, as a get is answered: encoded once, off the epochs' path.
    let model_full_bytes = server.take_published().map_or(0, |m| m.full().len());
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
    let first = timed.remove(0);
    let model_bytes = timed.last().map_or(first.model_bytes, |t| t.model_bytes);
    let times: Vec<f64> = timed.iter().map(|t| t.ms).collect();
    let model_times: Vec<f64> = timed.iter().map(|t| t.model_ms).collect();
    let first_fit_ms = first.ms;
    let faults: Vec<u64> = timed.iter().map(|t| t.faults).collect();
    let n = times.len();
    let pct = |p: f64| percentile(&times, p);
    Ok(EpochTiming {
        grid: [rows, cols],
        aerials,
        boats,
        epochs: n,
        first_fit_ms,
        p50_ms: pct(0.5),
        p99_ms: pct(0.99),
        epoch_ms: times,
        model_p50_ms: percentile(&model_times, 0.5),
        model_p99_ms: percentile(&model_times, 0.99),
        model_epoch_ms: model_times,
        epoch_faults: faults,
        model_bytes,
        model_full_bytes,
        batch_bytes_per_epoch: batch_bytes as f64 / (n + 1) as f64,
        peak_resident_kb: fleet_mission::memory::peak_resident_kb(),
        phases_ms: vec![],
    })
}

/// One epoch's figures, from the batch that completes it.
struct EpochTimes {
    /// To the model out and every vehicle's next plan encoded.
    ms: f64,
    /// To the model handed to the publisher.
    model_ms: f64,
    faults: u64,
    model_bytes: usize,
}

/// Ingest epoch `e`'s `batches` and time the last one's epoch: as the node publishes the model
/// (handed over beside the placement, or made now if it was not), then the plans.
fn time_epoch(
    server: &mut ServerCore,
    batches: Vec<protocol::MeasurementBatch>,
    e: u64,
) -> Result<EpochTimes, TeamError> {
    let (mut t0, mut f0) = (Instant::now(), minor_faults());
    for b in batches {
        (t0, f0) = (Instant::now(), minor_faults());
        let taken = server.ingest(b).map_err(|err| TeamError::Config(err.to_string()))?;
        if matches!(taken, Ingested::Assimilated(_)) {
            break;
        }
    }
    let model = server.take_published();
    let out = model.as_ref().and_then(|m| m.handed_out).unwrap_or_else(Instant::now);
    let model_bytes = model.as_ref().map_or(0, |m| m.bytes.len());
    model.into_iter().for_each(|m| server.keep_published(m));
    tracing::info_span!("plans encoded").in_scope(|| {
        for v in server.vehicles().to_vec() {
            let plan = server.plan(&v.id, e + 1, 3).map(|p| protocol::encode(&Body::Plan(p)));
            std::hint::black_box(plan);
        }
    });
    Ok(EpochTimes {
        ms: t0.elapsed().as_secs_f64() * 1e3,
        model_ms: out.saturating_duration_since(t0).as_secs_f64() * 1e3,
        faults: minor_faults() - f0,
        model_bytes,
    })
}

/// A directory for one run's history files (two runs of one process side by side do not share
/// their files).
fn run_dir() -> std::path::PathBuf {
    static RUNS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let run = RUNS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    std::env::temp_dir().join(format!("hetfleet-bench-epoch-{}-{run}", std::process::id()))
}

/// The `p` quantile of `times`: the smallest value at least a share `p` of them reach (the
/// largest, for p99 of fewer than 100).
fn percentile(times: &[f64], p: f64) -> f64 {
    let mut t = times.to_vec();
    t.sort_by(f64::total_cmp);
    let n = t.len();
    t.get(((p * n as f64).ceil() as usize).clamp(1, n.max(1)) - 1)
        .copied()
        .unwrap_or(f64::NAN)
}

/// Minor page faults of this process so far (every thread's).
fn minor_faults() -> u64 {
    // SAFETY: getrusage writes the struct it is given and nothing else.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
        return 0;
    }
    usage.ru_minflt as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fault_count_sees_memory_first_touched() {
        // 32 MB written: 8,192 faults in 4 kB pages, 16 if the kernel gives 2 MB ones.
        let before = minor_faults();
        let touched = vec![1u8; 32 << 20];
        std::hint::black_box(&touched);
        assert!(minor_faults() - before >= 16, "{} faults", minor_faults() - before);
    }

    #[test]
    fn every_timed_epoch_has_its_time_and_its_faults() {
        let fleet = Fleet {
            aerials: 1,
            boats: 2,
            radius: 10.0,
        };
        let t = run(24, 48, fleet, 2).unwrap();
        assert!(t.epochs >= 2, "{} epochs", t.epochs);
        assert_eq!((t.epoch_ms.len(), t.epoch_faults.len()), (t.epochs, t.epochs));
        assert!(t.p50_ms > 0.0 && t.p99_ms >= t.p50_ms && t.model_bytes > 0);
        // The model goes out before the plans are answered, never after.
        assert_eq!(t.model_epoch_ms.len(), t.epochs);
        assert!(t.model_epoch_ms.iter().zip(&t.epoch_ms).all(|(m, e)| m <= e));
    }
}
