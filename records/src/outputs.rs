//! What the model server's core leaves in a run directory, written the same way by the server
//! at the end of a mission and by `fleet replay`: the final model (`model.cbor`, as published),
//! the fused estimate and its reported variance at every step (`estimate.npy`, `variance.npy`,
//! `(steps, rows, cols)` float64) and every plan published (`plans.json`).

use anyhow::Context as _;
use fleet_mission::events::{PlanPlaces, PublishedPlans};
use fleet_mission::protocol::{self, Body};
use fleet_mission::server::ServerCore;
use std::path::Path;

/// `estimate.npy` and `variance.npy`: already written step by step when the core keeps its
/// history in `dir` (then given their names), otherwise written from it, land NaN.
fn write_history(dir: &Path, core: &ServerCore) -> anyhow::Result<()> {
    let history = core.history();
    if history.files_dir().is_some_and(|d| same_dir(d, dir)) {
        return history
            .publish()
            .with_context(|| format!("naming {}/estimate.npy and variance.npy", dir.display()));
    }
    // The same writer the server uses (land NaN, the header, the names at the end).
    let grid = core.assimilator().grid();
    let context = || format!("writing {}/estimate.npy and variance.npy", dir.display());
    let mut files = fleet_mission::history::History::in_files(dir, grid.rows, grid.cols, core.assimilator().land())
        .with_context(context)?;
    for k in 0..history.len() {
        let (estimate, variance) = (history.estimate(k)?, history.variance(k)?);
        files
            .push(estimate.into_owned(), variance.into_owned())
            .with_context(context)?;
    }
    files.publish().with_context(context)?;
    Ok(())
}

/// Whether two paths name the same directory.
fn same_dir(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

pub fn write(dir: &Path, core: &ServerCore, horizon: u64) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    if let Some(m) = core.model_update() {
        std::fs::write(dir.join("model.cbor"), protocol::encode(&Body::Model(m)))
            .with_context(|| format!("writing {}/model.cbor", dir.display()))?;
    }
    write_history(dir, core)?;
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
