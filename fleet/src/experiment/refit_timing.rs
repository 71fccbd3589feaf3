//! The cost of a late batch: a long mission whose boat comes back from an outage at the end,
//! re-fitted from the newest checkpoint before its first late epoch, against a re-fit from
//! epoch 0 (the server without checkpoints). Timings for `fleet bench refit`.

use super::team::{TeamConfig, TeamError};
use fleet_math::grid::Grid;
use fleet_math::process::synthetic::plume_field;
use fleet_mission::server::ServerCore;
use fleet_mission::vehicle::VehicleBrain;
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct RefitTiming {
    pub epochs: u64,
    pub late_epochs: u64,
    pub grid: [usize; 2],
    /// Seconds of the one re-fit the backlog causes, and epochs it assimilated again.
    pub with_checkpoints_s: f64,
    pub with_checkpoints_epochs: u64,
    pub from_epoch_0_s: f64,
    pub from_epoch_0_epochs: u64,
    /// The two re-fitted models are the same (eigenvalues equal bit for bit).
    pub same_model: bool,
}

/// Run a mission of `epochs` boat epochs on a moving plume (`rows x cols`, the default team)
/// with boat-2 away for its last `late` epochs, twice (checkpoints on, off), and time the
/// re-fit its backlog causes.
pub fn run(rows: usize, cols: usize, epochs: usize, late: u64) -> Result<RefitTiming, TeamError> {
    let cfg = TeamConfig::default();
    let frames = cfg.init_steps + epochs * cfg.boat_period;
    let truth = plume_field(rows, cols, frames, 0.0, 3);
    let grid = Grid::new(rows, cols, 1.0)?;
    let x = |k: usize| -> Vec<f64> { truth.snapshots.col(k).iter().copied().collect() };
    let mut out = vec![];
    for checkpoints in [true, false] {
        let server = ServerCore::new(&cfg, grid, frames)?;
        let mut server = if checkpoints {
            server
        } else {
            server.without_checkpoints()
        };
        let last = server.schedule().epochs();
        let mut brains = crate::experiment::team::brains_of(&server, &cfg, grid);
        run_with_boat_2_away(&mut server, &mut brains, last, late, &x)?;
        let before = server.counters.refit_epochs;
        let t0 = std::time::Instant::now();
        server.settle()?;
        out.push((
            t0.elapsed().as_secs_f64(),
            server.counters.refit_epochs - before,
            server.model_update().map(|m| m.eigenvalues).unwrap_or_default(),
        ));
    }
    Ok(RefitTiming {
        epochs: epochs as u64,
        late_epochs: late,
        grid: [rows, cols],
        with_checkpoints_s: out[0].0,
        with_checkpoints_epochs: out[0].1,
        from_epoch_0_s: out[1].0,
        from_epoch_0_epochs: out[1].1,
        same_model: out[0].2 == out[1].2,
    })
}

/// The mission to its last epoch with boat-2 away for `late` epochs before it (its epochs
/// assimilated without it), then its backlog in: the re-fit is due.
fn run_with_boat_2_away(
    server: &mut ServerCore,
    brains: &mut [VehicleBrain],
    last: u64,
    late: u64,
    x: &impl Fn(usize) -> Vec<f64>,
) -> Result<(), TeamError> {
    let away = (last - 1 - late)..(last - 1);
    let mut backlog = vec![];
    for e in 0..last {
        for brain in brains.iter_mut() {
            let gone = brain.id == "boat-2" && away.contains(&e);
            if !gone {
                let plan = server.plan(&brain.id, e, late + 1);
                brain.set_plan(plan.ok_or(TeamError::NotReady(fleet_mission::team::Missing::Plan { epoch: e }))?);
            }
            let Some(b) = brain.sense_epoch(e, x)? else { continue };
            if gone {
                backlog.push(b);
            } else {
                server.ingest(b).map_err(|err| TeamError::Config(err.to_string()))?;
            }
        }
        if away.contains(&e) {
            server.force()?;
        }
    }
    for b in backlog {
        server
            .ingest_deferred(b)
            .map_err(|err| TeamError::Config(err.to_string()))?;
    }
    Ok(())
}
