//! The model server's core driven offline, without a network: the mission's vehicles sense its
//! truth under the core's plans, epoch by epoch, and the core assimilates their batches, as
//! `fleet up`'s nodes do over Zenoh (and `fleet experiment` does for its teams). It prints each
//! epoch's mean squared error against the truth.
//!
//! `offline_core <mission.toml>`: a mission with a `[truth]` (the bundled
//! `config/mission-tiny.toml` takes a few seconds). Exit 0 when every epoch is assimilated,
//! 2 when the mission cannot run (its one line says why).

use fleet_math::fusion::AerialNoise;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::VehicleKind;
use fleet_mission::server::ServerCore;
use fleet_mission::vehicle::{vehicle_rng, VehicleBrain};

fn main() {
    if let Err(e) = run() {
        fleet_exit::fail("offline_core", &e);
    }
}

fn run() -> anyhow::Result<()> {
    let path = std::env::args()
        .nth(1)
        .ok_or_else(|| fleet_exit::bad_input(anyhow::anyhow!("usage: offline_core <mission.toml>")))?;
    let mission = MissionConfig::load(Some(std::path::Path::new(&path)))?;
    let truth = mission
        .truth(|_| {})?
        .ok_or_else(|| fleet_exit::bad_input(anyhow::anyhow!("{path}: this example needs a [truth] to sense")))?;
    let (grid, frames) = mission.workspace(Some(truth.shape()))?;
    let team = &mission.team;
    let mut core = ServerCore::new(team, grid, frames)?;
    // Each vehicle as its node runs it, with its own random stream (its sensor noise).
    let mut brains: Vec<VehicleBrain> = core
        .vehicles()
        .iter()
        .enumerate()
        .map(|(v, spec)| {
            let noise = match spec.kind {
                VehicleKind::Aerial => core.assimilator().aerial_noise(),
                VehicleKind::Boat => AerialNoise {
                    sigma0: team.boat_sigma,
                    growth_per_m: 0.0,
                },
            };
            let rng = vehicle_rng(team.seed, v);
            VehicleBrain::new(&spec.id, spec.kind, grid, *core.schedule(), noise, rng, f64::MAX)
        })
        .collect();
    let truth_at = |k: usize| truth.snapshots.col(k).iter().copied().collect::<Vec<f64>>();
    for e in 0..core.schedule().epochs() {
        for brain in &mut brains {
            let plan = core
                .plan(&brain.id, e, 1)
                .ok_or_else(|| anyhow::anyhow!("no plan of {} for epoch {e}", brain.id))?;
            brain.set_plan(plan);
            if let Some(batch) = brain.sense_epoch(e, truth_at)? {
                core.ingest(batch)?;
            }
        }
        let steps = core.steps_of(e);
        let mse: f64 = steps
            .clone()
            .map(|k| {
                let estimate = core.history().estimate(k)?;
                let t = truth_at(k);
                let cells = t.iter().filter(|x| !x.is_nan()).count().max(1);
                let sum: f64 = estimate
                    .iter()
                    .zip(&t)
                    .filter(|(_, x)| !x.is_nan())
                    .map(|(a, b)| (a - b).powi(2))
                    .sum();
                Ok(sum / cells as f64)
            })
            .sum::<std::io::Result<f64>>()?
            / steps.len().max(1) as f64;
        println!(
            "epoch {e:>3} (steps {}..{}): model v{}, mean squared error {mse:.4e}",
            steps.start, steps.end, core.version
        );
    }
    Ok(())
}
