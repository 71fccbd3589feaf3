//! A mission's recording (`recording.mcap`, the MCAP log format the robotics tools read): the
//! Zenoh traffic the model server saw and sent, each message at its receive time, and the
//! server core's operations in the order it made them. The traffic is for people and tools
//! (Foxglove, `mcap`, Python); the operations make the recording replayable: the core is pure,
//! so applying them again to a fresh core gives the same model bit for bit.
//!
//! Channels: the key of each message as its topic (`<mission>/vehicle/boat-1/measurements`,
//! `.../model/latest`, `.../plan/boat-1`, ...) with encoding `cbor` (the wire protocol's
//! bytes, as they were), `server/events` in `json` (the `--events` stream), and
//! [`CORE_TOPIC`] with the [`CoreOp`]s in `cbor`. A metadata record [`HEADER`] carries the
//! mission file and the workspace, so a recording replays on its own.

use fleet_math::grid::Grid;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::{self, Body, Context, MeasurementBatch};
use fleet_mission::server::ServerCore;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

/// The channel of the core's operations.
pub const CORE_TOPIC: &str = "server/core";
/// The channel of the server's events (JSON, one per message).
pub const EVENTS_TOPIC: &str = "server/events";
/// The JSON of header entry `k` (its default where the recording is older than the entry).
fn metadata<T: serde::de::DeserializeOwned + Default>(
    h: &std::collections::BTreeMap<String, String>,
    k: &str,
) -> Result<T, String> {
    h.get(k).map_or(Ok(T::default()), |f| {
        serde_json::from_str(f).map_err(|e| format!("its `{HEADER}` metadata `{k}`: {e}"))
    })
}

/// The metadata record with the mission and its workspace.
pub const HEADER: &str = "hetfleet";

/// One operation of the server core, as the node made it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoreOp {
    /// The node started from its journal: these batches (encoded) and epoch records.
    Restore {
        batches: Vec<Vec<u8>>,
        records: Vec<(String, Vec<u8>)>,
    },
    /// The batch recorded as message `arrival` (its sequence number) went to
    /// `ServerCore::ingest_deferred`.
    Ingest { arrival: u32 },
    /// `ServerCore::settle` (late batches re-fit the model).
    Settle,
    /// `ServerCore::force` (an epoch timed out).
    Force,
    /// `ServerCore::set_available` from a vehicle's telemetry.
    Available {
        vehicle: fleet_mission::protocol::VehicleId,
        available: bool,
    },
    /// `ServerCore::override_sensor` from the operator, then `ServerCore::settle`.
    Override(fleet_mission::protocol::SensorOverride),
}

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("{}: {why}", path.display())]
    Io { path: PathBuf, why: String },
    /// The file is not a readable recording, or is cut short.
    #[error("{}: {why}", path.display())]
    Bad { path: PathBuf, why: String },
    /// Applying the recorded operations failed: the recording does not fit this build's core.
    #[error("{}: replaying operation {index} ({op}): {why}", path.display())]
    Replay {
        path: PathBuf,
        index: usize,
        op: String,
        why: String,
    },
}

impl RecordingError {
    pub fn is_bad_file(&self) -> bool {
        matches!(self, Self::Bad { .. })
    }
}

/// Nanoseconds since the Unix epoch (MCAP's log time).
pub fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// What a recording keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, strum::Display, strum::EnumString)]
#[strum(serialize_all = "lowercase")]
pub enum RecordMode {
    /// Everything the server saw and sent, uncompressed, each model as published.
    Full,
    /// What `fleet replay` needs to rebuild the model bit for bit (the core's operations, every
    /// batch, plan, telemetry and event) and the Foxglove channels, in zstd chunks closed at
    /// every flush; of the published models, every [`LEAN_MODEL_EVERY`]th and the last.
    #[default]
    Lean,
}

/// A lean recording keeps one published model in this many (and always the last).
pub const LEAN_MODEL_EVERY: u64 = 50;

/// Writes a recording as the node goes. A full recording writes records straight to the file
/// (no chunks), a lean one in compressed chunks closed at each [`Recorder::flush`]: either way
/// a flushed recording is readable up to its last flush even if the node dies.
pub struct Recorder<W: Write + Seek> {
    w: mcap::Writer<W>,
    path: PathBuf,
    mode: RecordMode,
    channels: BTreeMap<String, u16>,
    schemas: BTreeMap<String, u16>,
    next: u32,
    /// Models published so far, and the newest one a lean recording has not kept yet.
    models: u64,
    held_model: Option<(String, Vec<u8>, u64)>,
    /// The Foxglove channels' translation of what is recorded.
    view: Option<crate::foxglove::FoxgloveView>,
}

impl Recorder<BufWriter<std::fs::File>> {
    /// Start a recording at `path`, or beside it (`recording.1.mcap`, ...) if `path` exists: a
    /// restarted server does not overwrite its first life's recording.
    pub fn create(
        path: &Path,
        mode: RecordMode,
        mission: &MissionConfig,
        mission_toml: &str,
        grid: &Grid,
        frames: usize,
    ) -> Result<Self, RecordingError> {
        let mut path = path.to_path_buf();
        let stem = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
        let mut k = 0;
        while path.exists() {
            k += 1;
            path = path.with_file_name(format!("{stem}.{k}.mcap"));
        }
        let io = |e: &dyn std::fmt::Display| RecordingError::Io {
            path: path.clone(),
            why: e.to_string(),
        };
        let file = std::fs::File::create(&path).map_err(|e| io(&e))?;
        let lean = mode == RecordMode::Lean;
        let opts = mcap::WriteOptions::new()
            .compression(lean.then_some(mcap::Compression::Zstd))
            .use_chunks(lean)
            // A lean recording's chunks close at each flush (an epoch), not by size.
            .chunk_size(None)
            .profile("hetfleet")
            .library(concat!("hetfleet-", env!("CARGO_PKG_VERSION")));
        let mut w = opts.create(BufWriter::new(file)).map_err(|e| io(&e))?;
        let meta = BTreeMap::from([
            ("mission_toml".to_string(), mission_toml.to_string()),
            ("rows".into(), grid.rows.to_string()),
            ("cols".into(), grid.cols.to_string()),
            ("cell_m".into(), grid.cell_m.to_string()),
            ("frames".into(), frames.to_string()),
            ("mode".into(), mode.to_string()),
            // The boundary as read (the file it came from need not travel with the recording).
            (
                "fence".into(),
                serde_json::to_string(&mission.team.fence).expect("a fence serialises"),
            ),
            // The land the truth left off the model grid (the truth need not travel either).
            (
                "land".into(),
                serde_json::to_string(&mission.team.land).expect("cells serialise"),
            ),
        ]);
        w.write_metadata(&mcap::records::Metadata {
            name: HEADER.into(),
            metadata: meta,
        })
        .map_err(|e| io(&e))?;
        Ok(Self {
            w,
            path,
            mode,
            channels: BTreeMap::new(),
            schemas: BTreeMap::new(),
            next: 0,
            models: 0,
            held_model: None,
            view: None,
        })
    }
}

impl<W: Write + Seek> Recorder<W> {
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn failed(&self, e: impl std::fmt::Display) -> RecordingError {
        RecordingError::Io {
            path: self.path.clone(),
            why: e.to_string(),
        }
    }

    /// Translate what is recorded into Foxglove's channels too (from here on).
    pub fn with_foxglove(mut self, view: crate::foxglove::FoxgloveView) -> Result<Self, RecordingError> {
        let ns = now_ns();
        for m in view.start() {
            self.fox_message(&m, ns)?;
        }
        self.view = Some(view);
        Ok(self)
    }

    /// The channel of `topic`, added (with `schema`, if any) on first use.
    fn channel(
        &mut self,
        topic: &str,
        encoding: &str,
        schema: Option<&foxglove::Schema>,
    ) -> Result<u16, RecordingError> {
        if let Some(&id) = self.channels.get(topic) {
            return Ok(id);
        }
        let schema_id = match schema {
            None => 0,
            Some(s) => match self.schemas.get(&s.name) {
                Some(&id) => id,
                None => {
                    let id = self
                        .w
                        .add_schema(&s.name, &s.encoding, &s.data)
                        .map_err(|e| self.failed(e))?;
                    self.schemas.insert(s.name.clone(), id);
                    id
                }
            },
        };
        let id = self
            .w
            .add_channel(schema_id, topic, encoding, &BTreeMap::new())
            .map_err(|e| self.failed(e))?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    fn fox_message(&mut self, m: &crate::foxglove::FoxMessage, log_ns: u64) -> Result<u32, RecordingError> {
        let c = &m.channel;
        let channel_id = self.channel(&c.topic, &c.encoding, Some(&c.schema))?;
        self.write(channel_id, &m.data, log_ns)
    }

    /// Record `body` (encoded as `data`) on `topic` at `log_ns`, and its Foxglove translation;
    /// returns the sequence number of `data`, or `None` where a lean recording holds it back
    /// (a model between the ones it keeps).
    pub fn body(&mut self, topic: &str, body: &Body, data: &[u8], log_ns: u64) -> Result<Option<u32>, RecordingError> {
        let seq = if matches!(body, Body::Model(_)) {
            self.model(topic, data, log_ns)?
        } else {
            Some(self.message(topic, "cbor", data, log_ns)?)
        };
        self.foxglove(body, log_ns)?;
        Ok(seq)
    }

    /// Only the Foxglove translation of `body` (its own bytes recorded already).
    pub fn foxglove(&mut self, body: &Body, log_ns: u64) -> Result<(), RecordingError> {
        let Some(view) = self.view.as_ref() else { return Ok(()) };
        for m in view.of(body, log_ns) {
            self.fox_message(&m, log_ns)?;
        }
        Ok(())
    }

    /// A published model: recorded, or in a lean recording held unless it is one to keep.
    fn model(&mut self, topic: &str, data: &[u8], log_ns: u64) -> Result<Option<u32>, RecordingError> {
        self.models += 1;
        if self.mode == RecordMode::Full || self.models.is_multiple_of(LEAN_MODEL_EVERY) {
            self.held_model = None;
            return self.message(topic, "cbor", data, log_ns).map(Some);
        }
        self.held_model = Some((topic.to_string(), data.to_vec(), log_ns));
        Ok(None)
    }

    /// Record `data` on `topic` at `log_ns`; returns its sequence number.
    pub fn message(&mut self, topic: &str, encoding: &str, data: &[u8], log_ns: u64) -> Result<u32, RecordingError> {
        let channel_id = self.channel(topic, encoding, None)?;
        self.write(channel_id, data, log_ns)
    }

    fn write(&mut self, channel_id: u16, data: &[u8], log_ns: u64) -> Result<u32, RecordingError> {
        let sequence = self.next;
        self.next += 1;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence,
            log_time: log_ns,
            publish_time: log_ns,
        };
        self.w
            .write_to_known_channel(&header, data)
            .map_err(|e| self.failed(e))?;
        Ok(sequence)
    }

    /// Record one operation of the core.
    pub fn op(&mut self, op: &CoreOp) -> Result<(), RecordingError> {
        let mut bytes = vec![];
        ciborium::into_writer(op, &mut bytes).expect("an operation serialises");
        self.message(CORE_TOPIC, "cbor", &bytes, now_ns()).map(drop)
    }

    /// Make what is recorded so far durable in the file (readable if the node dies next).
    pub fn flush(&mut self) -> Result<(), RecordingError> {
        self.w.flush().map_err(|e| self.failed(e))
    }

    /// End the recording (its summary and footer), with the last model a lean one held.
    pub fn finish(mut self) -> Result<(), RecordingError> {
        if let Some((topic, data, log_ns)) = self.held_model.take() {
            self.message(&topic, "cbor", &data, log_ns)?;
        }
        self.w.finish().map_err(|e| self.failed(e))?;
        Ok(())
    }
}

/// One recorded message.
#[derive(Debug, Clone)]
pub struct Recorded {
    pub topic: String,
    pub sequence: u32,
    pub log_ns: u64,
    pub data: Vec<u8>,
}

/// A recording read whole and checked.
pub struct Recording {
    pub mission: MissionConfig,
    pub mission_toml: String,
    pub grid: Grid,
    pub frames: usize,
    pub messages: Vec<Recorded>,
}

impl Recording {
    /// Read `path`; a file that is not a finished recording (cut short, not MCAP, no header)
    /// is refused.
    pub fn read(path: &Path) -> Result<Self, RecordingError> {
        let bad = |why: String| RecordingError::Bad { path: path.into(), why };
        let bytes = std::fs::read(path).map_err(|e| RecordingError::Io {
            path: path.into(),
            why: e.to_string(),
        })?;
        let mut header = None;
        let mut topics: BTreeMap<u16, String> = BTreeMap::new();
        let mut messages = vec![];
        let mut footer = false;
        // Chunks (a lean recording's) opened in place: their records in order.
        let reader =
            mcap::read::ChunkFlattener::new(&bytes).map_err(|e| bad(format!("not an MCAP recording ({e})")))?;
        for record in reader {
            let record = record.map_err(|e| {
                bad(format!(
                    "cut short or damaged after {} messages ({e}): the recording did not end (was the server killed?)",
                    messages.len()
                ))
            })?;
            match record {
                mcap::records::Record::Metadata(m) if m.name == HEADER => header = Some(m.metadata),
                mcap::records::Record::Channel(c) => {
                    topics.insert(c.id, c.topic);
                }
                mcap::records::Record::Message { header, data } => {
                    let topic = topics.get(&header.channel_id).cloned().ok_or_else(|| {
                        bad(format!(
                            "message {} names channel {} before it is defined",
                            header.sequence, header.channel_id
                        ))
                    })?;
                    messages.push(Recorded {
                        topic,
                        sequence: header.sequence,
                        log_ns: header.log_time,
                        data: data.into_owned(),
                    });
                }
                mcap::records::Record::Footer(_) => footer = true,
                _ => {}
            }
        }
        if !footer {
            return Err(bad(format!(
                "cut short after {} messages: the recording did not end (was the server killed?)",
                messages.len()
            )));
        }
        let h = header.ok_or_else(|| bad(format!("no `{HEADER}` metadata: not a hetfleet recording")))?;
        let field = |k: &str| {
            h.get(k)
                .cloned()
                .ok_or_else(|| bad(format!("its `{HEADER}` metadata has no `{k}`")))
        };
        let num = |k: &str| -> Result<usize, RecordingError> {
            field(k)?
                .parse()
                .map_err(|e| bad(format!("its `{HEADER}` metadata `{k}`: {e}")))
        };
        let mission_toml = field("mission_toml")?;
        let mut mission = MissionConfig::from_toml(&mission_toml).map_err(|e| bad(format!("its mission: {e}")))?;
        // Recordings made before boundaries (masks) existed have no `fence` (`land`): none.
        mission.team.fence = metadata(&h, "fence").map_err(&bad)?;
        mission.team.land = metadata(&h, "land").map_err(&bad)?;
        let cell_m: f64 = field("cell_m")?
            .parse()
            .map_err(|e| bad(format!("its `{HEADER}` metadata `cell_m`: {e}")))?;
        let grid = Grid::new(num("rows")?, num("cols")?, cell_m).map_err(|e| bad(format!("its workspace: {e}")))?;
        let frames = num("frames")?;
        Ok(Self {
            mission,
            mission_toml,
            grid,
            frames,
            messages,
        })
    }

    /// The messages on topics ending in `suffix`.
    pub fn on<'a>(&'a self, suffix: &'a str) -> impl Iterator<Item = &'a Recorded> + 'a {
        self.messages.iter().filter(move |m| m.topic.ends_with(suffix))
    }

    /// The last model the server published.
    pub fn final_model(&self) -> Option<&Recorded> {
        self.on("/model/latest").last()
    }

    /// A fresh core of this mission with every recorded operation applied, in order. `each`
    /// sees each operation's log time (for pacing) before it is applied.
    pub fn replay(&self, path: &Path, mut each: impl FnMut(u64, &CoreOp)) -> Result<ServerCore, RecordingError> {
        let mut r = self.replayer(path)?;
        for m in self.messages.iter().filter(|m| m.topic == CORE_TOPIC) {
            r.apply(m, &mut each)?;
        }
        Ok(r.core)
    }

    /// A fresh core of this mission, to apply the recorded operations to one by one.
    pub fn replayer<'a>(&'a self, path: &'a Path) -> Result<Replayer<'a>, RecordingError> {
        let core = ServerCore::new(&self.mission.team, self.grid, self.frames)
            .map_err(|e| RecordingError::Bad {
                path: path.into(),
                why: format!("its mission makes no core: {e}"),
            })?
            .with_boat_speed(self.mission.motion.boat_speed);
        let mut ctx = Context::new(self.grid);
        ctx.vehicles = core.vehicles().iter().map(|v| v.id.clone()).collect();
        Ok(Replayer {
            path,
            core,
            ctx,
            by_seq: self.messages.iter().map(|m| (m.sequence, m)).collect(),
            index: 0,
        })
    }
}

/// A core the recorded operations are applied to, in their order: `fleet replay` applies them
/// all at once, `model-server --replay` as it plays them (its models are this core's).
pub struct Replayer<'a> {
    path: &'a Path,
    pub core: ServerCore,
    ctx: Context,
    by_seq: BTreeMap<u32, &'a Recorded>,
    /// Operations applied so far.
    index: usize,
}

impl Replayer<'_> {
    /// Apply the operation recorded as `m` (on [`CORE_TOPIC`]); `each` sees it first.
    pub fn apply(&mut self, m: &Recorded, each: &mut impl FnMut(u64, &CoreOp)) -> Result<(), RecordingError> {
        let (path, index) = (self.path, self.index);
        self.index += 1;
        let op: CoreOp = ciborium::from_reader(&m.data[..]).map_err(|e| RecordingError::Bad {
            path: path.into(),
            why: format!("operation {index} does not decode: {e}"),
        })?;
        let fail = |why: String| RecordingError::Replay {
            path: path.into(),
            index,
            op: format!("{op:?}").chars().take(60).collect(),
            why,
        };
        each(m.log_ns, &op);
        let decode = |bytes: &[u8]| -> Result<MeasurementBatch, String> {
            match protocol::decode(bytes, &self.ctx) {
                Ok(Body::Batch(b)) => Ok(b),
                Ok(_) => Err("not a batch".into()),
                Err(e) => Err(e.to_string()),
            }
        };
        let core = &mut self.core;
        match &op {
            CoreOp::Restore { batches, records } => {
                let batches = batches
                    .iter()
                    .map(|b| decode(b))
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(&fail)?;
                core.restore(batches, records).map_err(|e| fail(e.to_string()))?;
            }
            CoreOp::Ingest { arrival } => {
                let raw = self
                    .by_seq
                    .get(arrival)
                    .ok_or_else(|| fail(format!("message {arrival} is not in the recording")))?;
                let batch = decode(&raw.data).map_err(&fail)?;
                // Refusals are part of what happened: the core counts them as it did live.
                match core.ingest_deferred(batch) {
                    Ok(_)
                    | Err(fleet_mission::server::IngestError::Rejected { .. })
                    | Err(fleet_mission::server::IngestError::Protocol(_)) => {}
                    Err(e) => return Err(fail(e.to_string())),
                }
            }
            CoreOp::Settle => core.settle().map(drop).map_err(|e| fail(e.to_string()))?,
            CoreOp::Force => core.force().map(drop).map_err(|e| fail(e.to_string()))?,
            CoreOp::Available { vehicle, available } => {
                core.set_available(vehicle, *available);
            }
            CoreOp::Override(o) => {
                // A refused override is part of what happened too: the core took nothing.
                if core.override_sensor(o).is_ok() {
                    core.settle().map_err(|e| fail(e.to_string()))?;
                }
            }
        }
        Ok(())
    }
}
