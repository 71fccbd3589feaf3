//! A mission's logged readings assimilated after the fact (`fleet assimilate`): the vehicles'
//! brains and the server core, driven epoch by epoch as the fleet drives them, each vehicle's
//! batch made from its logged readings by the same steps its node takes (placed by the
//! mission's clock and site, averaged per step and cell, an aerial's frames seen from where it
//! was), so the same readings give the same batches and the same model as the live run did.
//!
//! What a live run decides that readings do not say is taken as the undisturbed run has it:
//! every vehicle gets its epoch's plan (none follows an old horizon for want of one) and none is
//! held out of the allocation. A run where that was not so made its batches under other plans;
//! `fleet replay` on its recording is the way to its exact model then.

use crate::config::MissionConfig;
use crate::instrument::{Collected, Placer, Reading, Refusal, Tally};
use crate::protocol::{VehicleId, VehicleKind};
use crate::server::{IngestError, ServerCore};
use crate::team::TeamError;
use crate::vehicle::{vehicle_rng, Fix, VehicleBrain};
use fleet_math::grid::Grid;
use std::collections::BTreeMap;

/// What was logged for one vehicle.
#[derive(Debug, Clone, Default)]
pub struct VehicleLog {
    /// Point readings, as the instrument said them.
    pub readings: Vec<Reading>,
    /// Frames on the model grid: their name, time (UTC seconds) and a value per cell.
    pub frames: Vec<(String, f64, Vec<Option<f64>>)>,
    /// Where an aerial was at its sampling steps (grid metres).
    pub fixes: BTreeMap<u64, (f64, f64)>,
}

/// What an offline run could not make work.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    #[error("{0}")]
    Team(#[from] TeamError),
    #[error("{0}")]
    Ingest(#[from] IngestError),
    #[error("the mission has no [time]: logged readings are placed by the mission's clock")]
    NoClock,
}

/// The server core after every epoch, and what was taken and refused of each vehicle's log.
pub struct Offline {
    pub core: ServerCore,
    pub tallies: BTreeMap<VehicleId, Tally>,
}

/// Assimilate `logs` (by vehicle id) on the mission's `grid` over `frames` steps; `progress`
/// sees each epoch done and the number of epochs.
pub fn run(
    mission: &MissionConfig,
    (grid, frames): (Grid, usize),
    logs: &BTreeMap<String, VehicleLog>,
    mut progress: impl FnMut(u64, u64),
) -> Result<Offline, OfflineError> {
    let placer = Placer {
        site: mission.mavlink.site(&grid),
        grid,
        fence: mission.team.fence.clone(),
        clock: mission.clock().ok_or(OfflineError::NoClock)?,
        frames: frames as u64,
    };
    let mut core = ServerCore::new(&mission.team, grid, frames)?
        .with_boat_speed(mission.motion.boat_speed)
        .with_holdout(mission.holdout_share());
    let mut brains = brains_of(mission, &core, grid);
    let empty = VehicleLog::default();
    let mut tallies = BTreeMap::new();
    let mut collected: Vec<Collected> = brains
        .iter()
        .map(|b| {
            let log = logs.get(b.id.as_str()).unwrap_or(&empty);
            let sigma = mission.noise(b.kind).sigma0;
            let (c, tally) = collect(&placer, log, b.first_sensed_step(), sigma);
            tallies.insert(b.id.clone(), tally);
            c
        })
        .collect();
    let (schedule, horizon) = (*core.schedule(), mission.pace.horizon);
    for e in 0..schedule.epochs() {
        let steps = schedule.steps_of(e);
        for (brain, readings) in brains.iter_mut().zip(&mut collected) {
            if schedule.seq_of(brain.kind, e).is_none() {
                continue;
            }
            if let Some(plan) = core.plan(&brain.id, e, horizon) {
                brain.set_plan(plan);
            }
            let samples = readings.take(steps.start as u64..steps.end as u64);
            let samples = match brain.kind {
                VehicleKind::Boat => samples,
                VehicleKind::Aerial => {
                    let fixes = fixes_of(logs.get(brain.id.as_str()).unwrap_or(&empty));
                    brain.seen_from_targets(e, samples, &fixes)
                }
            };
            if let Some(batch) = brain.batch_of(e, samples) {
                core.ingest(batch)?;
            }
        }
        progress(e + 1, schedule.epochs());
    }
    Ok(Offline { core, tallies })
}

/// Each vehicle's brain as its node makes it.
fn brains_of(mission: &MissionConfig, core: &ServerCore, grid: Grid) -> Vec<VehicleBrain> {
    core.vehicles()
        .iter()
        .map(|v| {
            VehicleBrain::new(
                &v.id,
                v.kind,
                grid,
                *core.schedule(),
                mission.noise(v.kind),
                vehicle_rng(mission.team.seed, v.index),
                mission.speed(v.kind),
            )
        })
        .collect()
}

/// A vehicle's log placed and kept by step and cell, as its node keeps them (readings before
/// its first sensed step are too old), and the tally of what was taken and refused.
fn collect(placer: &Placer, log: &VehicleLog, first: u64, sigma: f64) -> (Collected, Tally) {
    let (mut c, mut tally) = (Collected::default(), Tally::default());
    // Nothing logged is from the future of an offline run.
    let now = f64::INFINITY;
    let mut keep = |r: Result<(), (Refusal, String)>| match r {
        Ok(()) => tally.accept(),
        Err((kind, _)) => {
            tally.refuse(kind, 0.0);
        }
    };
    for r in &log.readings {
        keep(placer.place(r, now, first).map(|p| c.add(&p, sigma)));
    }
    for (_, t, values) in &log.frames {
        keep(
            placer
                .step_at(*t, now, first)
                .map(|k| c.add_frame(k, &placer.grid, values, sigma)),
        );
    }
    (c, tally)
}

fn fixes_of(log: &VehicleLog) -> BTreeMap<u64, Fix> {
    log.fixes
        .iter()
        .map(|(&k, &position)| {
            (
                k,
                Fix {
                    position,
                    arrived: true,
                },
            )
        })
        .collect()
}
