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
    let mut on_land = vec![false; grid.len()];
    land.iter().for_each(|&c| on_land[c] = true);
    for (name, steps) in [("estimate.npy", &core.snapshots), ("variance.npy", &core.variances)] {
        let values = steps
            .iter()
            .flat_map(|step| step.iter().zip(&on_land).map(|(&v, &l)| if l { f64::NAN } else { v }));
        let shape = [steps.len(), grid.rows, grid.cols];
        crate::npy::write_values(dir.join(name), &shape, steps.iter().map(Vec::len).sum(), values)?;
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
