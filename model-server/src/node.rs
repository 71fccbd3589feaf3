//! The server's event loop: one task owns the `ServerCore` and reacts to batches, plan and
//! model queries, liveliness changes and a status tick. Everything that reaches the core has
//! been decoded and validated; everything refused is counted by reason and logged once.

mod queries;

use crate::departure::Departure;
use crate::publisher::ModelPublisher;
use crate::Args;
use anyhow::Context as _;
use fleet_exit::bad_input;
use fleet_math::process::frames::Frames;
use fleet_mission::config::MissionConfig;
use fleet_mission::events::{Percentiles, ServerEvent, ServerSummary};
use fleet_mission::protocol::{self, keys::Keys, AutopilotLink, Body, Context, ServerStatus, VehicleId};
use fleet_mission::server::{EpochRecord, IngestError, Ingested, ServerCore, OVERRIDE_PREFIX};
use fleet_net::store::{Store, StoreError};
use fleet_net::{zenoh, Role};
use fleet_records::recording::{self, CoreOp, Recorder, RecordingError};
use std::collections::{BTreeMap, BTreeSet};
use std::io::Write as _;
use std::time::{Duration, Instant};
use tracing::{error, info, warn};
use zenoh::sample::SampleKind;

struct Server {
    mission: MissionConfig,
    keys: Keys,
    core: ServerCore,
    ctx: Context,
    /// The mixed-reality truth the run is scored against (`None` in the field).
    truth: Option<std::sync::Arc<Frames>>,
    /// Each instrument-fed vehicle's reading counts, as its telemetry last said.
    readings: BTreeMap<VehicleId, fleet_mission::protocol::ReadingCounts>,
    /// Each vehicle's link traffic, as its telemetry last said.
    traffic: BTreeMap<VehicleId, fleet_mission::protocol::LinkTraffic>,
    /// Each vehicle's last telemetry, and when it came.
    heard: BTreeMap<VehicleId, (Instant, fleet_mission::protocol::Telemetry)>,
    /// Why each vehicle the next epoch waits for is behind (once it has waited a while), and
    /// when that was last said.
    behind: BTreeMap<VehicleId, String>,
    said_behind: Option<Instant>,
    events: bool,
    alive: BTreeSet<VehicleId>,
    link_ups: BTreeMap<VehicleId, u64>,
    latencies: Vec<f64>,
    mse: Vec<f64>,
    /// Every accepted batch, durably, before it is acknowledged: the model is a pure function
    /// of this set, so a restart replays it and carries on.
    journal: Store,
    /// Reasons already logged (each refusal reason is logged once, then only counted).
    logged: BTreeSet<String>,
    started: Instant,
    /// Late batches (vehicle, seq, epoch) taken but not yet re-fitted: a backlog arrives as a
    /// burst, re-fitted once after it.
    late: Vec<(VehicleId, u64, u64)>,
    /// Vehicles already reported as having batches the journal lost.
    lost_reported: BTreeSet<VehicleId>,
    /// Plan queries held until their plan exists.
    held_queries: Vec<HeldQuery>,
    /// The mission's recording (`--record`): traffic and the core's operations. A recording
    /// that cannot be written is dropped with one warning; the mission goes on.
    recorder: std::sync::Mutex<Option<Recorder<std::io::BufWriter<std::fs::File>>>>,
    /// Puts every model on `model/latest`, in order, the moment it is handed over.
    publisher: ModelPublisher,
}

fn emit(on: bool, e: &ServerEvent) {
    if on {
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "{}", serde_json::to_string(e).expect("events serialise"));
        let _ = out.flush();
    }
}

impl Server {
    /// Run `f` on the recorder, if recording; a failure ends the recording, not the server.
    fn recording(
        &self,
        f: impl FnOnce(&mut Recorder<std::io::BufWriter<std::fs::File>>) -> Result<(), RecordingError>,
    ) {
        let mut guard = self.recorder.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(r) = guard.as_mut() {
            if let Err(e) = f(r) {
                warn!("the recording stops here: {e} (the mission goes on; the file is readable up to its last flush)");
                *guard = None;
            }
        }
    }

    /// Record a message as it arrived or left, now.
    fn record(&self, topic: &str, data: &[u8]) -> Option<u32> {
        let mut seq = None;
        self.recording(|r| {
            seq = Some(r.message(topic, "cbor", data, recording::now_ns())?);
            Ok(())
        });
        seq
    }

    /// Record an operation of the core (before it is made: the order is the replay's).
    fn record_op(&self, op: CoreOp) {
        self.recording(|r| r.op(&op));
    }

    /// An event: to stdout with `--events`, and into the recording.
    fn event(&self, e: &ServerEvent) {
        emit(self.events, e);
        let line = serde_json::to_vec(e).expect("events serialise");
        self.recording(|r| {
            r.message(recording::EVENTS_TOPIC, "json", &line, recording::now_ns())
                .map(drop)
        });
    }

    /// Record `body`, encoded as `data`, with its Foxglove translation, now.
    fn record_body(&self, key: &str, body: &Body, data: &[u8]) {
        self.recording(|r| r.body(key, body, data, recording::now_ns()).map(drop));
    }

    /// Publish `body` on `key`, recorded. Encoded once: CBOR's float encoding (ciborium tries
    /// each float as f16 and f32) is costly, and the recording takes the wire's bytes.
    async fn put(&self, session: &zenoh::Session, key: &str, body: &Body) -> anyhow::Result<()> {
        let bytes = protocol::encode(body);
        // Out first; the recording (and its Foxglove translation) after, off the path to Zenoh.
        let sent = fleet_net::put_bytes(session, key, bytes.clone(), fleet_net::Traffic::of(body)).await;
        self.record_body(key, body, &bytes);
        Ok(sent?)
    }

    /// Count a refusal the node made itself, and log it (once per reason).
    fn refuse(&mut self, reason: &str, detail: String) {
        *self.core.counters.rejected.entry(reason.into()).or_default() += 1;
        self.log_refusal(reason, detail);
    }

    /// Sessions the router refused at the handshake (counted in `sessions_refused`; the first of
    /// each kind logged). Zenoh does not tell its host which user tried: the client's own log
    /// names it.
    fn note_session_refusals(&mut self) {
        use fleet_net::SessionRefusal::*;
        for r in fleet_net::session_refusals() {
            let what = match r {
                InvalidPassword => "a client's password is wrong for its user",
                UnknownUser => "a client's user is not in the router's dictionary",
                NoCredentials => "a client gave no credentials",
                RefusedByRouter => continue,
            };
            self.core.counters.sessions_refused += 1;
            if self.logged.insert(what.to_string()) {
                warn!(
                    sessions_refused = self.core.counters.sessions_refused,
                    "refused a Zenoh session: {what} (Zenoh does not give its host the user's name; the client's own \
                        log says which; further refusals of this kind are only counted)"
                );
            }
        }
    }

    /// Log a refusal (already counted, by the node or the core): the first of each reason.
    fn log_refusal(&mut self, reason: &str, detail: String) {
        if self.logged.insert(reason.to_string()) {
            warn!(
                reason,
                "refused a message: {detail} (further refusals of this kind are only counted)"
            );
        }
    }

    /// Commit the core's changed epoch records (and a batch, if any) in one transaction: before
    /// any ack or plan that depends on them leaves the server.
    fn journal(&mut self, batch: Option<((&str, u64), &[u8])>) -> anyhow::Result<()> {
        let records = self.core.take_journal_records();
        if batch.is_none() && records.is_empty() {
            return Ok(());
        }
        let meta: Vec<(&str, &[u8])> = records.iter().map(|(k, v)| (k.as_str(), v.as_slice())).collect();
        self.journal.commit(batch.as_slice(), &meta)?;
        Ok(())
    }

    fn status(&self) -> ServerStatus {
        let p = Percentiles::of(&self.latencies);
        ServerStatus {
            version: self.core.version,
            next_epoch: self.core.next_epoch(),
            finished: self.core.finished(),
            batches: self.core.counters.batches,
            duplicates: self.core.counters.duplicates,
            rejected: self.core.counters.rejected.clone(),
            alive: self.alive.iter().cloned().collect(),
            waiting_for: self.core.waiting_for(),
            pending_epochs: self.core.pending_epochs(),
            latency_p50_ms: p.p50,
            latency_p99_ms: p.p99,
            readings: self.readings.clone(),
            behind: self.behind.clone(),
            skill: self.core.skills().last().copied(),
            health: self.core.sensor_health(),
            overrides: self.core.counters.overrides,
            holdout: self.core.holdout(),
        }
    }

    /// Once the next epoch has waited [`SAY_BEHIND_AFTER`] (and every as long after), why each
    /// vehicle it waits for is behind: in the log, as an event, and in the status.
    fn say_behind(&mut self, since: &(u64, Instant)) {
        let waited = since.1.elapsed();
        if since.0 != self.core.next_epoch() || waited < SAY_BEHIND_AFTER || self.core.finished() {
            self.behind.clear();
            return;
        }
        self.behind = self
            .core
            .waiting_for()
            .into_iter()
            .map(|v| {
                let why = self.why_behind(&v);
                (v, why)
            })
            .collect();
        let due = self.said_behind.is_none_or(|t| t.elapsed() >= SAY_BEHIND_AFTER);
        if due && !self.behind.is_empty() {
            self.said_behind = Some(Instant::now());
            let waited_s = waited.as_secs_f64();
            for (v, why) in &self.behind {
                warn!(epoch = since.0, waited_s = format!("{waited_s:.0}"), vehicle = %v, "behind: {why}");
            }
            self.event(&ServerEvent::Waiting {
                epoch: since.0,
                waited_s,
                behind: self.behind.clone(),
            });
        }
    }

    /// Why `v`'s batch is not here, from what the server knows of it.
    fn why_behind(&self, v: &VehicleId) -> String {
        let Some((at, t)) = self.heard.get(v) else {
            return "never heard from: not started, or out of range since the start".into();
        };
        let ago = at.elapsed().as_secs_f64();
        if !self.alive.contains(v) {
            return format!(
                "out of range: its link is down (last heard {ago:.0} s ago, {} batches in its outbox then); it keeps \
                 sensing and sends them when it is back",
                t.outbox_depth
            );
        }
        if let Some(a) = t
            .autopilot
            .as_ref()
            .filter(|a| !t.available() && a.link != AutopilotLink::Connecting)
        {
            return format!(
                "its autopilot is in {} ({:?}): left out of the allocation",
                a.mode, a.link
            );
        }
        if t.outbox_depth > 0 {
            return format!(
                "its batches are on their way: {} in its outbox, link up (a slow or lossy link: last heard {ago:.0} s \
                 ago)",
                t.outbox_depth
            );
        }
        format!(
            "still sensing the epoch (at step {} when last heard, {ago:.0} s ago)",
            t.step
        )
    }

    /// A batch arrived on `key` at `t0`.
    async fn on_batch(
        &mut self,
        session: &zenoh::Session,
        sample: &zenoh::sample::Sample,
        t0: Instant,
    ) -> anyhow::Result<()> {
        let key = sample.key_expr().as_str();
        let arrival = self.record(key, &sample.payload().to_bytes());
        let body = match fleet_net::decode(sample, &self.ctx) {
            Ok(b) => b,
            Err(e) => {
                self.core.counters.batches += 1;
                self.refuse(e.reason(), format!("{key}: {e}"));
                return Ok(());
            }
        };
        let Body::Batch(batch) = body else {
            self.refuse("wrong_type", format!("{key}: not a batch"));
            return Ok(());
        };
        // A vehicle speaks only for itself.
        if self.keys.vehicle_of(key).as_deref() != Some(batch.vehicle.as_str()) {
            self.refuse("key_mismatch", format!("{key} carries a batch of {}", batch.vehicle));
            return Ok(());
        }
        let (vehicle, seq) = (batch.vehicle.clone(), batch.seq);
        if let Some(arrival) = arrival {
            self.record_op(CoreOp::Ingest { arrival });
        }
        let ingested = match self.core.ingest_deferred(batch) {
            Ok(i) => i,
            // The vehicle's fault: counted by the core, logged here; its epoch cannot complete.
            Err(IngestError::Rejected { why, .. }) => {
                self.log_refusal("invalid_batch", format!("{key}: {why}"));
                error!(
                    %vehicle,
                    seq, "batch refused: {why}; the vehicle re-sends the same batch, so its epoch cannot complete"
                );
                self.event(&ServerEvent::Refused {
                    vehicle,
                    seq,
                    reason: "invalid_batch".into(),
                    detail: why,
                });
                return Ok(());
            }
            Err(e @ IngestError::Protocol(_)) => {
                self.log_refusal("unknown_vehicle", format!("{key}: {e}"));
                return Ok(());
            }
            // The server's own failure (the model's numerics): as everywhere else, it ends the
            // server (exit 1); the journal is intact.
            Err(IngestError::Model(e)) => {
                return Err(anyhow::Error::new(e).context(format!("assimilating batch {seq} of {vehicle}")))
            }
        };
        if matches!(
            ingested,
            Ingested::Buffered | Ingested::Assimilated(_) | Ingested::Refitted(_)
        ) {
            self.journal(Some(((vehicle.as_str(), seq), &sample.payload().to_bytes())))?;
        }
        match ingested {
            Ingested::Assimilated(epochs) => self.model_changed(session, epochs, t0, false).await?,
            Ingested::Refitted(e) => self.late.push((vehicle, seq, e)),
            Ingested::Duplicate | Ingested::Buffered => self.ack(session, &vehicle).await?,
        }
        Ok(())
    }

    /// Re-fit once with the late batches of the burst just taken, publish, and report each.
    async fn settle_late(&mut self, session: &zenoh::Session, t0: Instant) -> anyhow::Result<()> {
        if self.late.is_empty() {
            return Ok(());
        }
        self.record_op(CoreOp::Settle);
        if self.core.settle()? {
            self.journal(None)?;
            let done = (0..self.core.next_epoch()).collect();
            self.model_changed(session, done, t0, true).await?;
        }
        for (vehicle, seq, e) in std::mem::take(&mut self.late) {
            info!(%vehicle, seq, epoch = e, "late batch: model re-fitted with it");
            self.event(&ServerEvent::Late {
                vehicle,
                epoch: e,
                version: self.core.version,
            });
        }
        Ok(())
    }

    /// A new model: publish it and every ack, then account for `epochs` (latency, error,
    /// events). After a re-fit every epoch's error is computed again.
    async fn model_changed(
        &mut self,
        session: &zenoh::Session,
        epochs: Vec<u64>,
        t0: Instant,
        refit: bool,
    ) -> anyhow::Result<()> {
        // From the batch to the model out: beside the placement, not after it.
        let out = self.publish_model().unwrap_or_else(Instant::now);
        let latency_ms = out.saturating_duration_since(t0).as_secs_f64() * 1e3;
        self.answer_held().await;
        for v in self.core.vehicles().to_vec() {
            self.ack(session, &v.id).await?;
        }
        if refit {
            self.mse.clear();
        }
        for e in epochs {
            let steps = self.core.steps_of(e);
            let mse = self.evaluate(steps);
            if refit {
                continue;
            }
            self.latencies.push(latency_ms);
            info!(
                epoch = e,
                version = self.core.version,
                latency_ms = format!("{latency_ms:.1}"),
                mse = mse.map(|m| format!("{m:.3e}")),
                "epoch assimilated"
            );
            for v in self.core.verdicts_at(self.core.steps_of(e)) {
                warn!(vehicle = %v.vehicle, step = v.step, from = %v.from, to = %v.to, reason = %v.reason, "sensor health");
                self.event(&ServerEvent::Sensor(v));
            }
            let next = e + 1;
            let places = places_at(&self.core, next);
            self.event(&ServerEvent::Epoch {
                epoch: e,
                version: self.core.version,
                mse,
                latency_ms,
                alive: self.alive.len(),
                batches: self.core.counters.batches,
                held: self.core.held_at(next),
                places,
                missing: self.core.missing_at(e),
            });
        }
        Ok(())
    }

    /// The next epoch has waited `timeout` for a late vehicle: assimilate it without.
    async fn force_if_due(
        &mut self,
        session: &zenoh::Session,
        since: &mut (u64, Instant),
        timeout: Option<Duration>,
    ) -> anyhow::Result<()> {
        if since.0 != self.core.next_epoch() {
            *since = (self.core.next_epoch(), Instant::now());
        }
        let Some(timeout) = timeout else { return Ok(()) };
        if since.1.elapsed() < timeout {
            return Ok(());
        }
        let before = self.core.next_epoch();
        let t0 = Instant::now();
        self.record_op(CoreOp::Force);
        if self.core.force()? {
            self.journal(None)?;
            warn!(epoch = before, missing = ?self.core.waiting_for(), "epoch assimilated without late vehicles; their \
                batches will re-fit it");
            let done = (before..self.core.next_epoch()).collect();
            self.model_changed(session, done, t0, false).await?;
        }
        *since = (self.core.next_epoch(), Instant::now());
        Ok(())
    }

    /// Mean squared error of the fused snapshots of `steps` against the truth (none without
    /// one).
    fn evaluate(&mut self, steps: std::ops::Range<usize>) -> Option<f64> {
        let truth = self.truth.as_ref()?;
        let (mut sum, mut scored) = (0.0, 0usize);
        for k in steps {
            let est = match self.core.history().estimate(k) {
                Ok(est) => est,
                Err(e) => {
                    warn!(step = k, "the fused estimate could not be read back to score it: {e}");
                    return None;
                }
            };
            let x = match truth.frame(k) {
                Ok(x) => x,
                Err(e) => {
                    warn!(step = k, "the truth could not be read to score the estimate: {e}");
                    return None;
                }
            };
            let e = fleet_math::fusion::mse(&est, &x);
            if self.mse.len() == k {
                self.mse.push(e);
            }
            // A step whose truth has no value is not scored (NaN).
            if !e.is_nan() {
                sum += e;
                scored += 1;
            }
        }
        (scored > 0).then(|| sum / scored as f64)
    }

    /// The model on `model/latest`: the one the core made beside the placement (encoded there,
    /// and already handed to the publisher), or made now.
    /// Returns when it went out (handed to the publisher), if there is one.
    fn publish_model(&mut self) -> Option<Instant> {
        let mut p = self.core.take_published()?;
        let at = self.publisher.publish(&mut p);
        self.record_body(&self.keys.model_latest(), &p.shown, &p.bytes);
        self.core.keep_published(p);
        Some(at)
    }

    async fn ack(&self, session: &zenoh::Session, vehicle: &VehicleId) -> anyhow::Result<()> {
        if let Some(a) = self.core.ack(vehicle) {
            self.put(session, &self.keys.ack(vehicle), &Body::Ack(a)).await?;
        }
        Ok(())
    }

    fn on_liveliness(&mut self, key: &str, kind: SampleKind) {
        let Some(id) = self
            .keys
            .id_after(key, "alive")
            .and_then(|id| id.parse::<VehicleId>().ok())
        else {
            return;
        };
        if !self.core.vehicles().iter().any(|v| v.id == id) {
            return;
        }
        let up = kind == SampleKind::Put;
        let changed = if up {
            self.alive.insert(id.clone())
        } else {
            self.alive.remove(&id)
        };
        if changed {
            if up {
                *self.link_ups.entry(id.clone()).or_default() += 1;
            }
            info!(vehicle = %id, alive = up, "link");
            self.event(&ServerEvent::Link { vehicle: id, alive: up });
        }
    }

    /// A vehicle's telemetry: whether its autopilot lets the planner allocate it.
    fn on_telemetry(&mut self, sample: &zenoh::sample::Sample) {
        let key = sample.key_expr().as_str();
        self.record(key, &sample.payload().to_bytes());
        let t = match fleet_net::decode(sample, &self.ctx) {
            Ok(Body::Telemetry(t)) => t,
            Ok(_) => return self.refuse("wrong_type", format!("{key}: not telemetry")),
            Err(e) => return self.refuse(e.reason(), format!("{key}: {e}")),
        };
        if self.keys.vehicle_of(key).as_deref() != Some(t.vehicle.as_str()) {
            return self.refuse("key_mismatch", format!("{key} carries telemetry of {}", t.vehicle));
        }
        if let Some(acked) = t.acked {
            let lacking = self.core.lacks_through(&t.vehicle, acked);
            if !lacking.is_empty() && self.lost_reported.insert(t.vehicle.clone()) {
                error!(vehicle = %t.vehicle, acked, lost = ?lacking, journal = %self.journal.path().display(), "the \
                    vehicle says these batches were acknowledged, but the journal does not hold them: the journal was \
                    deleted, replaced or rolled back, and the epochs that need them cannot complete");
                self.core.counters.lost += lacking.len() as u64;
                self.event(&ServerEvent::Lost {
                    vehicle: t.vehicle.clone(),
                    seqs: lacking,
                });
            }
        }
        if let Some(r) = &t.readings {
            self.readings.insert(t.vehicle.clone(), r.clone());
        }
        if let Some(traffic) = &t.traffic {
            self.traffic.insert(t.vehicle.clone(), traffic.clone());
        }
        self.recording(|r| r.foxglove(&Body::Telemetry(t.clone()), recording::now_ns()));
        self.heard.insert(t.vehicle.clone(), (Instant::now(), t.clone()));
        let available = t.available();
        if self.core.set_available(&t.vehicle, available) {
            // Recorded only when it changed something (a call that does not is a no-op).
            self.record_op(CoreOp::Available {
                vehicle: t.vehicle.clone(),
                available,
            });
            let mode = t.autopilot.as_ref().map_or_else(String::new, |a| {
                format!(
                    "{} ({:?}){}",
                    a.mode,
                    a.link,
                    a.failsafe.as_ref().map_or_else(String::new, |f| format!(": {f}"))
                )
            });
            info!(
                vehicle = %t.vehicle,
                held = !available,
                mode,
                "allocation: {} from the next epoch",
                if available { "back in" } else { "left out" }
            );
            self.event(&ServerEvent::Hold {
                vehicle: t.vehicle,
                held: !available,
                mode,
            });
        }
    }

    /// The operator's verdict on a sensor (from the ground station's seat: the access control
    /// lets no one else put there): journalled, then the model re-fitted from its step.
    async fn on_override(&mut self, session: &zenoh::Session, sample: &zenoh::sample::Sample) -> anyhow::Result<()> {
        let key = sample.key_expr().as_str();
        self.record(key, &sample.payload().to_bytes());
        let ours = |o: &protocol::SensorOverride| {
            self.keys.id_after(key, "server/sensor").as_deref() == Some(o.vehicle.as_str())
        };
        let o = match fleet_net::decode(sample, &self.ctx) {
            Ok(Body::Override(o)) if ours(&o) => o,
            Ok(Body::Override(o)) => {
                self.refuse("key_mismatch", format!("{key} carries an override of {}", o.vehicle));
                return Ok(());
            }
            Ok(_) => {
                self.refuse("wrong_type", format!("{key}: not a sensor override"));
                return Ok(());
            }
            Err(e) => {
                self.refuse(e.reason(), format!("{key}: {e}"));
                return Ok(());
            }
        };
        self.record_op(CoreOp::Override(o.clone()));
        if let Err(why) = self.core.override_sensor(&o) {
            self.refuse("invalid_override", format!("{key}: {why}"));
            return Ok(());
        }
        let set = o.set.map_or_else(|| "back to its tests".to_string(), |h| h.to_string());
        warn!(vehicle = %o.vehicle, from_step = o.from_step, set, "sensor verdict set by the operator");
        self.journal(None)?;
        self.event(&ServerEvent::Override(o));
        let t0 = Instant::now();
        if self.core.settle()? {
            self.journal(None)?;
            let done = (0..self.core.next_epoch()).collect();
            self.model_changed(session, done, t0, true).await?;
        }
        Ok(())
    }

    fn summary(&self) -> ServerSummary {
        let eigenvalues = self.core.model_update().map(|m| m.eigenvalues).unwrap_or_default();
        ServerSummary {
            mission: self.mission.mission.clone(),
            vehicles: self.core.vehicles().iter().map(|v| v.id.clone()).collect(),
            epochs: self.core.counters.epochs,
            model_version: self.core.version,
            rank: self.core.assimilator().rank(),
            counters: self.core.counters.clone(),
            latency_ms: Percentiles::of(&self.latencies),
            mean_mse: fleet_mission::events::mean_mse(&self.mse),
            mse: self.mse.clone(),
            eigenvalues,
            link_ups: self.link_ups.clone(),
            wall_s: self.started.elapsed().as_secs_f64(),
            peak_resident_mib: fleet_mission::memory::peak_resident_mib(),
            holdout: self.core.holdout(),
            innovations: self.core.innovations(),
            traffic: self.traffic.clone(),
            readings: self.readings.clone(),
            land_cells: self.core.assimilator().land().len(),
            skill: self.core.skills(),
            sensor_verdicts: self.core.verdicts_at(0..usize::MAX),
            screened: self.core.health().1,
            dt: self
                .truth
                .as_ref()
                .map_or_else(|| self.mission.clock().map_or(1.0, |c| c.step_s), |t| t.dt()),
        }
    }
}

/// Where epoch `e`'s allocation sends each vehicle that senses.
fn places_at(core: &ServerCore, e: u64) -> BTreeMap<VehicleId, [f64; 2]> {
    core.vehicles()
        .iter()
        .filter_map(|v| {
            core.plan(&v.id, e, 1)
                .and_then(|p| p.targets.into_iter().find(|t| !t.cells.is_empty()))
                .map(|t| (v.id.clone(), t.position))
        })
        .collect()
}

/// What to do about a state file the server cannot use, said after the error.
const JOURNAL_RECOVERY: &str = "to go on, move the file aside (keep it for inspection) and start the server again: it \
    starts a new journal, and the vehicles re-send every batch still in their outboxes (batches they had already had \
    acknowledged are lost with the old journal, and the server says which)";

/// The journal at `path`, checked whole, and a core restored from it (a restart after a
/// crash); returns the journal and how many batches it held. A damaged or foreign journal is
/// refused (bad input) and left as it is.
fn open_journal(
    path: &std::path::Path,
    mission: &str,
    core: &mut ServerCore,
    ctx: &Context,
) -> anyhow::Result<(Store, u64, Option<CoreOp>)> {
    let existed = path.exists();
    let journal = Store::open(path).map_err(|e| match e {
        e @ (StoreError::Damaged { .. } | StoreError::Empty { .. }) => {
            bad_input(anyhow::anyhow!("the journal {e}; {JOURNAL_RECOVERY}"))
        }
        e @ StoreError::InUse { .. } => bad_input(anyhow::anyhow!(
            "the journal {e}: is another model server running with this --state-dir?"
        )),
        e => anyhow::Error::new(e).context("opening the journal"),
    })?;
    let damaged = |what: String| {
        bad_input(anyhow::anyhow!(
            "the journal {} is damaged: {what} (the file was left as it is); {JOURNAL_RECOVERY}",
            path.display()
        ))
    };
    let fingerprint = core.fingerprint();
    match journal.meta("fingerprint").map_err(|e| damaged(e.to_string()))? {
        Some(f) if f != fingerprint.as_bytes() => {
            return Err(bad_input(anyhow::anyhow!(
                "the journal {} was written for another configuration of mission {mission:?} (team, grid or length \
                    differ): give this configuration its own --state-dir, or move the journal aside",
                path.display()
            )))
        }
        Some(_) => {}
        None => {
            let held = journal.size().1;
            if held > 0 {
                return Err(damaged(format!("it holds {held} batches but no mission fingerprint")));
            }
        }
    }
    let (mut batches, mut raw) = (vec![], vec![]);
    for ((vehicle, seq), bytes) in journal.messages().map_err(|e| damaged(e.to_string()))? {
        match protocol::decode(&bytes, ctx) {
            Ok(Body::Batch(b)) if b.vehicle == vehicle && b.seq == seq => {
                batches.push(b);
                raw.push(bytes);
            }
            Ok(_) => {
                return Err(damaged(format!(
                    "record ({vehicle}, {seq}) is not that vehicle's batch {seq}"
                )))
            }
            Err(e) => return Err(damaged(format!("batch {seq} of {vehicle} does not decode: {e}"))),
        }
    }
    let records = journal
        .meta_with_prefix(EpochRecord::PREFIX)
        .and_then(|mut r| {
            r.extend(journal.meta_with_prefix(OVERRIDE_PREFIX)?);
            Ok(r)
        })
        .map_err(|e| damaged(e.to_string()))?;
    let n = core.restore(batches, &records).map_err(|e| damaged(e.to_string()))?;
    let restore = (!raw.is_empty() || !records.is_empty()).then(|| CoreOp::Restore {
        batches: raw,
        records: records.clone(),
    });
    let mut journal = journal;
    if !existed || n == 0 {
        journal.commit(&[], &[("fingerprint", fingerprint.as_bytes())])?;
    }
    match (existed, n) {
        (false, _) => info!(journal = %path.display(), "journal: none yet, starting a new one"),
        (true, 0) => info!(journal = %path.display(), "journal: empty, starting the mission"),
        (true, n) => info!(journal = %path.display(), batches = n, next_epoch = core.next_epoch(), "journal: resuming"),
    }
    Ok((journal, n, restore))
}

/// The mission's recording (`--record`), headed by the mission file as the operator wrote it.
fn open_recorder(
    args: &Args,
    mission: &MissionConfig,
    grid: &fleet_math::grid::Grid,
    frames: usize,
    truth: Option<std::sync::Arc<Frames>>,
) -> anyhow::Result<Option<Recorder<std::io::BufWriter<std::fs::File>>>> {
    let Some(path) = &args.record else { return Ok(None) };
    let text = match &args.node.mission {
        Some(p) => std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?,
        None => fleet_mission::config::DEFAULT_MISSION.to_string(),
    };
    let view = fleet_records::foxglove::FoxgloveView::new(mission, *grid, truth);
    let r = Recorder::create(path, args.record_mode, mission, &text, grid, frames)?.with_foxglove(view)?;
    info!(recording = %r.path().display(), mode = %args.record_mode, "recording the mission");
    Ok(Some(r))
}

type Queries = zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>;
type Samples = zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// What the server listens to on Zenoh.
struct Inputs {
    batches: Samples,
    plans: Queries,
    models: Queries,
    telemetry: Samples,
    overrides: Samples,
    links: Samples,
    _token: zenoh::liveliness::LivelinessToken,
}

/// Everything the server's loop reacts to, one at a time, as it arrives.
enum Event {
    /// A measurement batch (what is queued behind it is taken with it).
    Batch(zenoh::sample::Sample),
    /// A vehicle asks for its plan.
    PlanQuery(zenoh::query::Query),
    /// A reader asks for the model.
    ModelQuery(zenoh::query::Query),
    /// A vehicle's telemetry (its holds).
    Telemetry(zenoh::sample::Sample),
    /// An operator's sensor override.
    Override(zenoh::sample::Sample),
    /// A node's liveliness token, put or deleted.
    Liveliness(zenoh::sample::Sample),
    /// Time to see whether the epoch waited for is due to be forced (every 50 ms).
    Check,
    /// Time to answer held plan queries and put the status (every second).
    StatusTick,
    /// A stop signal, by name.
    Stop(&'static str),
    /// A queryable or subscriber other than the batches' gave nothing (it is closing).
    Nothing,
}

/// The loop's clocks and the stop signals it listens to beside Zenoh.
struct Clocks {
    stop: fleet_net::StopSignals,
    status: tokio::time::Interval,
    check: tokio::time::Interval,
}

impl Inputs {
    /// The next event (an error once the batch subscriber is closed).
    async fn next(&self, clocks: &mut Clocks) -> anyhow::Result<Event> {
        Ok(tokio::select! {
            r = self.batches.recv_async() => {
                Event::Batch(r.map_err(|e| anyhow::anyhow!("batch subscriber closed: {e}"))?)
            }
            r = self.plans.recv_async() => r.map_or(Event::Nothing, Event::PlanQuery),
            r = self.models.recv_async() => r.map_or(Event::Nothing, Event::ModelQuery),
            r = self.telemetry.recv_async() => r.map_or(Event::Nothing, Event::Telemetry),
            r = self.overrides.recv_async() => r.map_or(Event::Nothing, Event::Override),
            r = self.links.recv_async() => r.map_or(Event::Nothing, Event::Liveliness),
            _ = clocks.check.tick() => Event::Check,
            _ = clocks.status.tick() => Event::StatusTick,
            signal = clocks.stop.recv() => Event::Stop(signal),
        })
    }
}

impl Inputs {
    async fn declare(session: &zenoh::Session, keys: &Keys) -> Result<Self, fleet_net::NetError> {
        let e = fleet_net::NetError::zenoh;
        let links = session
            .liveliness()
            .declare_subscriber(keys.all_alive())
            .history(true)
            .await;
        Ok(Self {
            batches: session
                .declare_subscriber(keys.all_measurements())
                .await
                .map_err(e("the batches"))?,
            plans: session
                .declare_queryable(keys.all_plans())
                .await
                .map_err(e("the plans' queryable"))?,
            models: session
                .declare_queryable(keys.model_latest())
                .await
                .map_err(e("the model's queryable"))?,
            telemetry: session
                .declare_subscriber(keys.telemetry("*"))
                .await
                .map_err(e("the telemetry"))?,
            overrides: session
                .declare_subscriber(keys.all_sensor_overrides())
                .await
                .map_err(e("the sensor overrides"))?,
            links: links.map_err(e("the vehicles' liveliness"))?,
            _token: session
                .liveliness()
                .declare_token(keys.alive("server"))
                .await
                .map_err(e("the token"))?,
        })
    }
}

pub async fn run(args: Args) -> anyhow::Result<()> {
    let (mission, truth) = args.node.load()?;
    let (grid, frames) = mission.workspace(truth.as_ref().map(Frames::shape))?;
    // One truth, shared with the recording's Foxglove view.
    let truth = truth.map(std::sync::Arc::new);
    let keys = Keys::new(&mission.mission)?;
    let mut core = ServerCore::new(&mission.team, grid, frames)?
        .with_boat_speed(mission.motion.boat_speed)
        .with_holdout(mission.holdout_share());
    // The fused map of every step goes to the run's files as it is made (memory does not grow
    // with the mission); a restart rebuilds them from the journal.
    if let Some(dir) = &args.out {
        core = core.with_history_in(dir)?;
    }
    let mut ctx = Context::new(grid);
    ctx.vehicles = core.vehicles().iter().map(|v| v.id.clone()).collect();
    let journal_path = args.state_dir.join(format!("{}.redb", mission.mission));
    let (journal, restored, restore) = open_journal(&journal_path, &mission.mission, &mut core, &ctx)?;
    let recorder = open_recorder(&args, &mission, &grid, frames, truth.clone())?;
    let session = fleet_net::open(args.node.zenoh_config(Role::Server, &mission.network, &mission.link)?).await?;
    let inputs = Inputs::declare(&session, &keys).await?;
    let publisher = ModelPublisher::start(session.clone(), keys.model_latest());
    let mut s = Server {
        core: core.with_publisher(publisher.hook()),
        publisher,
        keys,
        ctx,
        truth,
        readings: BTreeMap::new(),
        traffic: BTreeMap::new(),
        heard: BTreeMap::new(),
        behind: BTreeMap::new(),
        said_behind: None,
        events: args.events,
        alive: BTreeSet::new(),
        link_ups: BTreeMap::new(),
        latencies: vec![],
        mse: vec![],
        logged: BTreeSet::new(),
        started: Instant::now(),
        late: vec![],
        lost_reported: BTreeSet::new(),
        journal,
        mission,
        held_queries: vec![],
        recorder: std::sync::Mutex::new(recorder),
    };
    s.resume(&session, restored, restore).await?;
    let finished = s.serve(&session, &inputs, &args).await?;
    s.leave(&session, finished, &args).await
}

impl Server {
    /// After a restart: the model and every vehicle's ack again, and the error of what is in;
    /// then ready.
    async fn resume(&mut self, session: &zenoh::Session, restored: u64, restore: Option<CoreOp>) -> anyhow::Result<()> {
        if let Some(op) = restore {
            self.record_op(op);
        }
        if restored > 0 {
            self.publish_model();
            for v in self.core.vehicles().to_vec() {
                self.ack(session, &v.id).await?;
            }
            let done = self.core.schedule().steps_of(self.core.next_epoch()).start;
            self.evaluate(0..done);
        }
        let epochs = self.core.schedule().epochs();
        info!(
            mission = self.mission.mission,
            epochs,
            vehicles = self.core.vehicles().len(),
            "model server up"
        );
        self.event(&ServerEvent::Ready {
            mission: self.mission.mission.clone(),
            epochs,
            vehicles: self.core.vehicles().iter().map(|v| v.id.clone()).collect(),
            places: places_at(&self.core, self.core.next_epoch()),
        });
        Ok(())
    }

    /// The server's loop, one event at a time, until a stop signal or (with
    /// `--exit-when-done`) the mission's end; the summary as written at the end, if it came.
    async fn serve(
        &mut self,
        session: &zenoh::Session,
        inputs: &Inputs,
        args: &Args,
    ) -> anyhow::Result<Option<ServerSummary>> {
        let mut clocks = Clocks {
            stop: fleet_net::StopSignals::new()?,
            status: tokio::time::interval(Duration::from_secs(1)),
            check: tokio::time::interval(Duration::from_millis(50)),
        };
        let pace = &self.mission.pace;
        let epoch_timeout = (pace.epoch_timeout_ms > 0).then(|| Duration::from_millis(pace.epoch_timeout_ms));
        let mut since = (self.core.next_epoch(), Instant::now());
        // The summary as written when the mission finished: batches may still come after it (a
        // vehicle re-sends until it sees its ack) and are recorded, so its counters are brought
        // up to date when the server leaves.
        let mut finished = None;
        let mut departure = Departure::new(Duration::from_millis(args.linger_ms));
        loop {
            match inputs.next(&mut clocks).await? {
                Event::Stop(signal) => {
                    info!(
                        signal,
                        "stopping: the journal holds every accepted batch, a restart resumes"
                    );
                    break;
                }
                Event::Batch(sample) => {
                    self.on_batches(session, &inputs.batches, &sample).await?;
                    departure.heard_batch(Instant::now());
                }
                Event::Check => self.force_if_due(session, &mut since, epoch_timeout).await?,
                Event::StatusTick => self.on_status_tick(session, &since).await?,
                event => self.on_event(session, event).await?,
            }
            if self.core.finished() && finished.is_none() {
                departure.mission_done(Instant::now());
                finished = Some(self.on_finished(session, args).await?);
            }
            if args.exit_when_done && departure.leave(Instant::now(), !self.alive.is_empty()) {
                break;
            }
        }
        Ok(finished)
    }

    /// An event that needs neither the batch queue nor the epoch's clock.
    async fn on_event(&mut self, session: &zenoh::Session, event: Event) -> anyhow::Result<()> {
        match event {
            Event::PlanQuery(q) => self.on_plan_query(q).await,
            Event::ModelQuery(q) => self.on_model_query(q).await,
            Event::Telemetry(sample) => self.on_telemetry(&sample),
            Event::Override(sample) => self.on_override(session, &sample).await?,
            Event::Liveliness(sample) => self.on_liveliness(sample.key_expr().as_str(), sample.kind()),
            Event::Batch(_) | Event::Check | Event::StatusTick | Event::Stop(_) | Event::Nothing => {}
        }
        Ok(())
    }

    /// Every second: held plan queries answered, a slow epoch said, the status put.
    async fn on_status_tick(&mut self, session: &zenoh::Session, since: &(u64, Instant)) -> anyhow::Result<()> {
        self.answer_held().await;
        self.say_behind(since);
        self.note_session_refusals();
        self.recording(|r| r.flush());
        self.put(session, &self.keys.server_status(), &Body::Status(self.status()))
            .await
    }

    /// A batch, and what is queued behind it (a backlog comes as a burst: take what is queued
    /// already, then re-fit once).
    async fn on_batches(
        &mut self,
        session: &zenoh::Session,
        batches: &Samples,
        first: &zenoh::sample::Sample,
    ) -> anyhow::Result<()> {
        let t0 = Instant::now();
        self.on_batch(session, first, t0).await?;
        while let Ok(Some(sample)) = batches.try_recv() {
            self.on_batch(session, &sample, Instant::now()).await?;
        }
        self.settle_late(session, t0).await
    }

    /// The mission's end: the outputs, the event, and the status at once (observers see the
    /// end now, not at the next tick, which may never come).
    async fn on_finished(&mut self, session: &zenoh::Session, args: &Args) -> anyhow::Result<ServerSummary> {
        let summary = self.summary();
        if let Some(dir) = &args.out {
            write_outputs(dir, &summary, &self.core, self.mission.pace.horizon)?;
        }
        info!(
            epochs = summary.epochs,
            batches = summary.counters.batches,
            p99_ms = summary.latency_ms.p99,
            "mission finished"
        );
        self.event(&ServerEvent::Finished {
            summary: Box::new(summary.clone()),
        });
        self.put(session, &self.keys.server_status(), &Body::Status(self.status()))
            .await?;
        Ok(summary)
    }

    /// Leaving: the summary's counters brought up to date, the last word on the status key,
    /// the session closed and the recording finished.
    async fn leave(self, session: &zenoh::Session, finished: Option<ServerSummary>, args: &Args) -> anyhow::Result<()> {
        if let (Some(mut summary), Some(dir)) = (finished, &args.out) {
            if summary.counters != self.core.counters {
                summary.counters = self.core.counters.clone();
                std::fs::write(dir.join("summary.json"), serde_json::to_string_pretty(&summary)?)
                    .with_context(|| format!("writing {}/summary.json", dir.display()))?;
            }
        }
        self.publisher.flush().await;
        self.put(session, &self.keys.server_status(), &Body::Status(self.status()))
            .await?;
        fleet_net::close(session).await;
        if let Some(r) = self.recorder.into_inner().unwrap_or_else(|p| p.into_inner()) {
            let path = r.path().to_path_buf();
            r.finish()?;
            info!(recording = %path.display(), "recording ended");
        }
        Ok(())
    }
}

/// How long the next epoch waits before the server says why its vehicles are behind (and how
/// often it says it again).
const SAY_BEHIND_AFTER: Duration = Duration::from_secs(10);

/// The longest a plan query is held for its plan.
const MAX_HOLD_MS: u64 = 300_000;
/// Plan queries held at once for one vehicle.
const HELD_PER_VEHICLE: usize = 4;

/// A plan query held until its plan exists.
struct HeldQuery {
    query: zenoh::query::Query,
    vehicle: VehicleId,
    epoch: u64,
    until: Instant,
}

/// Reply to a plan query: the plan's bytes, or why not (a reply goes with its query's priority:
/// the vehicle asks with the plan's, [`fleet_net::Traffic::Plan`]).
async fn reply(q: zenoh::query::Query, answer: Result<Vec<u8>, String>) {
    let sent = match answer {
        Ok(bytes) => {
            q.reply(q.key_expr().clone(), bytes)
                .encoding(fleet_net::encoding())
                .await
        }
        Err(why) => q.reply_err(why.into_bytes()).await,
    };
    if let Err(e) = sent {
        warn!("replying to {}: {e}", q.key_expr());
    }
}

/// What a finished run leaves for export (`fleet export`): the summary, and the core's
/// outputs (`fleet_records::outputs`).
fn write_outputs(
    dir: &std::path::Path,
    summary: &ServerSummary,
    core: &ServerCore,
    horizon: u64,
) -> anyhow::Result<()> {
    fleet_records::outputs::write(dir, core, horizon)?;
    std::fs::write(dir.join("summary.json"), serde_json::to_string_pretty(summary)?)
        .with_context(|| format!("writing {}/summary.json", dir.display()))
}
