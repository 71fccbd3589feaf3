//! A truth field for an experiment or a mixed-reality mission: the plasma-cloud simulator on a
//! given grid, or a `.npy` dataset, then area-averaged onto the model grid.

use super::plasma::{PlasmaCloud, Preset};
use super::FieldSeries;
use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Where the truth comes from (exactly one of the two).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TruthSource {
    #[serde(default)]
    pub preset: Option<Preset>,
    #[serde(default)]
    pub dataset: Option<PathBuf>,
}

impl TruthSource {
    pub fn check(&self) -> anyhow::Result<()> {
        if self.preset.is_some() == self.dataset.is_some() {
            bail!("give exactly one of preset or dataset");
        }
        Ok(())
    }

    /// The field at full resolution: the simulator at `grid` `[rows, cols]` for `frames`
    /// frames (seeded), or the dataset as it is.
    pub fn full(&self, grid: [usize; 2], frames: usize, seed: u64, progress: impl FnMut(usize)) -> anyhow::Result<FieldSeries> {
        self.check()?;
        match (&self.preset, &self.dataset) {
            (Some(preset), _) => {
                let mut p = preset.params();
                (p.ny, p.nx) = (grid[0], grid[1]);
                p.seed = seed;
                let mut sim = PlasmaCloud::new(p).with_context(|| format!("simulating {preset:?}"))?;
                Ok(sim.run(frames, progress)?)
            }
            (None, Some(path)) => super::dataset::load(path, 1.0).with_context(|| format!("loading the dataset {}", path.display())),
            (None, None) => unreachable!("checked above"),
        }
    }
}

/// `full` area-averaged by `factor` in both directions (the model grid of that space rate).
pub fn averaged_by(full: &FieldSeries, factor: usize) -> anyhow::Result<FieldSeries> {
    let (rows, cols) = (full.rows / factor.max(1), full.cols / factor.max(1));
    if rows < 4 || cols < 4 {
        bail!("{} x {} averaged by {factor} leaves less than 4 x 4 cells", full.rows, full.cols);
    }
    Ok(full.area_averaged(rows, cols)?)
}
