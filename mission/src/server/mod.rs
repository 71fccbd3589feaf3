//! The model server's core, without the network: measurement batches in (any order, any
//! number of times), each assimilated exactly once, epochs folded into the model in step order
//! as soon as they are complete, acks, plans and model updates out. The Zenoh node wraps this.
//!
//! The epoch contract ([`Schedule`]): every vehicle sends one batch per epoch it takes part
//! in, and its `seq` counts those batches from 0 without gaps. Aerials take part from epoch 0
//! (the aerial-only initialisation); boats in every full epoch from epoch 1 (a boat left
//! without a disk sends an empty batch). An epoch is complete when every batch for it is in.
//!
//! [`ServerCore`] composes one module per concern, each with the state it owns:
//!
//! | module | state | what it does |
//! |---|---|---|
//! | `intake` | `Intake` | a batch checked against the mission, buffered by epoch; acks, what is missing |
//! | `epoch` | (the assimilator) | an epoch's steps screened, fused and learned, in step order |
//! | `refit` | `Checkpoints` | late batches and re-admissions: the model made again from a checkpoint |
//! | `journal` | `Journal` | the decisions a restart needs (holds, forced epochs, overrides) out and back |
//! | `sensors` | `SensorDecisions` | the operator's overrides and the tests' re-admissions, pinned per step |
//! | `ledger` | `Ledger` | per step and epoch: held-out scores, innovations, skill, verdicts |
//! | `planning` | `Planning` | the allocations handed out, the vehicles held, each vehicle's plan |
//! | `publish` | `Publication` | the model as published, made beside the next placement |
//!
//! Each concern's methods are an `impl ServerCore` block in its module: they read the mission
//! (schedule, roster, assimilator) this type holds, and write only their own state and the
//! model.

mod epoch;
mod intake;
mod journal;
mod ledger;
mod planning;
mod publish;
mod refit;
mod sensors;

pub use crate::roster::{Roster, VehicleSpec};
pub use journal::{EpochRecord, RestoreError, OVERRIDE_PREFIX};
pub use publish::Publisher;
pub use refit::{keep_checkpoint, CHECKPOINT_EVERY};

use crate::assimilator::Assimilator;
use crate::history::History;
use crate::protocol;
use crate::schedule::Schedule;
use crate::team::{TeamConfig, TeamError};
use fleet_math::grid::Grid;
use std::collections::BTreeMap;

/// What happened to one batch.
#[derive(Debug, Clone, PartialEq)]
pub enum Ingested {
    /// Already assimilated or already waiting: dropped (and acked again).
    Duplicate,
    /// Kept until its epoch is complete.
    Buffered,
    /// Completed these epochs, which are now in the model.
    Assimilated(Vec<u64>),
    /// Arrived for an epoch already assimilated without it (forced by a timeout): the model
    /// was re-fitted from that epoch on, with everything now in (by `ingest`; after
    /// `ingest_deferred`, once `settle` has run).
    Refitted(u64),
}

#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error(transparent)]
    Protocol(#[from] protocol::ProtocolError),
    #[error("batch from {vehicle}: {why}")]
    Rejected { vehicle: protocol::VehicleId, why: String },
    #[error(transparent)]
    Model(#[from] TeamError),
}

/// Counters a node reports.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Counters {
    pub batches: u64,
    pub duplicates: u64,
    pub rejected: BTreeMap<String, u64>,
    pub epochs: u64,
    /// Batches replayed from the journal at a restart (included in `batches`).
    #[serde(default)]
    pub restored: u64,
    /// Epochs assimilated without every batch (a timeout), and re-fits when the rest came.
    #[serde(default)]
    pub forced: u64,
    #[serde(default)]
    pub refits: u64,
    /// Epochs assimilated again by those re-fits (from the newest checkpoint before the
    /// earliest late epoch).
    #[serde(default)]
    pub refit_epochs: u64,
    /// Batches vehicles say were acknowledged but the journal does not hold (lost with it).
    #[serde(default)]
    pub lost: u64,
    /// Zenoh sessions the router refused at the handshake (wrong or missing credentials).
    #[serde(default)]
    pub sessions_refused: u64,
    /// Sensors re-admitted from `excluded` by their tests (each re-fits from its clean steps), and the
    /// operator's overrides taken.
    #[serde(default)]
    pub readmissions: u64,
    #[serde(default)]
    pub overrides: u64,
}

#[derive(Clone)]
pub struct ServerCore {
    cfg: TeamConfig,
    schedule: Schedule,
    vehicles: Roster,
    assim: Assimilator,
    /// Next epoch to assimilate.
    epoch: u64,
    pub counters: Counters,
    /// Model version: bumped at every assimilated epoch.
    pub version: u64,
    /// The fused estimate and its reported variance at every step assimilated so far (in
    /// memory, or in the run's files: [`Self::with_history_in`]).
    history: History,
    /// The aerial estimate of every step assimilated so far (the aerial-only team's map),
    /// kept only when asked for ([`Self::with_aerial_history`]: the experiments' baseline): a
    /// full field a step, 2.4 MB at 384 x 768, that the model server never reads.
    pub aerial_estimates: Vec<Vec<f64>>,
    keep_aerial_estimates: bool,
    intake: intake::Intake,
    planning: planning::Planning,
    checkpoints: refit::Checkpoints,
    journal: journal::Journal,
    ledger: ledger::Ledger,
    sensors: sensors::SensorDecisions,
    publication: publish::Publication,
}

impl ServerCore {
    pub fn new(cfg: &TeamConfig, grid: Grid, frames: usize) -> Result<Self, TeamError> {
        Ok(Self {
            assim: Assimilator::new(cfg, grid, frames)?,
            cfg: cfg.clone(),
            schedule: Schedule::new(cfg, frames),
            vehicles: Roster::of(cfg),
            epoch: 0,
            counters: Counters::default(),
            version: 0,
            history: History::default(),
            aerial_estimates: vec![],
            keep_aerial_estimates: false,
            intake: intake::Intake::default(),
            planning: planning::Planning::default(),
            checkpoints: refit::Checkpoints::default(),
            journal: journal::Journal::default(),
            ledger: ledger::Ledger::default(),
            sensors: sensors::SensorDecisions::default(),
            publication: publish::Publication::default(),
        })
    }

    pub fn vehicles(&self) -> &[VehicleSpec] {
        self.vehicles.all()
    }

    pub fn roster(&self) -> &Roster {
        &self.vehicles
    }

    /// The epoch the server waits for next.
    pub fn next_epoch(&self) -> u64 {
        self.epoch
    }

    pub fn schedule(&self) -> &Schedule {
        &self.schedule
    }

    /// Steps of epoch `e` (empty past the end of the mission).
    pub fn steps_of(&self, e: u64) -> std::ops::Range<usize> {
        self.schedule.steps_of(e)
    }

    /// Whether every step of the mission is in the model, with every batch.
    pub fn finished(&self) -> bool {
        !self.intake.stale && self.all_assimilated() && (0..self.epoch).all(|e| self.missing(e).next().is_none())
    }

    fn all_assimilated(&self) -> bool {
        self.steps_of(self.epoch).is_empty() && self.epoch > 0
    }

    /// Assimilate the next epoch with the batches it has (a vehicle is late); its missing
    /// batches re-fit the model when they come. Epoch 0 (the first model) is never forced.
    pub fn force(&mut self) -> Result<bool, TeamError> {
        self.settle()?;
        let e = self.epoch;
        if e == 0 || self.steps_of(e).is_empty() || self.missing(e).next().is_none() {
            return Ok(false);
        }
        self.assimilate_epoch(e)?;
        self.readmit()?;
        self.counters.forced += 1;
        self.journal.forced.insert(e);
        self.journal.unjournalled.insert(e);
        self.assimilate_complete()?;
        Ok(true)
    }

    /// Assimilate every epoch from the next on that has all its batches.
    fn assimilate_complete(&mut self) -> Result<(), TeamError> {
        while self.epoch_complete(self.epoch) {
            self.assimilate_epoch(self.epoch)?;
            self.readmit()?;
        }
        Ok(())
    }

    /// Write every step's fused estimate and variance to `dir`'s `estimate.npy` and
    /// `variance.npy` as they are made, instead of holding them in memory (the model server's
    /// memory then does not grow with the mission). Before the first step only.
    pub fn with_history_in(mut self, dir: &std::path::Path) -> Result<Self, TeamError> {
        if !self.history.is_empty() {
            return Err(TeamError::Config(
                "the history moves to files before the first step only".into(),
            ));
        }
        let grid = *self.assim.grid();
        self.history = History::in_files(dir, grid.rows, grid.cols, self.assim.land())
            .map_err(|e| TeamError::History(format!("{}: {e}", dir.display())))?;
        Ok(self)
    }

    /// The fused estimate and its reported variance at every step assimilated so far.
    pub fn history(&self) -> &History {
        &self.history
    }

    /// Keep the aerial estimate of every step in [`Self::aerial_estimates`].
    pub fn with_aerial_history(mut self) -> Self {
        self.keep_aerial_estimates = true;
        self
    }

    /// Keep each boat test's information on an offset ([`crate::health::Screen::information`]):
    /// for the fault study.
    pub fn with_screen_information(mut self) -> Self {
        self.assim.screen().keep_information();
        self
    }

    /// Boats go at most `speed` metres per step (the mission's `[motion]`): horizon placement
    /// plans only disks they reach in time. Set before the first epoch.
    pub fn with_boat_speed(mut self, speed: f64) -> Self {
        self.assim.set_boat_speed(speed);
        self
    }

    pub fn assimilator(&self) -> &Assimilator {
        &self.assim
    }

    /// A fingerprint of what the journal's batches mean: the team, the grid and the mission's
    /// length. A journal written under another one is refused, not replayed.
    pub fn fingerprint(&self) -> String {
        let g = self.assim.grid();
        format!(
            "{} grid {}x{} frames {}",
            serde_json::to_string(&self.cfg).expect("the team serialises"),
            g.rows,
            g.cols,
            self.schedule.frames
        )
    }
}

/// The run's estimate files could not be written or read back.
fn history_error(e: std::io::Error) -> TeamError {
    TeamError::History(e.to_string())
}
