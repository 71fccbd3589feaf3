//! What a team is: its vehicles, rates, noise, sensing radius, model and fusion choices, and
//! the checks that say up front whether it can run on a grid ([`TeamConfig::validate`]). The
//! mission file's `[team]` table and the experiment files' rows are this.

use fleet_math::dmd::{Method, RankPolicy};
use fleet_math::fusion::Scheme;
use fleet_math::grid::Grid;
use serde::{Deserialize, Serialize};

/// Where boats go.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
    strum::EnumString,
    strum::Display,
    strum::VariantNames,
    schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = placement_name_error)]
pub enum Placement {
    /// Block pivoted QR over the model's spatial modes (Alg. 2).
    Qr,
    /// Greedy D-optimal disks.
    DOptimal,
    /// Uniformly random non-overlapping disks (seeded): the baseline.
    Random,
    /// The disks that remove the most forecast uncertainty over the next `horizon_epochs`
    /// epochs, within each boat's reach, disks and boats chosen together (needs `fusion =
    /// "kalman"`: it plans on the filter's forecast covariance).
    Horizon,
}

/// What the online DMD is fed at each step after the first model.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    Serialize,
    Deserialize,
    strum::EnumString,
    strum::Display,
    strum::VariantNames,
    schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = learnfrom_name_error)]
pub enum LearnFrom {
    /// The fused estimate (the filter's posterior mean): every source, at every step.
    #[default]
    Posterior,
    /// The aerials' interpolated frame alone: no forecast in it, so the model can never learn
    /// its own predictions back, but coarse and noisy.
    Aerial,
}

/// Every choice of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct TeamConfig {
    /// Aerial vehicles in the team.
    pub aerials: usize,
    /// Aerial frames every this many steps (time rate).
    pub aerial_period: usize,
    /// Aerials keep every this-many-th cell (space rate).
    pub aerial_stride: usize,
    /// Aerial noise std at the aerial, and its growth per cell of distance (both in the field's
    /// units; a file that gives no growth gets [`default_growth`] of its noise).
    pub aerial_sigma0: f64,
    /// Growth of the aerial noise std per cell of distance from the aerial (field units a cell;
    /// unset: a twentieth of `aerial_sigma0`).
    pub aerial_growth_per_cell: f64,
    /// Boats in the team.
    pub boats: usize,
    /// Boat samples (and model updates) every this many steps.
    pub boat_period: usize,
    /// Sensing radius in cells.
    pub radius: f64,
    /// Boat noise standard deviation.
    pub boat_sigma: f64,
    /// Steps of aerial-only data before the first model.
    pub init_steps: usize,
    /// `full`, `optimal`, `energy:<f>` or an integer (`rank = 6` or `rank = "6"`).
    pub rank: RankPolicy,
    pub method: Method,
    /// The forgetting factor of `method = "long-term"` (0 < gamma <= 1; 1: no forgetting).
    pub gamma: f64,
    pub placement: Placement,
    /// `placement = "horizon"`: how many epochs ahead the uncertainty counts.
    pub horizon_epochs: usize,
    pub fusion: Scheme,
    /// What the model learns from: the fused estimate (`posterior`) or the aerials' frame alone
    /// (`aerial`).
    pub learn_from: LearnFrom,
    /// Floor of the aerials' coverage density.
    pub density_floor: f64,
    /// Seed of the vehicles' random streams (sensor noise) and of random placement.
    pub seed: u64,
    /// Test every reading and judge every sensor before the fusion uses them
    /// ([`crate::health`]); `false` takes every reading at its word.
    #[serde(skip_serializing_if = "is_true")]
    #[schemars(extend("default" = true))]
    pub sensor_health: bool,
    /// The site's boundary (`[mavlink] boundary` of a mission, read when the mission is
    /// loaded): no disk and no aerial place outside it. Not settable in `[team]`; serialised,
    /// so a journal's fingerprint knows it.
    #[serde(skip_deserializing, skip_serializing_if = "Option::is_none")]
    #[schemars(skip)]
    pub fence: Option<crate::fence::SiteFence>,
    /// Cells with no data in any frame of the truth (land, for an ocean field; set from the
    /// truth where it is loaded, [`fleet_math::process::FieldSeries::land`]): off the model grid,
    /// like cells outside the fence, and zero in every snapshot the model learns from.
    #[serde(skip_deserializing, skip_serializing_if = "Vec::is_empty")]
    #[schemars(skip)]
    pub land: Vec<u32>,
}

fn is_true(b: &bool) -> bool {
    *b
}

/// The aerial noise's growth per cell where a file does not give one: a twentieth of the noise
/// at the aerial (the default mission's 0.0005 at 0.01, to the bit). A fixed growth in the
/// field's units is no default: at 0.0005 a cell, a field of magnitude 1e-3 (a concentration,
/// a field in other units) had aerial noise 75 times the `noise` it was given, at 15 cells
/// (docs/guide/fields.md, "A field in any units").
pub fn default_growth(sigma0: f64) -> f64 {
    sigma0 / 20.0
}

/// Whether the `[team]` table of the TOML `text` gives `aerial_growth_per_cell` itself.
pub fn gives_growth(text: &str) -> bool {
    toml::from_str::<toml::Table>(text)
        .ok()
        .and_then(|t| {
            t.get("team")
                .and_then(|t| t.as_table())
                .map(|t| t.contains_key("aerial_growth_per_cell"))
        })
        .unwrap_or(false)
}

impl Default for TeamConfig {
    fn default() -> Self {
        Self {
            aerials: 2,
            aerial_period: 1,
            aerial_stride: 5,
            aerial_sigma0: 0.01,
            aerial_growth_per_cell: 0.0005,
            boats: 5,
            boat_period: 5,
            radius: 10.0,
            boat_sigma: 0.01,
            init_steps: 20,
            rank: RankPolicy::Fixed(10),
            method: Method::General,
            gamma: 1.0,
            placement: Placement::Qr,
            horizon_epochs: 3,
            fusion: Scheme::Kalman,
            learn_from: LearnFrom::Posterior,
            density_floor: 0.2,
            seed: 7,
            sensor_health: true,
            fence: None,
            land: vec![],
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TeamError {
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Asked for something the run has not reached yet (a state error, not a configuration one).
    #[error("not yet: {0}")]
    NotReady(Missing),
    #[error(transparent)]
    Dmd(#[from] fleet_math::dmd::DmdError),
    #[error(transparent)]
    Sensing(#[from] fleet_math::sensing::SensingError),
    #[error(transparent)]
    Fusion(#[from] fleet_math::fusion::FusionError),
    #[error(transparent)]
    Filter(#[from] fleet_math::kalman::FilterError),
    #[error(transparent)]
    Grid(#[from] fleet_math::grid::GridError),
    /// The fused map's files in the run directory (`estimate.npy`, `variance.npy`).
    #[error("the run's estimate files: {0}")]
    History(String),
}

impl TeamConfig {
    /// The choices that must go together, whatever the grid.
    pub fn check_choices(&self) -> Result<(), TeamError> {
        if self.placement == Placement::Horizon && self.fusion != Scheme::Kalman {
            return Err(TeamError::Config(format!(
                "placement = \"horizon\" plans on the Kalman filter's forecast \
                covariance: it needs fusion = \"kalman\", not \"{}\"",
                self.fusion
            )));
        }
        if self.horizon_epochs == 0 {
            return Err(TeamError::Config("horizon_epochs must be at least 1".into()));
        }
        Ok(())
    }

    /// Long because it is one check per setting, in the order of the fields.
    /// The team has vehicles, the grid is not empty, and the land mask fits it and leaves the model room: at least as many wet cells as
    /// the rank asks for, and as the boats' disks take.
    fn check_land(&self, grid: &Grid) -> Result<(), TeamError> {
        if self.aerials == 0 || self.boats == 0 {
            return Err(TeamError::Config(
                "a heterogeneous team needs at least one aerial and one boat".into(),
            ));
        }
        if grid.is_empty() {
            return Err(TeamError::Config("empty grid".into()));
        }
        if let Some(c) = self.land.iter().find(|&&c| c as usize >= grid.len()) {
            return Err(TeamError::Config(format!(
                "land cell {c} is off the {}-cell grid",
                grid.len()
            )));
        }
        let wet = grid.len() - self.land.len();
        let rank = match self.rank {
            RankPolicy::Fixed(r) => r,
            _ => 1,
        };
        if wet < rank.max(self.boats) {
            return Err(TeamError::Config(format!(
                "the field's mask leaves {wet} cells with data of {}, fewer than the model's rank {rank} or \
                the {} boats",
                grid.len(),
                self.boats
            )));
        }
        Ok(())
    }

    /// The sensors' noises in units the estimator holds ([`fleet_math::process::units::check_noise`]).
    fn check_noise(&self) -> Result<(), TeamError> {
        for (what, sigma) in [("aerial_sigma0", self.aerial_sigma0), ("boat_sigma", self.boat_sigma)] {
            fleet_math::process::units::check_noise(sigma)
                .map_err(|why| TeamError::Config(format!("{what}: {why}")))?;
        }
        Ok(())
    }

    pub fn validate(&self, grid: &Grid, frames: usize) -> Result<(), TeamError> {
        let bad = |m: String| Err(TeamError::Config(m));
        if self.aerial_period == 0 || self.boat_period == 0 || self.aerial_stride == 0 {
            return bad("periods and stride must be at least 1".into());
        }
        if self.init_steps < 3 || self.init_steps + self.boat_period > frames {
            return bad(format!(
                "init_steps {} must be >= 3 and leave at least one epoch of {} steps in {frames} frames",
                self.init_steps, self.boat_period
            ));
        }
        // Planning further ahead than the run lasts costs time and changes nothing.
        let epochs = (frames - self.init_steps) / self.boat_period;
        if self.placement == Placement::Horizon && self.horizon_epochs > epochs {
            return bad(format!(
                "horizon_epochs {} is beyond the run's {epochs} boat epochs",
                self.horizon_epochs
            ));
        }
        let nonneg = [
            self.aerial_sigma0,
            self.aerial_growth_per_cell,
            self.boat_sigma,
            self.density_floor,
        ];
        if nonneg.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || !(self.radius.is_finite() && self.radius >= 0.0) {
            return bad("noise, radius and density floor must be finite and >= 0".into());
        }
        self.check_noise()?;
        self.check_choices()?;
        if self.density_floor > 1.0 {
            return bad("density_floor must be in [0, 1]".into());
        }
        self.check_land(grid)?;
        if self.method == Method::LongTerm {
            return bad(
                "method = \"long-term\": its operator has every one of the grid's N modes, so the boats' gappy \
                fit is underdetermined and every disk scores the same (block QR sees Phi Phi^T = I); a team or \
                mission uses \"general\" (default) or \"batch\", which keep the rank"
                    .into(),
            );
        }
        if self.method != Method::LongTerm && self.gamma != 1.0 {
            return bad(format!(
                "gamma = {}: the forgetting factor applies to method = \"long-term\" only ({:?} keeps every snapshot)",
                self.gamma, self.method
            ));
        }
        if !(self.gamma > 0.0 && self.gamma <= 1.0) {
            return bad(format!("gamma = {}: must be in (0, 1]", self.gamma));
        }
        let lattice = grid.strided(self.aerial_stride)?;
        if self.aerials > lattice.rows * lattice.cols {
            return bad(format!(
                "aerials = {}: the aerial lattice has only {} cells ({} x {} grid, aerial_stride {}), so some aerial \
                    would see nothing; use at most {} aerials or a smaller aerial_stride",
                self.aerials,
                lattice.rows * lattice.cols,
                grid.rows,
                grid.cols,
                self.aerial_stride,
                lattice.rows * lattice.cols
            ));
        }
        if !disk_fits(grid, self.boats, self.radius) {
            return bad(match largest_radius(grid, self.boats) {
                Some(r) => format!(
                    "radius = {}: {} boats' disks of that radius do not fit side by side on the {} x \
                    {} grid; at most radius {r}",
                    self.radius, self.boats, grid.rows, grid.cols
                ),
                None => format!(
                    "boats = {}: more boats than cells on the {} x {} grid",
                    self.boats, grid.rows, grid.cols
                ),
            });
        }
        Ok(())
    }
}

/// What a run lacks when it is asked too early.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Missing {
    #[error("no aerial data yet")]
    AerialData,
    #[error("part of the lattice unseen and no earlier frame")]
    EarlierFrame,
    #[error("the first model needs at least 3 snapshots, there are {have}")]
    Snapshots { have: usize },
    #[error("no model yet")]
    Model,
    #[error("no plan for epoch {epoch}")]
    Plan { epoch: u64 },
}

/// The largest sensing radius (cells) at which `boats` disks fit side by side on `grid`: a
/// disk inside the grid, and the disks' cells together no more than the grid's.
fn largest_radius(grid: &Grid, boats: usize) -> Option<usize> {
    (0..grid.rows.min(grid.cols))
        .take_while(|&r| disk_fits(grid, boats, r as f64))
        .last()
}

fn disk_fits(grid: &Grid, boats: usize, radius: f64) -> bool {
    let span = 2 * radius.floor() as usize + 1;
    if span > grid.rows.min(grid.cols) {
        return false;
    }
    let centre = fleet_math::grid::Cell::new(grid.rows / 2, grid.cols / 2);
    boats.saturating_mul(grid.disk(centre, radius).len()) <= grid.len()
}

/// A name that is not a [`Placement`]'s.
fn placement_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!(
        "placement must be one of {}, got {got:?}",
        Placement::VARIANTS.join(", ")
    )
}

/// A name that is not a [`LearnFrom`]'s.
fn learnfrom_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!(
        "learn_from must be one of {}, got {got:?}",
        LearnFrom::VARIANTS.join(", ")
    )
}
