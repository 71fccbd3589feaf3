//! What the model server's core leaves in a run directory, written the same way by the server
//! at the end of a mission and by `fleet replay`: the final model (`model.cbor`, as published),
//! the fused estimate and its reported variance at every step (`estimate.npy`, `variance.npy`,
//! `(steps, rows, cols)` float64) and every plan published (`plans.json`).

use crate::events::{PlanPlaces, PublishedPlans};
use crate::protocol::{self, Body};
use crate::server::ServerCore;
use anyhow::Context as _;
use std::path::Path;

pub fn write(dir: &Path, core: &ServerCore, horizon: u64) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    if let Some(m) = core.model_update() {
        std::fs::write(dir.join("model.cbor"), protocol::encode(&Body::Model(m)))
            .with_context(|| format!("writing {}/model.cbor", dir.display()))?;
    }
    let grid = core.assimilator().grid();
    // Land (no data in the truth) is NaN: numpy's mark of a value that is not there.
    let land = core.assimilator().land();
    for (name, steps) in [("estimate.npy", &core.snapshots), ("variance.npy", &core.variances)] {
        let mut data: Vec<f64> = steps.iter().flatten().copied().collect();
        for k in 0..steps.len() {
            land.iter().for_each(|&c| data[k * grid.len() + c] = f64::NAN);
        }
        crate::npy::write(dir.join(name), &[steps.len(), grid.rows, grid.cols], &data)?;
    }
    let plans = (0..core.counters.epochs)
        .flat_map(|e| {
            core.vehicles()
                .iter()
                .filter_map(move |v| core.plan(&v.id, e, horizon).map(|p| (v.kind, p)))
        })
        .map(|(kind, p)| PlanPlaces {
            vehicle: p.vehicle,
            kind,
            epoch: p.epoch,
            targets: p
                .targets
                .into_iter()
                .map(|t| (t.epoch, t.step, t.position, t.radius))
                .collect(),
        })
        .collect();
    std::fs::write(
        dir.join("plans.json"),
        serde_json::to_string(&PublishedPlans { horizon, plans })?,
    )
    .with_context(|| format!("writing {}/plans.json", dir.display()))?;
    Ok(())
}
