//! Dynamic Mode Decomposition: one interface, three ways to keep it up to date.
//!
//! - [`BatchDmd`]: exact DMD recomputed from every stored pair (paper eqs. 2-8); the baseline.
//! - [`GeneralDmd`]: Brand's incremental SVD of `X` with a batch of any size per update, keeping
//!   the snapshots (paper Sect. 4.3.1). Its speed comes from the rank it keeps.
//! - [`LongTermDmd`]: `A = Q S` with a batch Woodbury update and a forgetting factor (paper
//!   Sect. 4.3.2); keeps no snapshots, needs `N` small (a few hundred) and a full-row-rank start.
//!
//! At full rank and `gamma = 1` all three give the same operator. Build one with [`DmdConfig::init`],
//! feed it with [`Dmd::update`], read it with [`Dmd::decompose`], and turn the result into a
//! predictive [`DmdModel`] with [`Modes::model`].

mod batch;
mod debias;
mod general;
pub mod linalg;
mod longterm;
mod model;
mod rank;
mod snapshots;

pub use batch::BatchDmd;
pub use debias::Debias;
pub use general::GeneralDmd;
pub use longterm::{Forgetting, ForgettingDirections, ForgettingUnit, LongTermDmd};
pub use model::{DmdModel, Factored, ModeFactors, ModelSummary, Modes, OrthogonalModes};
pub use rank::{numerical_rank, RankPolicy};
pub use snapshots::SnapshotPairs;

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum DmdError {
    #[error("shape: {0}")]
    Shape(String),
    #[error("non-finite value at row {row}, column {col} of the snapshots")]
    NonFinite { row: usize, col: usize },
    #[error(
        "the long-term method needs X (N x m) to have full row rank N = {n}: it has {m} snapshot pairs \
         of numerical rank {rank}; initialise it with at least {n} linearly independent snapshots \
         (e.g. the first {n} or more pairs of a noisy or rich field), or use the general method"
    )]
    NotFullRowRank { n: usize, m: usize, rank: usize },
    #[error("the data is all zeros or has no numerical rank")]
    ZeroRank,
    #[error("{0}")]
    Unsupported(String),
    #[error("numerical failure: {0}")]
    Numerical(String),
    #[error("forgetting factor gamma must be in (0, 1], got {0}")]
    Gamma(f64),
}

impl DmdError {
    /// Whether the data or the settings given are at fault (rather than the numerics).
    pub fn is_input(&self) -> bool {
        !matches!(self, Self::Numerical(_))
    }
}

/// Which update scheme a model uses.
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
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = method_name_error)]
pub enum Method {
    Batch,
    General,
    #[strum(to_string = "long-term", serialize = "longterm")]
    LongTerm,
}

/// Everything needed to start a model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DmdConfig {
    pub method: Method,
    pub rank: RankPolicy,
    /// Noise-robust eigenvalues (batch and general only).
    pub debias: Debias,
    /// Forgetting factor of the long-term method, in (0, 1]; 1 keeps everything.
    pub gamma: f64,
    /// How the long-term method forgets with `gamma < 1`.
    #[serde(default)]
    pub forgetting: Forgetting,
}

impl Default for DmdConfig {
    fn default() -> Self {
        Self {
            method: Method::Batch,
            rank: RankPolicy::Full,
            debias: Debias::None,
            gamma: 1.0,
            forgetting: Forgetting::default(),
        }
    }
}

impl DmdConfig {
    /// Fit the first model from snapshot pairs (columns of `x`, `y`, with `y_j` following `x_j`).
    pub fn init(&self, x: MatRef<'_, f64>, y: MatRef<'_, f64>) -> Result<Box<dyn Dmd>, DmdError> {
        Ok(match self.method {
            Method::Batch => Box::new(BatchDmd::fit(x, y, self.rank, self.debias)?),
            Method::General => Box::new(GeneralDmd::init(x, y, self.rank, self.debias)?),
            Method::LongTerm => {
                if self.debias != Debias::None {
                    return Err(DmdError::Unsupported(
                        "the long-term method keeps no snapshots, so it cannot debias; use batch or general".into(),
                    ));
                }
                Box::new(LongTermDmd::init_with(x, y, self.gamma, self.forgetting)?)
            }
        })
    }
}

/// A DMD model that assimilates snapshot pairs and yields its eigendecomposition.
pub trait Dmd: dyn_clone::DynClone + Send + Sync {
    fn method(&self) -> Method;
    /// Fold in new pairs: column `j` of `y_new` is the snapshot one step after column `j` of
    /// `x_new`. Any number of columns, including one.
    fn update(&mut self, x_new: MatRef<'_, f64>, y_new: MatRef<'_, f64>) -> Result<(), DmdError>;
    /// The part of [`Self::update`] that needs only `x_new` (the snapshots the pairs start
    /// from), made ahead of `y_new` and the model left as it is: a server makes it beside the
    /// filter step that makes `y_new`'s last column. `None` where the method has no such part,
    /// or where `x_new` would be refused (the update then makes, or refuses, it all itself).
    fn prepare(&self, _x_new: MatRef<'_, f64>) -> Option<Prepared> {
        None
    }
    /// [`Self::update`] with what [`Self::prepare`] made: the same model to the bit. What was
    /// made of another `x_new`, or before the model last changed, is not taken (the update is
    /// then made whole).
    fn update_prepared(
        &mut self,
        prepared: Option<Prepared>,
        x_new: MatRef<'_, f64>,
        y_new: MatRef<'_, f64>,
    ) -> Result<(), DmdError> {
        let _ = prepared;
        self.update(x_new, y_new)
    }
    /// Eigenvalues (discrete time) and modes of the current operator.
    fn decompose(&self) -> Result<Modes, DmdError>;
    /// [`Self::decompose`]'s eigenvalues and its modes' factors, without the modes, when the
    /// method has them (exact DMD's; `None` for the others): what needs only the modes' span
    /// is then made from the factors while the modes are ([`ModeFactors::modes`]).
    fn factored(&self) -> Result<Option<Factored>, DmdError> {
        Ok(None)
    }
    /// Number of modes the model currently keeps.
    fn rank(&self) -> usize;
    /// Number of snapshot pairs assimilated so far.
    fn pairs(&self) -> usize;
    /// State dimension `N`.
    fn dim(&self) -> usize;
}

/// What [`Dmd::prepare`] made of a model's next `x_new` (the general method's new `U`, `S`
/// and the vectors that carry `YW` over), with the `x_new` and the model's update count it
/// was made at, so that no other update takes it.
#[derive(Debug)]
pub struct Prepared {
    x: Mat<f64>,
    updates: usize,
    ahead: general::Ahead,
}

// A boxed model is `Clone` (a server keeps copies as checkpoints, to re-fit from the middle).
dyn_clone::clone_trait_object!(Dmd);

/// Split a snapshot sequence (columns, in time order) into the pairs `X = Z[:, :-1]`,
/// `Y = Z[:, 1:]`.
pub fn pairs_of(z: MatRef<'_, f64>) -> (MatRef<'_, f64>, MatRef<'_, f64>) {
    let m = z.ncols().saturating_sub(1);
    (z.subcols(0, m), z.subcols(1, m))
}

/// A name that is not a [`Method`]'s.
fn method_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!("method must be one of {}, got {got:?}", Method::VARIANTS.join(", "))
}
