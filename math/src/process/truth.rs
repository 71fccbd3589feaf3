//! A truth field for an experiment or a mixed-reality mission: the plasma-cloud simulator on a
//! given grid, or a `.npy` dataset, then area-averaged onto the model grid.

use super::plasma::{PlasmaCloud, Preset};
use super::FieldSeries;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    #[error("give exactly one of preset or dataset")]
    Source,
    #[error("simulating {preset:?}: {source}")]
    Simulation { preset: Preset, source: super::plasma::PlasmaError },
    #[error("loading the dataset {}: {source}", path.display())]
    Dataset { path: PathBuf, source: super::dataset::DatasetError },
    #[error("{rows} x {cols} averaged by {factor} leaves less than 4 x 4 cells")]
    TooCoarse { rows: usize, cols: usize, factor: usize },
    #[error(transparent)]
    Grid(#[from] crate::grid::GridError),
}

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
    pub fn check(&self) -> Result<(), TruthError> {
        if self.preset.is_some() == self.dataset.is_some() {
            return Err(TruthError::Source);
        }
        Ok(())
    }

    /// The field at full resolution: the simulator at `grid` `[rows, cols]` for `frames`
    /// frames (seeded), or the dataset as it is.
    pub fn full(&self, grid: [usize; 2], frames: usize, seed: u64, progress: impl FnMut(usize)) -> Result<FieldSeries, TruthError> {
        self.check()?;
        match (&self.preset, &self.dataset) {
            (Some(preset), _) => {
                let mut p = preset.params();
                (p.ny, p.nx) = (grid[0], grid[1]);
                p.seed = seed;
                let sim_err = |source| TruthError::Simulation { preset: *preset, source };
                let mut sim = PlasmaCloud::new(p).map_err(sim_err)?;
                sim.run(frames, progress).map_err(sim_err)
            }
            (None, Some(path)) => super::dataset::load(path, 1.0).map_err(|source| TruthError::Dataset { path: path.clone(), source }),
            (None, None) => unreachable!("checked above"),
        }
    }
}

/// `full` area-averaged by `factor` in both directions (the model grid of that space rate).
pub fn averaged_by(full: &FieldSeries, factor: usize) -> Result<FieldSeries, TruthError> {
    let (rows, cols) = (full.rows / factor.max(1), full.cols / factor.max(1));
    if rows < 4 || cols < 4 {
        return Err(TruthError::TooCoarse { rows: full.rows, cols: full.cols, factor });
    }
    Ok(full.area_averaged(rows, cols)?)
}
