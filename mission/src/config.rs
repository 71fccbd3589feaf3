//! The mission file (`config/mission.toml`): which field, which team, how the nodes reach each
//! other and how fast the mission runs. Every node of a mission reads the same file, so the
//! server and each vehicle agree on the grid, the schedule and the vehicles without talking.

use crate::instrument::clock::TimeConfig;
use crate::instrument::source::Sensors;
use crate::instrument::{MissionClock, SensorSource};
use crate::protocol::{keys, Noise, VehicleKind};
use crate::roster::{Roster, VehicleSpec};
use crate::schedule::Schedule;
use crate::team::TeamConfig;
use fleet_math::grid::Grid;
use fleet_math::process::truth::{averaged_by, TruthError, TruthSource};
use fleet_math::process::FieldSeries;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// A field out of its range (`[table] key: rule`).
fn field(table: &'static str, key: impl Into<Option<String>>, rule: impl Into<String>) -> ConfigError {
    ConfigError::Field {
        table,
        key: key.into(),
        rule: rule.into(),
    }
}

/// What is wrong with a mission file, or with a node's inputs against it. Every variant is the
/// operator's to fix (exit 2), named by file or field.
#[derive(Debug, thiserror::Error, strum::VariantNames)]
pub enum ConfigError {
    /// Not a mission file: its TOML (syntax, a type, an unknown key), reason first, then where.
    #[error("{0}")]
    Toml(String),
    /// A field out of its range: its table, the key (with the value given), and the rule.
    #[error("[{table}]{}: {rule}", key.as_ref().map(|k| format!(" {k}")).unwrap_or_default())]
    Field {
        table: &'static str,
        key: Option<String>,
        rule: String,
    },
    /// The mission's id, which every key expression carries.
    #[error("{0}")]
    MissionId(crate::protocol::ProtocolError),
    /// The site's boundary file (`[mavlink] boundary`).
    #[error("[mavlink] boundary: {0}")]
    Boundary(String),
    /// A node's `--id` that is not a vehicle of the mission.
    #[error("--id {id}: no such vehicle in mission {mission:?} (it has {known})")]
    UnknownVehicle { id: String, mission: String, known: String },
    /// More vehicles than MAVLink has system ids.
    #[error("{id}: MAVLink has system ids 1-254 only (the mission has {vehicles} vehicles)")]
    TooManyVehicles { id: String, vehicles: usize },
    /// A truth whose grid is not a grid.
    #[error("the truth's grid: {0}")]
    TruthGrid(fleet_math::grid::GridError),
    /// A node's `--truth` of another shape than the mission senses.
    #[error(
        "--truth {} is {} x {} cells for {} steps, but mission {mission:?} senses {} x {} cells for {} steps: give \
         the truth `fleet up` or the server made for this mission (every node must sense the same field)",
        path.display(), got.0, got.1, got.2, want.0, want.1, want.2
    )]
    TruthShape {
        path: std::path::PathBuf,
        mission: String,
        got: (usize, usize, usize),
        want: (usize, usize, usize),
    },
    #[error("{}: {source}", path.display())]
    Read {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("{file}: {source}")]
    InFile { file: String, source: Box<ConfigError> },
    #[error("[team] {0}")]
    Team(crate::team::TeamError),
}

/// The bundled default mission (`fleet up` without an argument).
pub const DEFAULT_MISSION: &str = include_str!("../../config/mission.toml");

/// The mixed-reality truth: a simulator preset or a dataset, on `grid`, averaged by
/// `average` onto the model grid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TruthSpec {
    #[serde(flatten)]
    pub source: TruthSource,
    /// Simulator grid `[rows, cols]` for a preset (96 x 192 unless given); a dataset's grid is
    /// its file's, and a `grid` beside one is refused (it would be ignored).
    #[serde(default)]
    pub grid: Option<[usize; 2]>,
    /// Steps of the mission: the truth's frames (a dataset's first `frames`).
    #[serde(default = "default_frames")]
    pub frames: usize,
    /// The truth is area-averaged over blocks of this many cells a side onto the model grid
    /// (the simulator's 96 x 192 by 2 is the default mission's 48 x 96).
    #[serde(default = "one")]
    pub average: usize,
}

impl TruthSpec {
    /// The simulator's grid (a dataset ignores it).
    pub fn sim_grid(&self) -> [usize; 2] {
        self.grid.unwrap_or([96, 192])
    }
}
fn default_frames() -> usize {
    100
}
fn one() -> usize {
    1
}

/// The model grid and the mission's length, for a mission without a truth (`[field]`): the
/// instruments' readings land on `grid` cells of 1 grid metre (`[mavlink] size_m` places them
/// on the Earth), and the mission runs `frames` steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FieldSpec {
    /// Model grid `[rows, cols]`.
    pub grid: [usize; 2],
    /// Steps of the mission.
    pub frames: usize,
}

/// How nodes reach each other (Zenoh endpoints; a Zenoh JSON5 file may override anything).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Network {
    /// Where the server, in router mode, listens.
    pub listen: Vec<String>,
    /// Where vehicles connect (the server or a `zenohd` router).
    pub connect: Vec<String>,
    /// Optional Zenoh JSON5 configs, applied before the endpoints above.
    pub server_config: Option<std::path::PathBuf>,
    /// `{id}` in it is the node's id (`secure/{id}.json5`: each vehicle its own credentials).
    pub vehicle_config: Option<std::path::PathBuf>,
    /// Zenoh link lease (ms): how soon a silent link counts as lost (Zenoh's default 10 s).
    pub lease_ms: Option<u64>,
}

impl Network {
    /// This network as node `id` sees it: `{id}` in the vehicle config's path replaced.
    pub fn for_node(&self, id: &str) -> Self {
        let mut n = self.clone();
        n.vehicle_config = n
            .vehicle_config
            .map(|p| std::path::PathBuf::from(p.to_string_lossy().replace("{id}", id)));
        n
    }
}

impl Default for Network {
    fn default() -> Self {
        Self {
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: vec!["tcp/127.0.0.1:7447".into()],
            server_config: None,
            vehicle_config: None,
            lease_ms: None,
        }
    }
}

/// Pace of a mixed-reality run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Pace {
    /// Wall-clock milliseconds per step (0: as fast as the plans come).
    pub step_ms: u64,
    /// How long a vehicle waits for the plan of its next epoch before it follows the horizon
    /// of the plan it holds.
    pub plan_timeout_ms: u64,
    /// How often unacknowledged batches are sent again.
    pub resend_ms: u64,
    /// Epochs each plan covers.
    pub horizon: u64,
    /// How long the server waits for a late vehicle's batch before it assimilates an epoch
    /// without it (0: wait for every batch); the late batch re-fits the model when it comes.
    pub epoch_timeout_ms: u64,
}

impl Default for Pace {
    fn default() -> Self {
        Self {
            step_ms: 0,
            plan_timeout_ms: 30_000,
            resend_ms: 1_000,
            horizon: 3,
            epoch_timeout_ms: 0,
        }
    }
}

/// The radio between the vehicles and the base: what crosses it besides the mission's own data,
/// and how long a question over it may take. The defaults fit a SiK-class telemetry radio
/// (64 kbit/s on air, shared by the fleet, a few hundred ms of round trip).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Link {
    /// The link's rate (kbit/s) and round trip (ms): a plan reply's transfer time and the
    /// round trip bound how long a vehicle waits for an answer before it asks again.
    pub rate_kbps: f64,
    /// The link's round trip (ms): with `rate_kbps`, how long a vehicle waits for an answer
    /// before it asks again.
    pub rtt_ms: u64,
    /// Each periodic message of the autopilot's stream (position, status, battery) goes to the
    /// ground stations at most this often (Hz); events (text, command and mission replies,
    /// parameters) always go. The full stream stays on the vehicle.
    pub mavlink_hz: f64,
}

impl Default for Link {
    fn default() -> Self {
        Self {
            rate_kbps: 64.0,
            rtt_ms: 300,
            mavlink_hz: 1.0,
        }
    }
}

impl Link {
    fn check(&self) -> Result<(), ConfigError> {
        if !(self.rate_kbps.is_finite() && self.rate_kbps > 0.0) {
            return Err(field("link", format!("rate_kbps = {}", self.rate_kbps), "must be > 0"));
        }
        if !(self.mavlink_hz.is_finite() && self.mavlink_hz >= 0.0) {
            return Err(field(
                "link",
                format!("mavlink_hz = {}", self.mavlink_hz),
                "must be >= 0",
            ));
        }
        Ok(())
    }

    /// How long the autopilot's periodic frames wait to share one put to the gateway: one
    /// period of the forwarded stream, at most a second (none when nothing periodic goes).
    pub fn mavlink_linger(&self) -> std::time::Duration {
        let period = if self.mavlink_hz > 0.0 {
            1.0 / self.mavlink_hz
        } else {
            0.0
        };
        std::time::Duration::from_secs_f64(period.min(1.0))
    }

    /// How long a question whose answer is `bytes` long may take over the link: its round trip
    /// and the answer's transfer at the link's rate, four times over (a lossy link resends),
    /// and never less than 2 s.
    pub fn answer_within(&self, bytes: usize) -> std::time::Duration {
        let transfer_s = bytes as f64 * 8.0 / (self.rate_kbps * 1000.0);
        let s = 4.0 * (self.rtt_ms as f64 / 1000.0 + transfer_s);
        std::time::Duration::from_secs_f64(s.max(2.0))
    }
}

/// Vehicle kinematics (metres per step on the model grid, 1 m cells).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Motion {
    /// How far an aerial goes in one step (model-grid metres: cells).
    pub aerial_speed: f64,
    /// How far a boat goes in one step (model-grid metres: cells); horizon placement plans
    /// only disks a boat reaches by its sampling step.
    pub boat_speed: f64,
}

impl Default for Motion {
    fn default() -> Self {
        Self {
            aerial_speed: 200.0,
            boat_speed: 40.0,
        }
    }
}

/// How vehicle nodes reach their autopilots and ground stations (MAVLink 2, common dialect).
/// The workspace grid is placed on the Earth by `origin` (its (0, 0) corner) and `size_m`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MavlinkConfig {
    /// Each vehicle's autopilot: `sim` (a simulated one in the vehicle node), `none` (the
    /// node's own kinematics, no MAVLink), or a connection string (`udpin:`, `udpout:`,
    /// `tcpout:`, `serial:/dev/ttyUSB0:57600`). A vehicle's `--autopilot` overrides it.
    pub autopilot: String,
    /// Where the ground-station gateway offers the whole fleet (`udpout:` to where QGroundControl
    /// or MAVProxy listens, or `udpin:` to be connected to); empty: no gateway.
    pub gcs: String,
    /// Latitude and longitude (degrees) and altitude (m, AMSL) of the workspace's (0, 0) corner.
    pub origin: [f64; 3],
    /// Physical extent of the workspace, east and north (m); default: the grid's own metres.
    pub size_m: Option<[f64; 2]>,
    /// The simulated autopilots run this many times faster than the wall clock (SITL's
    /// speed-up), so a 100 m leg of a 2 m/s boat does not hold a test for a minute.
    pub sim_speedup: f64,
    /// A simulated autopilot also listens for a companion computer (an instrument's driver
    /// sending NAMED_VALUE_FLOAT) on UDP `127.0.0.1:(this + its system id)` and routes what
    /// comes there onto its link to the vehicle, as ArduPilot routes between its serial ports
    /// (SITL's second port); unset: no companion link.
    pub sim_companion_port: Option<u16>,
    /// Simulated boat: top speed (m/s) and turn-rate limit (deg/s).
    pub boat_speed_ms: f64,
    /// Simulated boat: turn-rate limit (deg/s).
    pub boat_turn_rate_dps: f64,
    /// Simulated multirotor: top speed (m/s) and cruise altitude above the origin (m).
    pub multirotor_speed_ms: f64,
    /// Copters' cruise altitude above the origin (m): a copter takes off to it before the
    /// planner drives it.
    pub cruise_alt_m: f64,
    /// A target counts as reached within this distance (m, physical), or within the
    /// autopilot's own `WP_RADIUS` (`WPNAV_RADIUS` for copters) when that is larger: the bridge
    /// reads it, and waiting for less than the autopilot stops short of would never end.
    pub acceptance_m: f64,
    /// The autopilots' `FENCE_MARGIN` (m; ArduPilot's default 2) and a boat's turning radius
    /// (`TURN_RADIUS`, m; ArduRover's default 0.9): launch and rally points are set inside the
    /// fence by their sum (a vehicle inside the margin is in a margin breach, which versions
    /// before 4.7 refused to arm in, and a turn from rest sweeps the radius), and a fence that
    /// leaves no such room is refused at load. A bridge
    /// whose autopilot keeps a larger margin says so.
    pub fence_margin_m: f64,
    /// A boat's turning radius (`TURN_RADIUS`, m; ArduRover's default 0.9): launch and rally
    /// points sit inside the fence by it and the margin.
    pub turn_radius_m: f64,
    /// The simulated autopilots' `WP_RADIUS` / `WPNAV_RADIUS` (m; ArduPilot's default 2).
    pub wp_radius_m: f64,
    /// A simulated autopilot has no GPS fix, no EKF origin and no position for this long after
    /// boot (simulated seconds), as a real one waits for satellites.
    pub sim_gps_delay_s: f64,
    /// How long the bridge waits for the autopilot to be ready (a GPS fix, the EKF, its pre-arm
    /// checks) before it asks for GUIDED and arming anyway and leaves the rest to the operator.
    pub ready_timeout_s: f64,
    /// How long a vehicle waits at a sampling step for its autopilot to reach the target
    /// before it senses from where it is.
    pub arrival_timeout_ms: u64,
    /// No HEARTBEAT from the autopilot for this long: autopilot lost.
    pub heartbeat_timeout_ms: u64,
    /// The site's boundary: a QGroundControl `.plan` (its inclusion geofence) or a GeoJSON
    /// polygon, relative to the mission file. The planner keeps every disk and every aerial
    /// place inside it.
    pub boundary: Option<std::path::PathBuf>,
    /// MAVLink 2 signing of the ground-station link: the key file `fleet secure` writes
    /// (`mavlink-signing.key`), relative to the mission file. The gateway then signs what it
    /// sends the ground station and refuses (and counts) unsigned, wrongly signed and replayed
    /// frames from it.
    pub signing_key: Option<std::path::PathBuf>,
    /// Signing of each vehicle's autopilot link: its key file, `{id}` the vehicle's id
    /// (`fleet secure` writes `autopilot/{id}.key`), relative to the mission file. The bridge
    /// signs what it sends the autopilot and refuses its unsigned or wrongly signed frames.
    pub autopilot_signing_key: Option<std::path::PathBuf>,
    /// Take unsigned frames from an autopilot that cannot sign (what is sent to it is still
    /// signed).
    pub accept_unsigned_telemetry: bool,
    /// What an autopilot does on a fence breach (`rtl`, `hold`, or `report`): set as its
    /// `FENCE_ACTION` when the bridge uploads the site's fence and enables it.
    pub fence_action: String,
    /// Drive a vehicle whose autopilot did not confirm the fence (the upload failed, the list
    /// read back differs, or FENCE_ENABLE did not take). Off by default: such a vehicle waits,
    /// unarmed, with the reason on telemetry, the live view and the log; on, the planner alone
    /// keeps it inside and the node says so at start.
    pub drive_without_fence: bool,
    /// Simulated autopilots' battery (mAh), the charge left at which the low-battery failsafe
    /// acts, and how (`rtl`, `hold`, `continue`): their `BATT_CAPACITY`, `BATT_LOW_MAH` and
    /// `BATT_FS_LOW_ACT`.
    pub battery_mah: f64,
    /// Simulated autopilots: the charge left (mAh) at which the low-battery failsafe acts
    /// (`BATT_LOW_MAH`).
    pub battery_low_mah: f64,
    /// Simulated autopilots: what the low-battery failsafe does, `rtl`, `hold` or `continue`
    /// (`BATT_FS_LOW_ACT`).
    pub low_battery_action: String,
    /// What a vehicle does when its link to the model server is lost for `link_loss_s`
    /// seconds: `continue` (boats keep sensing out of range, the default), `rtl` or `hold`.
    /// Back in range, it rejoins (GUIDED again, back in the allocation).
    pub link_loss_action: String,
    /// Seconds without the model server before `link_loss_action` acts.
    pub link_loss_s: f64,
    /// What each autopilot does when the mission is done: `rtl` (back to its launch point; a
    /// copter lands there, as ArduCopter's RTL does), `hold`, or `continue` (left as it is).
    pub end_action: String,
}

/// What a failsafe may do (the autopilot's names: return to launch, stop, go on reporting).
pub const FAILSAFE_ACTIONS: [&str; 4] = ["rtl", "hold", "report", "continue"];

impl Default for MavlinkConfig {
    fn default() -> Self {
        Self {
            autopilot: "none".into(),
            gcs: String::new(),
            // The paper's tank sits nowhere in particular; a harbour basin in Copenhagen.
            origin: [55.6761, 12.5683, 0.0],
            size_m: None,
            sim_speedup: 1.0,
            sim_companion_port: None,
            boat_speed_ms: 2.0,
            boat_turn_rate_dps: 90.0,
            multirotor_speed_ms: 10.0,
            cruise_alt_m: 30.0,
            acceptance_m: 0.25,
            fence_margin_m: 2.0,
            turn_radius_m: 0.9,
            wp_radius_m: 2.0,
            sim_gps_delay_s: 10.0,
            ready_timeout_s: 120.0,
            arrival_timeout_ms: 20_000,
            heartbeat_timeout_ms: 3_000,
            boundary: None,
            signing_key: None,
            autopilot_signing_key: None,
            accept_unsigned_telemetry: false,
            fence_action: "rtl".into(),
            drive_without_fence: false,
            battery_mah: 20_000.0,
            battery_low_mah: 4_000.0,
            low_battery_action: "rtl".into(),
            link_loss_action: "continue".into(),
            link_loss_s: 30.0,
            end_action: "rtl".into(),
        }
    }
}

impl MavlinkConfig {
    /// Where the grid is on the Earth: the origin and the site's extent.
    pub fn site(&self, grid: &Grid) -> crate::site::Site {
        crate::site::Site::new(self.origin, self.size_m, grid)
    }

    /// The autopilot-link key file of vehicle `id`, if the mission signs those links.
    pub fn autopilot_key_of(&self, id: &str) -> Option<std::path::PathBuf> {
        self.autopilot_signing_key
            .as_ref()
            .map(|p| std::path::PathBuf::from(p.to_string_lossy().replace("{id}", id)))
    }

    fn check(&self) -> Result<(), ConfigError> {
        if !(self.link_loss_s.is_finite() && self.link_loss_s > 0.0) {
            return Err(field(
                "mavlink",
                format!("link_loss_s = {}", self.link_loss_s),
                "must be > 0",
            ));
        }
        for (key, v) in [
            ("fence_action", &self.fence_action),
            ("low_battery_action", &self.low_battery_action),
            ("link_loss_action", &self.link_loss_action),
            ("end_action", &self.end_action),
        ] {
            if !FAILSAFE_ACTIONS.contains(&v.as_str()) {
                let rule = format!("one of {}", FAILSAFE_ACTIONS.join(", "));
                return Err(field("mavlink", format!("{key} = {v:?}"), rule));
            }
        }
        if !(self.battery_mah.is_finite()
            && self.battery_mah > 0.0
            && self.battery_low_mah.is_finite()
            && (0.0..self.battery_mah).contains(&self.battery_low_mah))
        {
            let key = format!(
                "battery_mah = {}, battery_low_mah = {}",
                self.battery_mah, self.battery_low_mah
            );
            return Err(field("mavlink", key, "need 0 <= low < capacity"));
        }
        let [lat, lon, alt] = self.origin;
        if !(lat.abs() < 85.0 && lon.abs() <= 180.0 && alt.is_finite()) {
            let rule = "latitude within +-85, longitude within +-180, finite altitude";
            return Err(field("mavlink", "origin".to_string(), rule));
        }
        if let Some([e, n]) = self.size_m {
            if !(e > 0.0 && n > 0.0 && e.is_finite() && n.is_finite()) {
                return Err(field("mavlink", "size_m".to_string(), "two positive extents"));
            }
        }
        let positive = [
            self.sim_speedup,
            self.boat_speed_ms,
            self.boat_turn_rate_dps,
            self.multirotor_speed_ms,
            self.acceptance_m,
        ];
        if !positive.iter().all(|v| *v > 0.0 && v.is_finite()) || !(self.cruise_alt_m >= 0.0) {
            let rule = "speeds, speed-up, turn rate and acceptance must be > 0, cruise_alt_m >= 0";
            return Err(field("mavlink", None, rule));
        }
        if self.heartbeat_timeout_ms == 0 {
            return Err(field("mavlink", None, "heartbeat_timeout_ms must be > 0"));
        }
        let lengths = [
            ("fence_margin_m", self.fence_margin_m),
            ("turn_radius_m", self.turn_radius_m),
            ("wp_radius_m", self.wp_radius_m),
            ("sim_gps_delay_s", self.sim_gps_delay_s),
        ];
        if let Some((key, v)) = lengths.iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
            return Err(field("mavlink", format!("{key} = {v}"), "must be finite and >= 0"));
        }
        if !(self.ready_timeout_s.is_finite() && self.ready_timeout_s > 0.0) {
            return Err(field(
                "mavlink",
                format!("ready_timeout_s = {}", self.ready_timeout_s),
                "must be > 0",
            ));
        }
        Ok(())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MissionConfig {
    /// The mission id: every key lives under `fleet/<mission>/`.
    pub mission: String,
    /// Whether the truth's latitude and longitude placed the site ([`Self::place_by_truth`]),
    /// for [`Self::site_said`]: not a key of the file.
    #[serde(skip)]
    #[schemars(skip)]
    pub placed_by_truth: bool,
    /// The mixed-reality truth: the field the simulated sensors sample and the runs are scored
    /// against. Absent in the field (give `[field]` instead).
    #[serde(default)]
    pub truth: Option<TruthSpec>,
    /// The model grid and the mission's length without a truth.
    #[serde(default)]
    pub field: Option<FieldSpec>,
    #[serde(default)]
    pub team: TeamConfig,
    #[serde(default)]
    pub network: Network,
    #[serde(default)]
    pub pace: Pace,
    /// The radio between the vehicles and the base (`[link]`).
    #[serde(default)]
    pub link: Link,
    #[serde(default)]
    pub motion: Motion,
    #[serde(default)]
    pub mavlink: MavlinkConfig,
    /// Mission time (`[time] start`, `step_s`); without it a step is the simulator's counter.
    #[serde(default)]
    pub time: Option<TimeConfig>,
    /// Where each vehicle's readings come from ([`crate::instrument`]).
    #[serde(default)]
    pub sensors: Sensors,
    /// How a run is scored beyond the truth (`[scoring] holdout`).
    #[serde(default)]
    pub scoring: Scoring,
}

/// `[scoring]`: the share of the boats' readings held out of the fusion to score it
/// ([`crate::holdout`]); unset, 0.1 without a truth and none with one (the truth scores it).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Scoring {
    /// The share (0-1) of the boats' readings held out of the fusion and predicted by the
    /// estimate that never saw them (a fixed hash of step and cell); unset: 0.1 without a
    /// truth, none with one.
    pub holdout: Option<f64>,
}

impl MissionConfig {
    /// Parse and check a mission; every error is bad input (the binaries exit 2), on one line.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let mut cfg: Self = toml::from_str(text).map_err(|e| ConfigError::Toml(toml_error(text, &e)))?;
        if !crate::team::gives_growth(text) {
            cfg.team.aerial_growth_per_cell = crate::team::default_growth(cfg.team.aerial_sigma0);
        }
        cfg.place_by_truth(text)?;
        keys::check_id("mission", &cfg.mission).map_err(ConfigError::MissionId)?;
        match (&cfg.truth, &cfg.field) {
            (Some(t), None) if t.frames < 10 || t.average == 0 => {
                return Err(field("truth", None, "need at least 10 frames and average >= 1"));
            }
            (Some(t), None) if t.grid.is_some() && !matches!(t.source, TruthSource::Preset(_)) => {
                let [r, c] = t.sim_grid();
                let rule = "the simulator's grid goes with a preset: a dataset's grid is its file's; remove it";
                return Err(field("truth", format!("grid = [{r}, {c}]"), rule));
            }
            (None, Some(f)) if f.frames < 10 || f.grid.contains(&0) => {
                return Err(field(
                    "field",
                    None,
                    "need at least 10 frames and a grid of at least one cell",
                ));
            }
            (Some(_), Some(_)) => {
                return Err(field(
                    "field",
                    None,
                    "give [field] only without [truth] (a truth sets the grid)",
                ))
            }
            (None, None) => {
                return Err(field(
                    "truth",
                    None,
                    "give [truth] (mixed reality) or [field] (grid and frames)",
                ))
            }
            _ => {}
        }
        if cfg.network.listen.is_empty() && cfg.network.connect.is_empty() {
            return Err(field("network", None, "give listen or connect endpoints"));
        }
        if !(cfg.motion.aerial_speed > 0.0 && cfg.motion.boat_speed > 0.0) {
            return Err(field("motion", None, "speeds must be > 0"));
        }
        cfg.mavlink.check()?;
        cfg.link.check()?;
        if cfg.pace.horizon == 0 {
            return Err(field("pace", None, "horizon must be >= 1"));
        }
        if let Some(h) = cfg.scoring.holdout {
            if !(0.0..0.5).contains(&h) {
                return Err(field(
                    "scoring",
                    format!("holdout = {h}"),
                    "a share from 0 to below 0.5",
                ));
            }
        }
        if let Some(t) = &cfg.time {
            MissionClock::of(t).map_err(|(key, rule)| field("time", key.to_string(), rule))?;
        }
        cfg.sensors
            .check(
                &cfg.roster(),
                crate::instrument::source::Mission {
                    timed: cfg.time.is_some(),
                    truth: cfg.truth.is_some(),
                    autopilot: cfg.mavlink.autopilot != "none",
                },
            )
            .map_err(|(key, rule)| field("sensors", key, rule))?;
        Ok(cfg)
    }

    /// A NetCDF truth with latitude and longitude places the site where `[mavlink]` gives
    /// neither `origin` nor `size_m`: the grid's corner at the file's south-west cell edge, its
    /// extent the file's (east at the southern edge's scale, as [`crate::site::Site`] maps it).
    /// A latitude or longitude that cannot place it (not evenly spaced) is refused.
    fn place_by_truth(&mut self, text: &str) -> Result<(), ConfigError> {
        let given = text
            .parse::<toml::Table>()
            .ok()
            .and_then(|t| t.get("mavlink").and_then(|m| m.as_table()).cloned())
            .is_some_and(|m| m.contains_key("origin") || m.contains_key("size_m"));
        let Some(TruthSource::NetCdf { path, variable, select }) = self.truth.as_ref().map(|t| &t.source) else {
            return Ok(());
        };
        if given {
            return Ok(());
        }
        let placed = fleet_math::process::netcdf::bounds(path, variable, select);
        let Some([south, west, north, east]) =
            placed.map_err(|e| field("truth", "dataset".to_string(), e.to_string()))?
        else {
            return Ok(());
        };
        const R: f64 = crate::site::EARTH_RADIUS_M;
        self.placed_by_truth = true;
        self.mavlink.origin = [south, west, 0.0];
        self.mavlink.size_m = Some([
            (east - west).to_radians() * R * south.to_radians().cos(),
            (north - south).to_radians() * R,
        ]);
        Ok(())
    }

    /// Where the site is on the Earth and why, in one line: its south-west corner, extent and
    /// cell size in metres, and whether the truth's latitude and longitude placed it
    /// ([`Self::place_by_truth`]), the mission's `[mavlink] origin`, or the default origin (a
    /// truth without latitude and longitude is not on the Earth: its map is put there).
    pub fn site_said(&self, grid: &Grid) -> String {
        let m = &self.mavlink;
        let site = m.site(grid);
        let (east, north) = (grid.width_m() * site.scale.x, grid.height_m() * site.scale.y);
        let truth = self.truth.as_ref().map(|t| &t.source);
        let why = match (truth, self.placed_by_truth) {
            (Some(TruthSource::NetCdf { path, .. }), true) => {
                format!("from the latitude and longitude of {}", path.display())
            }
            _ if m.origin == MavlinkConfig::default().origin => {
                "the default origin: give [mavlink] origin and size_m to put it where it is".into()
            }
            _ => "the mission's [mavlink] origin".into(),
        };
        let hemi = |v: f64, pos: char, neg: char| format!("{:.5}{}", v.abs(), if v < 0.0 { neg } else { pos });
        format!(
            "south-west corner {} {}, {east:.0} m east x {north:.0} m north, cells of {:.1} x {:.1} m ({why})",
            hemi(m.origin[0], 'N', 'S'),
            hemi(m.origin[1], 'E', 'W'),
            east / grid.cols as f64,
            north / grid.rows as f64,
        )
    }

    /// The mission file at `path`, or the bundled default.
    pub fn load(path: Option<&Path>) -> Result<Self, ConfigError> {
        let in_file = |file: String| {
            move |e| ConfigError::InFile {
                file,
                source: Box::new(e),
            }
        };
        match path {
            Some(p) => {
                let text = std::fs::read_to_string(p).map_err(|source| ConfigError::Read { path: p.into(), source })?;
                let mut cfg = Self::from_toml(&text).map_err(in_file(p.display().to_string()))?;
                // Key files are read where they are used (a node reads only its own).
                if let Some(dir) = p.parent() {
                    for k in [&mut cfg.mavlink.signing_key, &mut cfg.mavlink.autopilot_signing_key]
                        .into_iter()
                        .flatten()
                    {
                        *k = dir.join(&*k);
                    }
                }
                if let Some(b) = &cfg.mavlink.boundary {
                    let file = p.parent().map_or_else(|| b.clone(), |d| d.join(b));
                    let fence = crate::fence::load(&file, cfg.mavlink.origin, cfg.mavlink.size_m)
                        .map_err(|e| ConfigError::Boundary(e.to_string()));
                    cfg.team.fence = Some(fence.map_err(in_file(p.display().to_string()))?);
                }
                Ok(cfg)
            }
            None => Self::from_toml(DEFAULT_MISSION).map_err(in_file("the bundled default mission".into())),
        }
    }

    /// The truth on the model grid (runs the simulator: seconds to minutes); `None` for a
    /// mission without one.
    pub fn truth(&self, progress: impl FnMut(usize)) -> Result<Option<FieldSeries>, TruthError> {
        let Some(t) = &self.truth else { return Ok(None) };
        let step_s = self.time.as_ref().map(|c| c.step_s);
        let full = t
            .source
            .full((t.sim_grid(), t.frames, self.team.seed), step_s, progress)?;
        averaged_by(&full, t.average).map(Some)
    }

    /// Where the truth has no value in any frame (land) is off the model grid: every node and
    /// every replay of the mission sets it from the truth here.
    /// `land` is the truth's ([`FieldSeries::land`]; none without a truth).
    pub fn adopt_land(&mut self, land: Vec<u32>) {
        self.team.land = land;
    }

    /// Steps in the mission as the file says them (a dataset's may be fewer).
    pub fn frames_hint(&self) -> usize {
        self.truth
            .as_ref()
            .map_or_else(|| self.field.as_ref().map_or(0, |f| f.frames), |t| t.frames)
    }

    /// The workspace grid and length: a truth's (checked against the team), or `[field]`'s.
    /// Bad input: a truth that does not fit the team (see [`TeamConfig::validate`]).
    /// `truth` is the truth's `(rows, cols, frames)` ([`FieldSeries::shape`]).
    pub fn workspace(&self, truth: Option<(usize, usize, usize)>) -> Result<(Grid, usize), ConfigError> {
        let (rows, cols, frames) = match (truth, &self.field) {
            (Some(t), _) => t,
            (None, Some(f)) => (f.grid[0], f.grid[1], f.frames),
            (None, None) => return Err(field("truth", None, "no truth given and no [field] to size the grid")),
        };
        let grid = Grid::new(rows, cols, 1.0).map_err(ConfigError::TruthGrid)?;
        self.team.validate(&grid, frames).map_err(ConfigError::Team)?;
        Ok((grid, frames))
    }

    /// The model grid `(rows, cols)` and steps the mission senses, when the mission file alone
    /// says it: a simulator preset always, a dataset when its file can be read here. Every
    /// node's truth must have this shape, or the nodes sense different cells.
    pub fn model_shape(&self) -> Option<(usize, usize, usize)> {
        let Some(t) = &self.truth else {
            return self.field.as_ref().map(|f| (f.grid[0], f.grid[1], f.frames));
        };
        let a = t.average.max(1);
        match &t.source {
            TruthSource::Preset(_) => Some((t.sim_grid()[0] / a, t.sim_grid()[1] / a, t.frames)),
            source => {
                let shape = source.file_shape()?;
                match shape.as_slice() {
                    &[t, r, c] => Some((r / a, c / a, t)),
                    _ => None,
                }
            }
        }
    }

    /// Check a truth given to a node (`--truth`) against [`Self::model_shape`].
    /// `truth` is the truth's `(rows, cols, frames)` ([`FieldSeries::shape`]).
    pub fn check_truth(&self, truth: (usize, usize, usize), path: &Path) -> Result<(), ConfigError> {
        let Some((rows, cols, frames)) = self.model_shape() else {
            return Ok(());
        };
        if truth != (rows, cols, frames) {
            return Err(ConfigError::TruthShape {
                path: path.into(),
                mission: self.mission.clone(),
                got: truth,
                want: (rows, cols, frames),
            });
        }
        Ok(())
    }

    pub fn vehicles(&self) -> Vec<VehicleSpec> {
        self.roster().all().to_vec()
    }

    pub fn roster(&self) -> Roster {
        Roster::of(&self.team)
    }

    pub fn schedule(&self, frames: usize) -> Schedule {
        Schedule::new(&self.team, frames)
    }

    /// A vehicle's index (its random stream) and kind.
    pub fn vehicle(&self, id: &str) -> Result<(usize, VehicleKind), ConfigError> {
        let roster = self.roster();
        roster
            .get(id)
            .map(|v| (v.index, v.kind))
            .ok_or_else(|| ConfigError::UnknownVehicle {
                id: id.to_string(),
                mission: self.mission.clone(),
                known: roster.ids().join(", "),
            })
    }

    /// The mission's clock (`None`: no `[time]`, steps are the simulator's counter).
    pub fn clock(&self) -> Option<MissionClock> {
        self.time.as_ref().and_then(|t| MissionClock::of(t).ok())
    }

    /// The share of boat readings held out to score the run ([`Scoring`]).
    pub fn holdout_share(&self) -> f64 {
        let default = if self.truth.is_some() {
            0.0
        } else {
            crate::holdout::DEFAULT_SHARE
        };
        self.scoring.holdout.unwrap_or(default)
    }

    /// Where vehicle `id`'s readings come from, as the mission says (checked when read).
    pub fn sensor_of(&self, id: &str) -> SensorSource {
        self.sensors.of(id).parse().unwrap_or(SensorSource::Sim)
    }

    /// A vehicle's sensor noise.
    pub fn noise(&self, kind: VehicleKind) -> Noise {
        match kind {
            VehicleKind::Aerial => Noise {
                sigma0: self.team.aerial_sigma0,
                growth_per_m: self.team.aerial_growth_per_cell,
            },
            VehicleKind::Boat => Noise {
                sigma0: self.team.boat_sigma,
                growth_per_m: 0.0,
            },
        }
    }

    /// A vehicle's MAVLink system id: its place in the mission, from 1.
    pub fn sysid(&self, id: &str) -> Result<u8, ConfigError> {
        let (i, _) = self.vehicle(id)?;
        u8::try_from(i + 1)
            .ok()
            .filter(|s| *s < 255)
            .ok_or_else(|| ConfigError::TooManyVehicles {
                id: id.to_string(),
                vehicles: self.roster().len(),
            })
    }

    pub fn speed(&self, kind: VehicleKind) -> f64 {
        match kind {
            VehicleKind::Aerial => self.motion.aerial_speed,
            VehicleKind::Boat => self.motion.boat_speed,
        }
    }
}

/// A TOML error as one line, reason first: `<reason> (at [table] key, line L column C)`.
pub fn toml_error(text: &str, e: &toml::de::Error) -> String {
    let reason = e.message().split_whitespace().collect::<Vec<_>>().join(" ");
    let Some(span) = e.span() else { return reason };
    let start = span.start.min(text.len());
    let line_no = text[..start].matches('\n').count() + 1;
    let line_start = text[..start].rfind('\n').map_or(0, |i| i + 1);
    let col = text[line_start..start].chars().count() + 1;
    let line = text[line_start..].lines().next().unwrap_or("");
    let table = text[..line_start]
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| l.starts_with('['))
        .map(|l| format!("{} ", l.split('#').next().unwrap_or(l).trim()));
    let key = line
        .split_once('=')
        .map(|(k, _)| k.trim())
        .filter(|k| !k.is_empty() && !k.starts_with('['));
    match key {
        Some(k) => format!(
            "{reason} (at {}{k}, line {line_no} column {col})",
            table.unwrap_or_default()
        ),
        None => format!("{reason} (line {line_no} column {col})"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct T {
        team: Team,
    }
    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct Team {
        boats: usize,
    }

    #[test]
    fn a_toml_error_is_one_line_reason_first_with_where() {
        let text = "[team]\nboats = \"five\"\n";
        let e = toml::from_str::<T>(text).unwrap_err();
        let s = toml_error(text, &e);
        assert!(!s.contains('\n'), "{s}");
        assert!(s.starts_with("invalid type"), "{s}");
        assert!(s.contains("[team] boats, line 2"), "{s}");
    }

    /// The default mission with `extra` tables added.
    fn with(extra: &str) -> Result<MissionConfig, ConfigError> {
        MissionConfig::from_toml(&format!("{DEFAULT_MISSION}\n{extra}"))
    }

    #[test]
    fn sensors_and_time_are_checked_against_the_mission() {
        let time = "[time]\nstart = \"2026-11-25T09:00:00Z\"\nstep_s = 2.0\n";
        let m = with(&format!(
            "{time}[sensors]\nboat-2 = \"udp:0.0.0.0:15602\"\nboat-3 = \"stdin\"\n"
        ))
        .unwrap();
        assert_eq!(m.sensor_of("boat-2").to_string(), "udp:0.0.0.0:15602");
        assert_eq!(m.sensor_of("boat-3"), SensorSource::Stdin);
        assert_eq!(m.sensor_of("av-1"), SensorSource::Sim);
        assert_eq!(m.clock().unwrap().start, 1_795_597_200.0);
        assert_eq!(
            MissionConfig::load(None).unwrap().sensor_of("boat-1"),
            SensorSource::Sim
        );
        let refused = |extra: &str| with(extra).unwrap_err().to_string();
        let e = refused("[sensors]\nboat-2 = \"udp:0.0.0.0:15602\"\n");
        assert!(e.contains("[sensors] boat-2") && e.contains("[time]"), "{e}");
        let e = refused(&format!("{time}[sensors]\nboat-9 = \"stdin\"\n"));
        assert!(e.contains("boat-9: not a vehicle of this mission"), "{e}");
        let e = refused(&format!("{time}[sensors]\nav-1 = \"stdin\"\n"));
        assert!(e.contains("[sensors] av-1") && e.contains("frames"), "{e}");
        let e = refused(&format!("{time}[sensors]\ndefault = \"udp:nowhere\"\n"));
        assert!(e.contains("[sensors] default") && e.contains("ADDR:PORT"), "{e}");
        let m = with(&format!("{time}[sensors]\nboat-1 = \"mavlink:SONDE\"\n")).unwrap();
        assert_eq!(m.sensor_of("boat-1"), SensorSource::Mavlink("SONDE".into()));
        let no_autopilot = DEFAULT_MISSION.replace("autopilot = \"sim\"", "autopilot = \"none\"");
        assert_ne!(no_autopilot, DEFAULT_MISSION);
        let e = MissionConfig::from_toml(&format!(
            "{no_autopilot}\n{time}[sensors]\nboat-1 = \"mavlink:SONDE\"\n"
        ))
        .unwrap_err()
        .to_string();
        assert!(e.contains("[sensors] boat-1") && e.contains("autopilot"), "{e}");
        let e = refused("[time]\nstart = \"9 o'clock\"\nstep_s = 1\n");
        assert!(e.contains("[time] start"), "{e}");
        let e = refused("[time]\nstart = \"2026-11-25T09:00:00Z\"\nstep_s = 1\nzone = \"CET\"\n");
        assert!(e.contains("zone"), "{e}");
    }

    #[test]
    fn the_default_mission_reads() {
        let m = MissionConfig::load(None).unwrap();
        assert_eq!(m.vehicles().len(), m.team.aerials + m.team.boats);
        assert!(MissionConfig::from_toml("mission = \"a/b\"\n[truth]\npreset = \"cloud1\"\n").is_err());
        assert!(MissionConfig::from_toml("mission = \"m\"\n[truth]\n")
            .unwrap_err()
            .to_string()
            .contains("[truth]"));
        // A simulator's grid beside a dataset would be ignored: refused, saying why.
        let e = MissionConfig::from_toml("mission = \"m\"\n[truth]\ndataset = \"f.npy\"\ngrid = [8, 8]\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("[truth] grid = [8, 8]: the simulator's grid goes with a preset"),
            "{e}"
        );
    }

    /// The names configurations ask for, and the choices that cannot go together.
    #[test]
    fn team_choices_parse_by_name_and_horizon_needs_the_filter() {
        use crate::team::{LearnFrom, Placement, TeamConfig};
        let t: TeamConfig = toml::from_str(
            "placement = \"horizon\"\nfusion = \"kalman\"\nlearn_from = \"aerial\"\nhorizon_epochs = 2\n",
        )
        .unwrap();
        assert_eq!(
            (t.placement, t.learn_from, t.horizon_epochs),
            (Placement::Horizon, LearnFrom::Aerial, 2)
        );
        t.check_choices().unwrap();
        assert_eq!(TeamConfig::default().learn_from, LearnFrom::Posterior);
        let e = TeamConfig {
            fusion: fleet_math::fusion::Scheme::InverseVariance,
            ..t.clone()
        }
        .check_choices()
        .unwrap_err()
        .to_string();
        assert!(e.contains("needs fusion = \"kalman\""), "{e}");
        assert!(TeamConfig {
            horizon_epochs: 0,
            ..t.clone()
        }
        .check_choices()
        .is_err());
        // Further ahead than the run lasts: refused with the run's length (100 frames, 20
        // initial steps, epochs of 5: 16 epochs).
        let grid = fleet_math::grid::Grid::new(48, 96, 1.0).unwrap();
        TeamConfig {
            horizon_epochs: 16,
            ..t.clone()
        }
        .validate(&grid, 100)
        .unwrap();
        TeamConfig {
            horizon_epochs: 17,
            placement: Placement::Qr,
            ..t.clone()
        }
        .validate(&grid, 100)
        .unwrap();
        let e = TeamConfig {
            horizon_epochs: 1_000_000_000_000,
            ..t
        }
        .validate(&grid, 100)
        .unwrap_err()
        .to_string();
        assert!(e.contains("beyond the run's 16 boat epochs"), "{e}");
        assert!(toml::from_str::<TeamConfig>("learn_from = \"forecast\"\n").is_err());
    }
}
