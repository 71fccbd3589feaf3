//! The fleet's wire protocol (DESIGN.md "The fleet"): typed messages, one self-describing
//! binary encoding (CBOR, Zenoh encoding [`ENCODING`]), a schema version in every message, and
//! validation of everything that comes in.
//!
//! One entry point each way: [`encode`] and [`decode`]. `decode` refuses oversized payloads
//! before parsing, trailing bytes after the message, unknown schema versions, and then checks
//! the message against what the receiver knows ([`Context`]: grid, vehicles, limits), so a
//! node only ever sees messages it can use. Every refusal is a [`ProtocolError`] that says
//! why; nodes count them by [`ProtocolError::reason`].
//!
//! A message is a CBOR map `{"v": 2, "type": "<kind>", ...fields}`; any CBOR library decodes
//! it (see docs/reference/protocol.md and the Python client in examples/). Cells travel as runs ([`cells`]).

pub mod cells;
pub mod floats;
pub mod keys;
mod vehicle_id;

pub use vehicle_id::VehicleId;

use fleet_math::grid::Grid;
use serde::{Deserialize, Serialize};

/// Schema version carried by every message; bumped on any incompatible change.
pub const SCHEMA_VERSION: u16 = 4;
/// Zenoh encoding set on every publication.
pub const ENCODING: &str = "application/cbor;hetfleet-v4";
/// Default size limit of one payload (a 384 x 768 model at rank 10 is ~27 MB; batches are
/// far smaller). Receivers may lower it.
pub const MAX_PAYLOAD: usize = 64 << 20;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProtocolError {
    #[error("payload of {size} bytes exceeds the {limit}-byte limit")]
    TooLarge { size: usize, limit: usize },
    #[error("malformed CBOR: {0}")]
    Malformed(String),
    #[error("{0} trailing bytes after the message")]
    Trailing(usize),
    #[error("schema version {got} (this node speaks {SCHEMA_VERSION})")]
    Version { got: u16 },
    #[error("unknown vehicle {0:?}")]
    UnknownVehicle(String),
    #[error("invalid message: {0}")]
    Invalid(String),
}

impl ProtocolError {
    /// A short stable name for counters and logs.
    pub fn reason(&self) -> &'static str {
        match self {
            Self::TooLarge { .. } => "too_large",
            Self::Malformed(_) => "malformed",
            Self::Trailing(_) => "trailing_bytes",
            Self::Version { .. } => "schema_version",
            Self::UnknownVehicle(_) => "unknown_vehicle",
            Self::Invalid(_) => "invalid",
        }
    }
}

/// What kind of vehicle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum VehicleKind {
    Aerial,
    Boat,
}

/// A sensor's noise: the sensor model's type, defined with it in `fleet-math` and carried on
/// the wire as it is.
pub use fleet_math::fusion::Noise;

/// What one vehicle measured at one step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Sample {
    /// The mission step the values are of.
    pub step: u64,
    /// Where the vehicle was, metres `(x, y)`.
    pub position: [f64; 2],
    /// Flat grid indices of the measured cells (aerials: the cells their coarse lattice sits on);
    /// on the wire as runs ([`cells`]).
    #[serde(with = "cells")]
    #[schemars(with = "cells::RunsSchema")]
    pub cells: Vec<u32>,
    /// The values at `cells`, in the field's units; on the wire as packed bytes ([`floats`]).
    #[serde(with = "floats")]
    #[schemars(with = "floats::PackedSchema<f64>")]
    pub values: Vec<f64>,
    /// Each value's own noise standard deviation, when an instrument said it (readings
    /// averaged in a cell, [`crate::instrument`]); absent, the batch's `noise` applies. Not
    /// written when absent, so a simulated vehicle's batches are the bytes they always were.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<Vec<f64>>,
}

impl fleet_math::fusion::Reading for Sample {
    fn position(&self) -> [f64; 2] {
        self.position
    }
    fn cells(&self) -> &[u32] {
        &self.cells
    }
    fn values(&self) -> &[f64] {
        &self.values
    }
}

/// A vehicle's batch of samples; `seq` is per vehicle and gap-free from 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct MeasurementBatch {
    /// Who measured.
    pub vehicle: VehicleId,
    /// What kind of vehicle it is (the server checks it against the mission).
    pub kind: VehicleKind,
    /// The batch's number, per vehicle, gap-free from 0: the server assimilates each once, in order.
    pub seq: u64,
    /// The sensor's noise model, for the values without their own `sigma`.
    pub noise: Noise,
    /// One sample per step of the epoch the batch is for.
    pub samples: Vec<Sample>,
}

/// Link as a vehicle sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum LinkState {
    Up,
    Down,
}

/// A vehicle's state as it reports it (at each epoch's end, and while it waits): where it is,
/// its battery, link, outbox and autopilot, and what its instrument delivered.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Telemetry {
    /// Who reports.
    pub vehicle: VehicleId,
    /// The mission step the vehicle is at.
    pub step: u64,
    /// Where it is, metres `(x, y)` from the workspace's corner.
    pub position: [f64; 2],
    /// Radians from +x.
    pub heading: f64,
    /// Fraction 0..1.
    pub battery: f64,
    /// Its link to the base as it sees it.
    pub link: LinkState,
    /// Batches sent and not yet acknowledged (kept on the vehicle until they are).
    pub outbox_depth: u64,
    /// The vehicle's autopilot as its MAVLink bridge sees it (`None`: no autopilot).
    #[serde(default)]
    pub autopilot: Option<AutopilotStatus>,
    /// The highest seq the server has acknowledged (the vehicle has dropped every batch up to
    /// it): a server whose journal lacks one of them has lost data, and says so.
    #[serde(default)]
    pub acked: Option<u64>,
    /// What the vehicle's instrument delivered (`None`: a simulated sensor).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub readings: Option<ReadingCounts>,
    /// What the vehicle has sent and received over its link so far, by key.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub traffic: Option<LinkTraffic>,
    /// The server's verdict on its sensor when not ok, as its last ack said.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<SensorHealth>,
}

/// A vehicle's traffic so far, by what it is (`batch`, `telemetry`, `mavlink`, `plan_query`
/// out; `ack`, `plan`, `gcs` in): messages and payload bytes (Zenoh's own headers and
/// keep-alives, and TCP/IP's, are on top: a capture on the link measures those).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct LinkTraffic {
    /// Out, by kind: `[messages, bytes]`.
    pub sent: std::collections::BTreeMap<String, [u64; 2]>,
    /// In, by kind: `[messages, bytes]`.
    pub received: std::collections::BTreeMap<String, [u64; 2]>,
}

impl LinkTraffic {
    pub fn send(&mut self, what: &str, bytes: usize) {
        Self::count(&mut self.sent, what, bytes);
    }

    pub fn receive(&mut self, what: &str, bytes: usize) {
        Self::count(&mut self.received, what, bytes);
    }

    fn count(map: &mut std::collections::BTreeMap<String, [u64; 2]>, what: &str, bytes: usize) {
        let c = map.entry(what.to_string()).or_default();
        c[0] += 1;
        c[1] += bytes as u64;
    }

    /// Payload bytes both ways.
    pub fn bytes(&self) -> u64 {
        self.sent.values().chain(self.received.values()).map(|c| c[1]).sum()
    }
}

/// A vehicle's instrument readings so far: received, accepted, and refused by kind
/// ([`crate::instrument::Refusal`]'s names).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ReadingCounts {
    /// Readings the instrument delivered.
    pub received: u64,
    /// Readings taken into samples.
    pub accepted: u64,
    /// Readings refused, by kind of refusal.
    pub refused: std::collections::BTreeMap<String, u64>,
    /// Frames taken that had no value at any cell (no-data throughout, or off the site): a
    /// camera that saw nothing, counted among the accepted, with nothing to assimilate.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub empty_frames: u64,
}

impl Telemetry {
    /// Whether the planner may allocate this vehicle: no autopilot, or one still being set up,
    /// or one in GUIDED mode. An operator's mode (hold, return, mission) or a lost autopilot
    /// takes it out of the allocation until it is back.
    pub fn available(&self) -> bool {
        self.autopilot.as_ref().is_none_or(|a| match a.link {
            AutopilotLink::Connecting => true,
            AutopilotLink::Up => a.guided,
            AutopilotLink::Lost => false,
        })
    }
}

/// An autopilot's link to its vehicle node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum AutopilotLink {
    /// No HEARTBEAT yet, or the node is still arming it and setting GUIDED.
    #[default]
    Connecting,
    Up,
    /// No HEARTBEAT within the timeout.
    Lost,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct AutopilotStatus {
    /// Whether the node hears the autopilot.
    pub link: AutopilotLink,
    /// MAVLink system id (0 before the first HEARTBEAT).
    pub sysid: u8,
    /// Mode by name (`GUIDED`, `HOLD`, `AUTO`, ...).
    pub mode: String,
    /// Armed, as its HEARTBEAT says.
    pub armed: bool,
    /// In GUIDED mode, armed: the fleet's planner drives it.
    pub guided: bool,
    /// Frames from the autopilot that did not parse, and ground-station frames refused.
    #[serde(default)]
    pub unreadable: u64,
    /// Ground-station frames the node did not pass to the autopilot.
    #[serde(default)]
    pub refused_from_gcs: u64,
    /// Why the autopilot left the planner's mode, as it said it (a low battery, a fence
    /// breach), until it is back in GUIDED.
    #[serde(default)]
    pub failsafe: Option<String>,
    /// What it waits for before the planner drives it (a GPS fix, the EKF, pre-arm checks,
    /// arming, a takeoff), with the autopilot's own refusal; or why it was left to the operator.
    #[serde(default)]
    pub waiting: Option<String>,
}

/// The highest gap-free `seq` of a vehicle the server has assimilated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Ack {
    /// Whose batches.
    pub vehicle: VehicleId,
    /// The highest `seq` such that every batch up to it is assimilated (journalled): the vehicle may drop them.
    pub seq: u64,
    /// The vehicle's sensor verdict when it is not ok ([`crate::health`]; absent: ok), so the
    /// vehicle knows, and says in its telemetry, that its readings are doubted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<SensorHealth>,
}

/// The model the server publishes on `model/latest`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ModelUpdate {
    /// The model's version: one more at every assimilated epoch.
    pub version: u64,
    /// The newest epoch assimilated.
    pub epoch: u64,
    /// Step of the snapshot the amplitudes are fitted to (forecasts count from it).
    pub step: u64,
    /// The model grid the per-cell arrays are on (row-major).
    pub grid: Grid,
    /// Time between the model's snapshots (continuous-time eigenvalues are `ln(lambda) / dt`).
    pub dt: f64,
    /// Discrete-time eigenvalues `[re, im]`, one per mode.
    pub eigenvalues: Vec<[f64; 2]>,
    /// Modes, row-major `N x r`, real and imaginary parts separately; empty in the model put on
    /// `model/latest` every epoch (which then carries `estimate`), held in the one a get on that
    /// key answers: an observer that forecasts asks for them. The per-cell arrays travel
    /// as `f32` (schema 4): an observer draws or forecasts the field from them, to a relative
    /// 6e-8 (half an `f32` ulp), far inside any sensor's noise, at half the bytes (27 MB
    /// rather than 54 at 384 x 768). The eigenvalues and amplitudes, raised to powers in a
    /// forecast, stay `f64`. The server keeps its own `f64` arrays (`estimate.npy`).
    #[serde(with = "floats")]
    #[schemars(with = "floats::PackedSchema<f32>")]
    pub modes_re: Vec<f32>,
    /// The modes' imaginary parts, as `modes_re`.
    #[serde(with = "floats")]
    #[schemars(with = "floats::PackedSchema<f32>")]
    pub modes_im: Vec<f32>,
    /// Each mode's amplitude `[re, im]` at `step`.
    pub amplitudes: Vec<[f64; 2]>,
    /// The newest fused estimate per cell (step `step`; the filter's posterior mean), which
    /// the modes alone do not hold (they leave out the filter's detail). Empty from a server
    /// that did not send it.
    #[serde(default, with = "floats")]
    #[schemars(with = "floats::PackedSchema<f32>")]
    pub estimate: Vec<f32>,
    /// Per-cell error variance the newest estimate (step `step`) reports: the fusion's
    /// posterior variance.
    #[serde(with = "floats")]
    #[schemars(with = "floats::PackedSchema<f32>")]
    pub variance: Vec<f32>,
    /// How many steps after `step` the forecast variance is for (the next boat step).
    pub forecast_steps: u64,
    /// Per-cell variance of the forecast `forecast_steps` ahead.
    #[serde(with = "floats")]
    #[schemars(with = "floats::PackedSchema<f32>")]
    pub forecast_variance: Vec<f32>,
    /// The cells off the model grid (no data in the truth: land), ascending; their values
    /// above are zeros that stand for nothing. Absent from a server without them.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub land: Vec<u32>,
    /// The field's mean level the modes' anomalies are about: a forecast at a wet cell is
    /// `level + (Phi Lambda^t b)` there (0 from a server that modelled the field itself).
    #[serde(default)]
    pub level: f64,
}

impl ModelUpdate {
    /// Takes the modes out (the model as `model/latest` is put every epoch), and gives them back.
    pub fn take_modes(&mut self) -> [Vec<f32>; 2] {
        [std::mem::take(&mut self.modes_re), std::mem::take(&mut self.modes_im)]
    }

    /// Whether the model on `n` cells gives an observer a field to draw: all its modes, or none
    /// and its estimate (as `model/latest` is put: a get asks for the modes).
    pub fn has_a_field(&self, n: usize) -> bool {
        let r = self.eigenvalues.len();
        let whole = self.modes_re.len() == n * r && self.modes_im.len() == n * r;
        let lean = self.modes_re.is_empty() && self.modes_im.is_empty() && self.estimate.len() == n;
        whole || lean
    }
}

/// One target of a plan: a sampling step of the vehicle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Target {
    /// The epoch the target is for.
    pub epoch: u64,
    /// The mission step to sense at.
    pub step: u64,
    /// Where to be, metres `(x, y)`, and the sensing radius there (cells; 0 for aerials).
    pub position: [f64; 2],
    /// The sensing radius there, cells (0 for aerials).
    pub radius: f64,
    /// What to sense there: a boat's disk, an aerial's region of the coarse lattice (flat grid
    /// indices, on the wire as runs; empty: nothing, the vehicle still reports for the epoch).
    #[serde(with = "cells")]
    #[schemars(with = "cells::RunsSchema")]
    pub cells: Vec<u32>,
}

/// A vehicle's allocation from `epoch` on, for the next H epochs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Plan {
    /// Whose plan.
    pub vehicle: VehicleId,
    /// The model version the plan was made from.
    pub model_version: u64,
    /// The first epoch it covers.
    pub epoch: u64,
    /// One target per sampling step, in step order.
    pub targets: Vec<Target>,
}

/// The server's own status on `server/status`: model version, counters and its view of the
/// links.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ServerStatus {
    /// The model version published last.
    pub version: u64,
    /// The epoch the server waits for next, and whether the mission is done.
    pub next_epoch: u64,
    /// Whether every epoch of the mission is assimilated.
    pub finished: bool,
    /// Batches taken (first copies, replays from the journal included).
    pub batches: u64,
    /// Batches received again after they were taken (a vehicle resending before its ack).
    pub duplicates: u64,
    /// Refusals by reason.
    pub rejected: std::collections::BTreeMap<String, u64>,
    /// Vehicles whose liveliness token is present.
    pub alive: Vec<VehicleId>,
    /// Vehicles whose batch for the next epoch is missing (the lag), and epochs waiting
    /// complete or in part behind it.
    pub waiting_for: Vec<VehicleId>,
    /// Epochs with batches waiting behind the next one.
    pub pending_epochs: u64,
    /// The median time from the last batch of an epoch arriving to its model being published
    /// (ms).
    pub latency_p50_ms: f64,
    /// The 99th percentile of the same (ms).
    pub latency_p99_ms: f64,
    /// Each instrument-fed vehicle's readings (received, accepted, refused by kind), from its
    /// telemetry.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub readings: std::collections::BTreeMap<VehicleId, ReadingCounts>,
    /// Why each vehicle the next epoch waits for is behind, in words (from its liveliness and
    /// its last telemetry), once the epoch has waited a while.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub behind: std::collections::BTreeMap<VehicleId, String>,
    /// The model's skill at the last epoch assimilated (`fusion = "kalman"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skill: Option<EpochSkill>,
    /// Each tested sensor's verdict and why ([`crate::health`]).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub health: std::collections::BTreeMap<VehicleId, SensorHealth>,
    /// The operator's sensor overrides taken so far (a sender sees its own taken).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub overrides: u64,
    /// The boats' held-out readings against the estimate so far (`[scoring] holdout`), with
    /// their squared z-scores by decile of the reported variance: the estimate's check of its
    /// own uncertainty without a truth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout: Option<HoldoutScore>,
}

/// The hold-out's figures over a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct HoldoutScore {
    /// Held-out readings scored.
    pub readings: usize,
    /// Mean squared difference between the held-out readings and the estimate.
    pub mse: f64,
    /// The readings' mean noise variance: `mse - noise_var` estimates the estimate's own MSE
    /// at the held-out cells.
    pub noise_var: f64,
    /// Share of held-out readings inside the estimate's 95% interval.
    pub coverage_95: f64,
    /// Mean normalised squared error (1 when the reported variance is right).
    pub normalised: f64,
    /// The readings by decile of the variance the estimate reported at their cells (smallest
    /// first): whether the reported variance is right where it is small and where it is
    /// large, not only on average. Empty with fewer than ten readings.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub by_decile: Vec<HeldDecile>,
    /// The expected normalised calibration error over those deciles: the mean of
    /// `|RMV - RMSE| / RMV`, the root mean reported variance against the root of the mean
    /// squared difference less the readings' noise (0: right in every decile).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ence: Option<f64>,
}

/// One decile of the held-out readings by reported variance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct HeldDecile {
    /// Readings in the decile.
    pub readings: usize,
    /// The mean variance the estimate reported at the readings' cells.
    pub variance: f64,
    /// The mean squared z-score, `(value - estimate)^2 / (variance + noise)`: 1 when the
    /// reported variance is right in this decile, above 1 overconfident.
    pub z2: f64,
    /// The mean squared difference less the mean noise variance (the estimate's own error
    /// there, at least 0).
    pub error: f64,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

/// A sensor's verdict ([`crate::health`]).
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
    schemars::JsonSchema,
    strum::Display,
    strum::EnumString,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case")]
pub enum Health {
    #[default]
    Ok,
    Suspect,
    Excluded,
}

/// A sensor's verdict now, and why (empty when ok).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SensorHealth {
    /// The verdict.
    pub state: Health,
    /// Why, in words (empty when ok).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub reason: String,
}

/// A change of a sensor's verdict: which vehicle (its id on the wire, its roster index inside
/// the server), at which step, from what to what, and why (an event and a line of the summary).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorVerdict<V = VehicleId> {
    pub vehicle: V,
    pub step: u64,
    pub from: Health,
    pub to: Health,
    pub reason: String,
}

/// The operator's verdict on a sensor from a step on: `set` pins it (`ok`: every value trusted
/// as it came; `excluded`: withheld), `None` hands it back to the tests. Sent by the ground
/// station's seat on `server/sensor/<vehicle>`; the server journals it and re-fits from its
/// step when that is already in the model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SensorOverride {
    /// Whose sensor.
    pub vehicle: VehicleId,
    /// The first step the verdict holds from.
    pub from_step: u64,
    /// The verdict pinned (`ok` or `excluded`), or absent to hand the sensor back to the tests.
    pub set: Option<Health>,
}

/// How much the model was worth in one epoch, as the filter measured it (no truth needed).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct EpochSkill {
    /// The epoch measured.
    pub epoch: u64,
    /// The forecast's skill against the aerials' lattice over the epoch's steps: 1 - (its mean
    /// squared error there, less the aerials' noise) / (the lattice values' variance). 1 is a
    /// perfect forecast, 0 no better than the field's mean, below 0 worse (`None`: no lattice).
    pub forecast: Option<f64>,
    /// How far the fused map between the lattice follows the filter rather than the aerials'
    /// interpolation, as the boats have measured (0: the aerials' own; 1: the filter's).
    pub between: f64,
}

/// Every message, tagged by `type`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum Body {
    Batch(MeasurementBatch),
    Telemetry(Telemetry),
    Ack(Ack),
    Model(ModelUpdate),
    Plan(Plan),
    Status(ServerStatus),
    Override(SensorOverride),
}

#[derive(Serialize, Deserialize)]
struct Wire {
    v: u16,
    #[serde(flatten)]
    body: Body,
}

/// [`Wire`] as it is written: the body borrowed, not copied (a model at 192 x 384 is 13 MB).
#[derive(Serialize)]
struct WireOut<'a> {
    v: u16,
    #[serde(flatten)]
    body: &'a Body,
}

/// Encode a message with the current schema version.
pub fn encode(body: &Body) -> Vec<u8> {
    // A model is mostly its packed float arrays: room for them at once, not grown by doubling
    // (each doubling copied all so far into fresh pages).
    let capacity = match body {
        Body::Model(m) => {
            let floats = [&m.modes_re, &m.modes_im, &m.estimate, &m.variance, &m.forecast_variance];
            4096 + 4 * floats.iter().map(|f| f.len()).sum::<usize>() + 16 * m.amplitudes.len()
        }
        _ => 256,
    };
    let mut out = Vec::with_capacity(capacity);
    ciborium::into_writer(
        &WireOut {
            v: SCHEMA_VERSION,
            body,
        },
        &mut out,
    )
    .expect("writing CBOR to memory cannot fail");
    out
}

/// Limits and knowledge a receiver checks messages against.
#[derive(Debug, Clone)]
pub struct Context {
    pub grid: Grid,
    /// Known vehicle ids (empty: any well-formed id).
    pub vehicles: Vec<VehicleId>,
    pub max_payload: usize,
    /// Most samples in one batch and most cells in one sample.
    pub max_samples: usize,
    pub max_cells: usize,
}

impl Context {
    pub fn new(grid: Grid) -> Self {
        Self {
            grid,
            vehicles: vec![],
            max_payload: MAX_PAYLOAD,
            max_samples: 10_000,
            max_cells: grid.len(),
        }
    }

    /// For messages that carry no cells (the server's status, an override): any grid reads them.
    pub fn cell_free() -> Self {
        Self::new(Grid::new(1, 1, 1.0).expect("a 1 x 1 grid"))
    }
}

/// Decode and validate one payload.
pub fn decode(bytes: &[u8], ctx: &Context) -> Result<Body, ProtocolError> {
    if bytes.len() > ctx.max_payload {
        return Err(ProtocolError::TooLarge {
            size: bytes.len(),
            limit: ctx.max_payload,
        });
    }
    // The version first, so an incompatible sender gets the right error, not "malformed".
    #[derive(Deserialize)]
    struct Version {
        v: u16,
    }
    let mut cursor = std::io::Cursor::new(bytes);
    let value: ciborium::Value =
        ciborium::from_reader(&mut cursor).map_err(|e| ProtocolError::Malformed(e.to_string()))?;
    let rest = bytes.len() - cursor.position() as usize;
    if rest > 0 {
        return Err(ProtocolError::Trailing(rest));
    }
    let v: Version = value
        .deserialized()
        .map_err(|e| ProtocolError::Malformed(format!("no schema version: {e}")))?;
    if v.v != SCHEMA_VERSION {
        return Err(ProtocolError::Version { got: v.v });
    }
    let wire: Wire = value.deserialized().map_err(|e| match e {
        // A well-formed message whose id is not one (the id's own check, as it is read).
        ciborium::value::Error::Custom(m) if m.starts_with(VehicleId::REFUSED) => ProtocolError::Invalid(m),
        e => ProtocolError::Malformed(e.to_string()),
    })?;
    validate(&wire.body, ctx)?;
    Ok(wire.body)
}

fn finite<T: Copy + Into<f64>>(what: &str, v: &[T]) -> Result<(), ProtocolError> {
    match v.iter().position(|x| !(*x).into().is_finite()) {
        Some(i) => Err(ProtocolError::Invalid(format!("{what}[{i}] is not finite"))),
        None => Ok(()),
    }
}

fn vehicle(id: &str, ctx: &Context) -> Result<(), ProtocolError> {
    keys::check_id("vehicle", id)?;
    if !ctx.vehicles.is_empty() && !ctx.vehicles.iter().any(|v| v == id) {
        return Err(ProtocolError::UnknownVehicle(id.into()));
    }
    Ok(())
}

fn position(p: [f64; 2], grid: &Grid) -> Result<(), ProtocolError> {
    finite("position", &p)?;
    if p[0] < 0.0 || p[1] < 0.0 || p[0] > grid.width_m() || p[1] > grid.height_m() {
        return Err(ProtocolError::Invalid(format!(
            "position {p:?} outside the {} x {} m workspace",
            grid.width_m(),
            grid.height_m()
        )));
    }
    Ok(())
}

/// Check a decoded message against the receiver's context.
///
/// Long because it is one arm per message kind, each beside the others it resembles.
pub fn validate(body: &Body, ctx: &Context) -> Result<(), ProtocolError> {
    let inv = |m: String| Err(ProtocolError::Invalid(m));
    let n = ctx.grid.len();
    match body {
        Body::Batch(b) => {
            vehicle(&b.vehicle, ctx)?;
            finite("noise", &[b.noise.sigma0, b.noise.growth_per_m])?;
            if b.noise.sigma0 < 0.0 || b.noise.growth_per_m < 0.0 {
                return inv("noise must be >= 0".into());
            }
            // An empty batch is a vehicle reporting an epoch in which it had nothing to sense.
            if b.samples.len() > ctx.max_samples {
                return inv(format!(
                    "a batch holds at most {} samples, got {}",
                    ctx.max_samples,
                    b.samples.len()
                ));
            }
            for (k, s) in b.samples.iter().enumerate() {
                position(s.position, &ctx.grid)?;
                if s.cells.len() != s.values.len() {
                    return inv(format!(
                        "sample {k}: {} cells but {} values",
                        s.cells.len(),
                        s.values.len()
                    ));
                }
                if s.cells.len() > ctx.max_cells {
                    return inv(format!(
                        "sample {k}: at most {} cells, got {}",
                        ctx.max_cells,
                        s.cells.len()
                    ));
                }
                if let Some(c) = s.cells.iter().find(|&&c| c as usize >= n) {
                    return inv(format!("sample {k}: cell {c} outside the {n}-cell grid"));
                }
                finite(&format!("sample {k} values"), &s.values)?;
                if let Some(sd) = &s.sigma {
                    if sd.len() != s.values.len() || !sd.iter().all(|v| v.is_finite() && *v > 0.0) {
                        return inv(format!("sample {k}: sigma wants one finite value > 0 per value"));
                    }
                }
            }
        }
        Body::Telemetry(t) => {
            vehicle(&t.vehicle, ctx)?;
            position(t.position, &ctx.grid)?;
            finite("telemetry", &[t.heading, t.battery])?;
            if t.readings
                .as_ref()
                .is_some_and(|r| r.refused.len() > 32 || r.refused.keys().any(|k| k.len() > 32))
            {
                return inv("reading counts: at most 32 kinds of refusal, names of at most 32 characters".into());
            }
            if t.autopilot.as_ref().is_some_and(|a| a.mode.len() > 32) {
                return inv("autopilot mode name over 32 characters".into());
            }
            // A STATUSTEXT is at most 50 characters.
            if t.autopilot
                .as_ref()
                .and_then(|a| a.failsafe.as_ref())
                .is_some_and(|f| f.len() > 64)
            {
                return inv("autopilot failsafe text over 64 characters".into());
            }
            if !(0.0..=1.0).contains(&t.battery) {
                return inv(format!("battery {} outside 0..1", t.battery));
            }
        }
        Body::Ack(a) => vehicle(&a.vehicle, ctx)?,
        Body::Override(o) => vehicle(&o.vehicle, ctx)?,
        Body::Model(m) => {
            if m.grid != ctx.grid {
                return inv(format!("model grid {:?} is not ours {:?}", m.grid, ctx.grid));
            }
            let r = m.eigenvalues.len();
            if !m.has_a_field(n) || m.amplitudes.len() != r || m.variance.len() != n || m.forecast_variance.len() != n {
                return inv(format!(
                    "model of rank {r} on {n} cells has {} / {} mode values, {} amplitudes, {} variances, {} forecast \
                        variances",
                    m.modes_re.len(),
                    m.modes_im.len(),
                    m.amplitudes.len(),
                    m.variance.len(),
                    m.forecast_variance.len()
                ));
            }
            if !(m.estimate.is_empty() || m.estimate.len() == n) {
                return inv(format!("an estimate of {} values on {n} cells", m.estimate.len()));
            }
            if m.variance.iter().chain(&m.forecast_variance).any(|v| *v < 0.0) {
                return inv("a variance is negative".into());
            }
            if !(m.dt.is_finite() && m.dt > 0.0) {
                return inv(format!("dt {} must be positive", m.dt));
            }
            finite("eigenvalues", m.eigenvalues.as_flattened())?;
            finite("amplitudes", m.amplitudes.as_flattened())?;
            finite("modes_re", &m.modes_re)?;
            finite("modes_im", &m.modes_im)?;
            finite("estimate", &m.estimate)?;
            finite("variance", &m.variance)?;
            finite("forecast_variance", &m.forecast_variance)?;
        }
        Body::Status(s) => {
            finite("latency", &[s.latency_p50_ms, s.latency_p99_ms])?;
            for id in s.alive.iter().chain(&s.waiting_for).chain(s.readings.keys()) {
                keys::check_id("vehicle", id)?;
            }
            if s.readings
                .values()
                .any(|r| r.refused.len() > 32 || r.refused.keys().any(|k| k.len() > 32))
            {
                return inv("reading counts: at most 32 kinds of refusal, names of at most 32 characters".into());
            }
        }
        Body::Plan(p) => {
            vehicle(&p.vehicle, ctx)?;
            if p.targets.len() > ctx.max_samples {
                return inv(format!("plan of {} targets", p.targets.len()));
            }
            for t in &p.targets {
                position(t.position, &ctx.grid)?;
                if !(t.radius.is_finite() && t.radius >= 0.0) {
                    return inv(format!("target radius {}", t.radius));
                }
                if t.cells.len() > ctx.max_cells {
                    return inv(format!("target of {} cells", t.cells.len()));
                }
                if let Some(c) = t.cells.iter().find(|&&c| c as usize >= n) {
                    return inv(format!("target cell {c} outside the {n}-cell grid"));
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ctx() -> Context {
        let mut c = Context::new(Grid::new(4, 5, 1.0).unwrap());
        c.vehicles = vec![
            "boat-1".parse::<VehicleId>().unwrap(),
            "av-1".parse::<VehicleId>().unwrap(),
        ];
        c
    }

    fn batch() -> Body {
        Body::Batch(MeasurementBatch {
            vehicle: "boat-1".parse::<VehicleId>().unwrap(),
            kind: VehicleKind::Boat,
            seq: 3,
            noise: Noise {
                sigma0: 0.1,
                growth_per_m: 0.0,
            },
            samples: vec![Sample {
                step: 10,
                position: [1.5, 2.5],
                cells: vec![0, 7, 19],
                values: vec![0.3, 0.4, 0.5],
                sigma: None,
            }],
        })
    }

    #[test]
    fn round_trips_every_message() {
        let g = Grid::new(4, 5, 1.0).unwrap();
        let msgs = vec![
            batch(),
            Body::Telemetry(Telemetry {
                vehicle: "av-1".parse::<VehicleId>().unwrap(),
                step: 2,
                position: [0.0, 4.0],
                heading: 1.0,
                battery: 0.5,
                link: LinkState::Down,
                outbox_depth: 7,
                autopilot: None,
                acked: Some(3),
                readings: None,
                traffic: None,
                sensor: None,
            }),
            Body::Ack(Ack {
                vehicle: "boat-1".parse::<VehicleId>().unwrap(),
                seq: 9,
                sensor: Some(SensorHealth {
                    state: Health::Excluded,
                    reason: "stuck: its values repeat".into(),
                }),
            }),
            Body::Model(ModelUpdate {
                version: 1,
                epoch: 2,
                step: 40,
                grid: g,
                dt: 0.25,
                eigenvalues: vec![[0.9, 0.1]],
                modes_re: vec![0.1; 20],
                modes_im: vec![0.0; 20],
                amplitudes: vec![[1.0, 0.0]],
                estimate: vec![0.5; 20],
                variance: vec![0.01; 20],
                forecast_steps: 5,
                forecast_variance: vec![0.02; 20],
                land: vec![],
                level: 0.0,
            }),
            Body::Plan(Plan {
                vehicle: "boat-1".parse::<VehicleId>().unwrap(),
                model_version: 1,
                epoch: 3,
                targets: vec![Target {
                    epoch: 3,
                    step: 45,
                    position: [2.0, 2.0],
                    radius: 1.5,
                    cells: vec![0, 1, 5],
                }],
            }),
        ];
        for m in msgs {
            assert_eq!(decode(&encode(&m), &ctx()).unwrap(), m);
        }
    }

    #[test]
    fn the_wire_is_a_flat_cbor_map_with_version_and_type() {
        let v: ciborium::Value = ciborium::from_reader(&encode(&batch())[..]).unwrap();
        let map = v.as_map().unwrap();
        let get = |k: &str| map.iter().find(|(a, _)| a.as_text() == Some(k)).map(|(_, b)| b.clone());
        assert_eq!(
            get("v").and_then(|x| x.as_integer()).map(i128::from),
            Some(SCHEMA_VERSION as i128)
        );
        assert_eq!(
            get("type").and_then(|x| x.as_text().map(str::to_string)).as_deref(),
            Some("batch")
        );
        assert_eq!(
            get("vehicle").and_then(|x| x.as_text().map(str::to_string)).as_deref(),
            Some("boat-1")
        );
        // A sample's values: one byte string of packed f64s ([`floats`]), not a list.
        let samples = get("samples").unwrap();
        let first = samples.as_array().unwrap()[0].as_map().unwrap().clone();
        let values = first.iter().find(|(k, _)| k.as_text() == Some("values")).unwrap();
        assert!(values.1.is_bytes(), "{:?}", values.1);
    }

    #[test]
    fn refuses_what_it_cannot_use() {
        let c = ctx();
        let good = encode(&batch());
        let mut trailing = good.clone();
        trailing.push(0);
        assert_eq!(decode(&trailing, &c), Err(ProtocolError::Trailing(1)));
        assert_eq!(decode(&good[..good.len() - 1], &c).unwrap_err().reason(), "malformed");
        let mut small = c.clone();
        small.max_payload = 8;
        assert_eq!(decode(&good, &small).unwrap_err().reason(), "too_large");
        // Another schema version.
        let mut v1 = vec![];
        ciborium::into_writer(&Wire { v: 1, body: batch() }, &mut v1).unwrap();
        assert_eq!(decode(&v1, &c), Err(ProtocolError::Version { got: 1 }));
        let bad = |f: &dyn Fn(&mut MeasurementBatch)| {
            let Body::Batch(mut b) = batch() else { unreachable!() };
            f(&mut b);
            decode(&encode(&Body::Batch(b)), &c).unwrap_err()
        };
        assert_eq!(
            bad(&|b| b.vehicle = "boat-2".parse::<VehicleId>().unwrap()).reason(),
            "unknown_vehicle"
        );
        // An id that is not one cannot be built: it is written into the CBOR instead.
        let Body::Batch(b) = batch() else { unreachable!() };
        let mut value = ciborium::Value::serialized(&Wire {
            v: SCHEMA_VERSION,
            body: Body::Batch(b),
        })
        .unwrap();
        if let ciborium::Value::Map(m) = &mut value {
            m.iter_mut()
                .filter(|(k, _)| k.as_text() == Some("vehicle"))
                .for_each(|(_, v)| *v = ciborium::Value::Text("boat/1".into()));
        }
        let mut bytes = vec![];
        ciborium::into_writer(&value, &mut bytes).unwrap();
        assert_eq!(decode(&bytes, &c).unwrap_err().reason(), "invalid");
        assert!(bad(&|b| b.samples[0].values[1] = f64::NAN)
            .to_string()
            .contains("not finite"));
        assert!(bad(&|b| b.samples[0].cells[2] = 20)
            .to_string()
            .contains("outside the 20-cell grid"));
        assert!(bad(&|b| b.samples[0].values.pop().map(|_| ()).unwrap_or(()))
            .to_string()
            .contains("3 cells but 2 values"));
        assert!(bad(&|b| b.samples[0].position = [9.0, 1.0])
            .to_string()
            .contains("outside"));
        let mut huge = c.clone();
        huge.max_samples = 0;
        assert!(decode(&good, &huge)
            .unwrap_err()
            .to_string()
            .contains("at most 0 samples"));
        assert!(bad(&|b| b.noise.sigma0 = -1.0).to_string().contains("noise"));
    }

    /// The model put every epoch leaves out its modes and carries its estimate; a model with
    /// neither, or with half its modes, gives an observer nothing to draw: refused.
    #[test]
    fn a_model_without_its_modes_must_carry_its_estimate() {
        let c = ctx();
        let whole = ModelUpdate {
            version: 1,
            epoch: 2,
            step: 40,
            grid: c.grid,
            dt: 0.25,
            eigenvalues: vec![[0.9, 0.1]],
            modes_re: vec![0.1; 20],
            modes_im: vec![0.0; 20],
            amplitudes: vec![[1.0, 0.0]],
            estimate: vec![],
            variance: vec![0.01; 20],
            forecast_steps: 5,
            forecast_variance: vec![0.02; 20],
            land: vec![],
            level: 0.0,
        };
        let check = |m: &ModelUpdate| decode(&encode(&Body::Model(m.clone())), &c);
        assert!(check(&whole).is_ok());
        let lean = ModelUpdate {
            modes_re: vec![],
            modes_im: vec![],
            estimate: vec![0.5; 20],
            ..whole.clone()
        };
        assert_eq!(check(&lean), Ok(Body::Model(lean.clone())));
        for bad in [
            ModelUpdate {
                estimate: vec![],
                ..lean.clone()
            },
            ModelUpdate {
                modes_im: vec![],
                ..whole.clone()
            },
        ] {
            assert!(check(&bad).unwrap_err().to_string().contains("mode values"), "{bad:?}");
        }
    }

    #[test]
    fn random_bytes_never_panic() {
        use rand::{RngExt, SeedableRng};
        let c = ctx();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let good = encode(&batch());
        let mut refused = 0;
        for i in 0..20_000 {
            let bytes: Vec<u8> = if i % 2 == 0 {
                (0..rng.random_range(0..64)).map(|_| rng.random()).collect()
            } else {
                // Mutate a valid message: flip, drop or insert bytes.
                let mut b = good.clone();
                for _ in 0..rng.random_range(1..4) {
                    let at = rng.random_range(0..b.len());
                    match rng.random_range(0..3) {
                        0 => b[at] ^= 1 << rng.random_range(0..8),
                        1 => {
                            b.remove(at);
                        }
                        _ => b.insert(at, rng.random()),
                    }
                }
                b
            };
            if decode(&bytes, &c).is_err() {
                refused += 1;
            }
        }
        assert!(refused > 15_000, "{refused}");
    }
}
