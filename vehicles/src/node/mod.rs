//! The vehicle's loop over the mission's epochs, one `select!` over what can happen, each an
//! [`Event`]: an ack (trim the outbox; the model moved, so ask for the plan again), the
//! server's liveliness (a returned link sends the whole backlog), the resend tick (re-send what
//! is due; ask for the plan every 250 ms; after `plan_timeout_ms` without an answer, follow the
//! horizon of the plan held), a plan reply (drive and sense the epoch) and the end of an
//! epoch's drive and step timer (commit the batch, send it, go on). Every batch is kept until
//! the server's ack covers it.

mod compose;
mod drive;
mod readings;
mod readings_log;
mod setup;
mod shown;

use crate::Args;
use drive::{drive, query_plan, Drive};
use fleet_math::grid::Grid;
use fleet_math::process::frames::Frames;
use fleet_mission::config::MissionConfig;
use fleet_mission::instrument::{check_source, MissionClock, SensorSource};
use fleet_mission::protocol::{self, keys::Keys, AutopilotStatus, Body, Context, LinkState, Plan, Telemetry};
use fleet_mission::vehicle::vehicle_rng;
use fleet_mission::vehicle::{BrainState, VehicleBrain};
use fleet_net::outbox::{Outbox, OutboxError};
use fleet_net::{zenoh, Role, Traffic};
use setup::Setup;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};
use tracing::{debug, info, warn};
use vehicles::autopilot::modes::Control;
use vehicles::bridge::Bridge;
use vehicles::sensor::Input;
use zenoh::sample::SampleKind;

/// How soon the plan is asked for again when a question came back without it (an ack asks at
/// once). The server holds a question until the plan exists, so this paces only the retries.
const ASK_EVERY: Duration = Duration::from_millis(250);
/// A plan's size on the wire, about, for how long its transfer may take (a boat's three disks'
/// cells: a few kB).
const PLAN_BYTES: usize = 8 << 10;

/// Where the vehicle is in its mission.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Waiting for the plan of `epoch`.
    Plan {
        epoch: u64,
        deadline: Instant,
        warned: bool,
        next_ask: Instant,
    },
    /// Driving to and sensing `epoch` (a task reports the fixes when its step timer ends).
    Sense {
        epoch: u64,
    },
    /// The outbox is at its bound: `epoch` waits for acks to make room (nothing is dropped).
    Full {
        epoch: u64,
    },
    /// Every epoch sensed: waiting until the last batch is acknowledged (`deadline`: the
    /// final wait from the last ack that moved the outbox).
    Finish {
        deadline: Instant,
    },
    Done,
}

/// What a drive task reports: the epoch and its drive.
type Driven = (u64, Drive);

struct Vehicle {
    args: Args,
    session: zenoh::Session,
    keys: Keys,
    ctx: Context,
    grid: Grid,
    brain: VehicleBrain,
    outbox: Outbox,
    server_alive: bool,
    /// The server's verdict on this vehicle's sensor when not ok (from its acks).
    sensor: Option<fleet_mission::protocol::SensorHealth>,
    /// When the link to the server went down, and whether the link-loss failsafe acted.
    link_lost_at: Option<Instant>,
    link_failsafe: bool,
    /// When the node started (the server not seen yet counts as gone since then), and how long
    /// the server's token must stay gone before the vehicle stops waiting for plans: two of the
    /// session's leases. A link whose lease ran out on one side is refused by the other (Zenoh's
    /// `MAX_LINKS`) until that side's lease runs out too, and then comes back; over a lossy radio
    /// a token vanishes for that long now and then while the server is there.
    started: Instant,
    link_grace: Duration,
    mavlink: fleet_mission::config::MavlinkConfig,
    /// The radio to the base (`[link]`): how long an answer over it may take.
    link: fleet_mission::config::Link,
    /// How long an unacknowledged batch waits before it goes again, measured on the link; and
    /// when each batch in flight first went, and whether it went again since (only a batch
    /// sent once is timed).
    resend: fleet_net::rto::Retransmit,
    in_flight: std::collections::BTreeMap<u64, (Instant, bool)>,
    plan_timeout: Duration,
    arrival_timeout: Duration,
    step_ms: u64,
    step: u64,
    phase: Phase,
    /// A plan query is out (one at a time).
    asking: bool,
    plans: mpsc::UnboundedSender<(u64, (Option<Plan>, usize))>,
    driven: mpsc::UnboundedSender<Driven>,
    bridge: Option<Bridge>,
    /// What the last telemetry said of the autopilot (link, guided, mode): a change is sent at
    /// once, so the server leaves a held vehicle out of the next allocation.
    shown: shown::Shown,
    /// When the epoch's plan came in, and how long after it each first guided target left (ms).
    plan_at: Option<Instant>,
    guided_ms: Vec<f64>,
    /// Mission time (`[time]`): epochs close by the clock rather than `step_ms`.
    clock: Option<MissionClock>,
    /// The instrument this vehicle reads (`None`: the simulated sensor, from the truth).
    instrument: Option<readings::Instrument>,
    /// What crossed the link so far (the MAVLink pipe counts its own, in `mavlink_out`).
    traffic: protocol::LinkTraffic,
    mavlink_out: compose::Counted,
}

fn outbox_error(e: OutboxError) -> anyhow::Error {
    const RECOVERY: &str = "to go on, move the file aside (keep it for inspection) and start the vehicle again: it \
        starts over from the first epoch, senses again what the plans say and the server keeps what it already has \
        (batches held only in this outbox are lost)";
    match e {
        OutboxError::Store(e @ fleet_net::store::StoreError::InUse { .. }) => {
            fleet_exit::bad_input(anyhow::anyhow!("the outbox {e}: is this vehicle already running?"))
        }
        e if e.is_bad_file() => fleet_exit::bad_input(anyhow::anyhow!("the outbox {e}; {RECOVERY}")),
        e => anyhow::Error::new(e).context("the outbox"),
    }
}

impl Vehicle {
    /// The mission is done: the readings on disk, a last telemetry, the link's count in the
    /// log, and the session closed (its close flushes what is still queued).
    async fn finish(mut self) -> anyhow::Result<()> {
        if let Some(i) = &mut self.instrument {
            i.sync();
        }
        self.telemetry().await;
        self.log_link();
        info!(
            vehicle = %self.brain.id,
            off_target = self.brain.off_target,
            "mission done, every batch acknowledged"
        );
        // After the last telemetry, so the server never takes the return for a hold.
        self.end_action().await;
        fleet_net::close(&self.session).await;
        Ok(())
    }

    fn on_ack(&mut self, sample: &zenoh::sample::Sample) -> anyhow::Result<()> {
        self.traffic.receive("ack", sample.payload().len());
        match fleet_net::decode(sample, &self.ctx) {
            Ok(Body::Ack(a)) if a.vehicle == self.brain.id => {
                self.time_ack(a.seq);
                self.sensor_verdict(a.sensor);
                let before = self.outbox.depth();
                if let Err(e) = self.outbox.ack(a.seq) {
                    warn!("recording ack {}: {e:#}", a.seq);
                }
                // The final wait counts from the last ack that moved the outbox: a slow link
                // that still delivers (a 9.6 kbit/s radio draining a backlog) is not a lost one.
                if let Phase::Finish { deadline } = &mut self.phase {
                    if self.outbox.depth() < before {
                        *deadline = Instant::now() + Duration::from_millis(self.args.final_ack_ms);
                    }
                }
                match self.phase {
                    // The model moved on: its plan may be there now.
                    Phase::Plan { ref mut next_ask, .. } => {
                        *next_ask = Instant::now();
                        self.ask_if_due();
                    }
                    Phase::Full { epoch } if !self.outbox.full() => self.begin(epoch),
                    Phase::Finish { .. } => self.finish_if_acknowledged(),
                    _ => {}
                }
            }
            Ok(_) => warn!("ignored a message on the ack key that is not our ack"),
            Err(e) => warn!("refused an ack: {e}"),
        }
        Ok(())
    }

    /// The server's verdict on this vehicle's sensor, in its log when it changes (and in its
    /// telemetry from now on).
    fn sensor_verdict(&mut self, sensor: Option<fleet_mission::protocol::SensorHealth>) {
        if sensor == self.sensor {
            return;
        }
        match &sensor {
            Some(s) => warn!(state = %s.state, reason = %s.reason, "the server doubts this vehicle's sensor"),
            None => info!("the server trusts this vehicle's sensor again"),
        }
        self.sensor = sensor;
    }

    /// The server's token has been gone for the link's grace (or never came in that time):
    /// out of range, not a moment's loss. Acting on the first loss sent a boat to its held
    /// plan's disk while the server's plan for the epoch, made from the same batches, was on
    /// its way; the two differ, so the mission's estimate then depended on a lost keep-alive.
    fn cut_off(&self, now: Instant) -> bool {
        link_cut_off(
            self.server_alive,
            self.link_lost_at.unwrap_or(self.started),
            self.link_grace,
            now,
        )
    }

    /// The ack covers `seq`: the batches it covers that went once are timed (the link's round
    /// trip, for the resend's wait).
    fn time_ack(&mut self, seq: u64) {
        let later = self.in_flight.split_off(&(seq + 1));
        let covered = std::mem::replace(&mut self.in_flight, later);
        for (sent, again) in covered.into_values() {
            if !again {
                self.resend.sample(sent.elapsed());
            }
        }
    }

    fn on_link(&mut self, sample: &zenoh::sample::Sample) {
        let up = sample.kind() == SampleKind::Put;
        if up {
            fleet_net::mark_connected();
        }
        if up != self.server_alive {
            info!(
                server_alive = up,
                backlog = self.outbox.depth(),
                "link to the model server"
            );
            if up {
                // Back in range: the whole backlog is due now, oldest first (and its acks are
                // no measure of the link's round trip).
                self.outbox.resend_all();
                self.in_flight.values_mut().for_each(|f| f.1 = true);
            }
            self.link_lost_at = (!up).then(Instant::now);
            if up && std::mem::take(&mut self.link_failsafe) {
                if let Some(b) = &self.bridge {
                    info!("link to the server back: GUIDED again, rejoining the allocation");
                    b.rejoin();
                }
            }
        }
        self.server_alive = up;
    }

    async fn resend_due(&mut self) -> anyhow::Result<()> {
        let key = self.keys.measurements(&self.brain.id);
        let (now, wait) = (Instant::now(), self.resend.timeout());
        let timed_out = self.outbox.overdue(now, wait);
        for (seq, bytes) in self.outbox.due(now, wait).map_err(outbox_error)? {
            debug!(seq, "sending from the outbox");
            if let Some((_, again)) = self.in_flight.get_mut(&seq) {
                *again = true;
            }
            self.traffic.send("batch", bytes.len());
            if let Err(e) = fleet_net::put_bytes(&self.session, &key, bytes, Traffic::Batch).await {
                warn!("sending batch {seq}: {e}");
            }
        }
        if timed_out {
            self.resend.back_off();
        }
        Ok(())
    }

    /// Start epoch `e` (or the next one this vehicle senses): ask for its plan, unless the
    /// outbox is full; past the last epoch, wait for the final ack.
    fn begin(&mut self, from: u64) {
        let schedule = *self.brain.schedule();
        let Some(e) = (from..schedule.epochs()).find(|&e| schedule.seq_of(self.brain.kind, e).is_some()) else {
            self.phase = Phase::Finish {
                deadline: Instant::now() + Duration::from_millis(self.args.final_ack_ms),
            };
            return self.finish_if_acknowledged();
        };
        if self.outbox.full() {
            warn!(
                depth = self.outbox.depth(),
                "outbox full: holding until the server acknowledges"
            );
            self.phase = Phase::Full { epoch: e };
            return;
        }
        let now = Instant::now();
        self.phase = Phase::Plan {
            epoch: e,
            deadline: now + self.plan_timeout,
            warned: false,
            next_ask: now,
        };
        self.ask_if_due();
    }

    /// In the plan phase, with no query out and the next one due: ask now.
    fn ask_if_due(&mut self) {
        if let Phase::Plan { epoch, next_ask, .. } = &mut self.phase {
            let now = Instant::now();
            if !self.asking && now >= *next_ask {
                *next_ask = now + ASK_EVERY;
                let e = *epoch;
                self.ask_plan(e);
            }
        }
    }

    fn finish_if_acknowledged(&mut self) {
        if schedule_last(&self.brain).is_none_or(|last| self.outbox.covers(last)) {
            self.phase = Phase::Done;
        }
    }

    /// Ask the server for the plan from epoch `e`, in a task; the reply comes on `plans`. The
    /// server holds the question until the plan exists or the plan's deadline passes (one
    /// question an epoch over the radio); the answer may take the link's round trip and the
    /// plan's transfer more.
    fn ask_plan(&mut self, e: u64) {
        self.asking = true;
        let (session, ctx, tx) = (self.session.clone(), self.ctx.clone(), self.plans.clone());
        let wait = match self.phase {
            Phase::Plan { deadline, .. } => deadline.saturating_duration_since(Instant::now()),
            _ => Duration::ZERO,
        };
        let timeout = wait + self.link.answer_within(PLAN_BYTES);
        let selector = format!(
            "{}?epoch={e};wait_ms={}",
            self.keys.plan(&self.brain.id),
            wait.as_millis()
        );
        self.traffic.send("plan_query", selector.len());
        tokio::spawn(async move {
            let _ = tx.send((e, query_plan(&session, &selector, &ctx, e, timeout).await));
        });
    }

    /// The resend tick: what is due goes out; the plan is asked for again, or, past the
    /// timeout (or with the server gone), the held plan's horizon is followed.
    /// The mission is over: its autopilot returns (a copter lands where it returns, as
    /// ArduCopter's RTL does) or holds, as `[mavlink] end_action` says (`continue`: left as is).
    /// Waits (up to a second) for the autopilot to take the mode, so the command is not lost
    /// with the node.
    async fn end_action(&self) {
        let role = match self.mavlink.end_action.as_str() {
            "rtl" => Control::Return,
            "hold" => Control::Hold,
            _ => return,
        };
        let Some(b) = self.bridge.as_ref().filter(|b| b.drivable()) else {
            info!("mission done: the autopilot is not driven by us, left as it is");
            return;
        };
        let mut changes = b.status_changes();
        if b.failsafe(role, "mission done") {
            // The `Ref` `wait_for` returns holds the channel's read lock: dropped here, before
            // `status()` reads the channel again (a second read behind the actor's waiting write
            // deadlocks the node).
            let taken = tokio::time::timeout(Duration::from_secs(1), changes.wait_for(|s| !s.guided))
                .await
                .is_ok_and(|r| r.is_ok());
            let mode = b.status().mode;
            info!(
                action = self.mavlink.end_action,
                mode, taken, "mission done: the autopilot ends it"
            );
        }
    }

    /// Out of range for longer than the mission allows: the link-loss failsafe's action.
    fn check_link_loss(&mut self) {
        let m = &self.mavlink;
        let role = match m.link_loss_action.as_str() {
            "rtl" => Control::Return,
            "hold" => Control::Hold,
            _ => return,
        };
        let (Some(since), Some(b)) = (self.link_lost_at, &self.bridge) else {
            return;
        };
        if !self.link_failsafe && since.elapsed().as_secs_f64() >= m.link_loss_s && b.failsafe(role, "ground link lost")
        {
            warn!(
                after_s = m.link_loss_s,
                action = m.link_loss_action,
                "link to the server lost: failsafe"
            );
            self.link_failsafe = true;
        }
    }

    async fn on_tick(&mut self) -> anyhow::Result<()> {
        self.check_link_loss();
        if let Some(i) = &mut self.instrument {
            i.sync();
        }
        self.resend_due().await?;
        let now = Instant::now();
        match self.phase {
            Phase::Plan {
                epoch,
                deadline,
                warned,
                next_ask,
            } => {
                // Cut off from the server (its liveliness token gone for two leases): no use waiting
                // out the timeout, the held horizon says where to sense, at the mission's pace.
                if (now > deadline || self.cut_off(now)) && self.brain.covers(epoch) {
                    warn!(
                        epoch,
                        server_alive = self.server_alive,
                        "no plan from the server: following the held plan's horizon"
                    );
                    self.sense(epoch);
                    return Ok(());
                }
                if now > deadline && !warned {
                    warn!(epoch, "no plan from the server and none held: still asking");
                }
                self.phase = Phase::Plan {
                    epoch,
                    deadline,
                    warned: warned || now > deadline,
                    next_ask,
                };
                self.ask_if_due();
            }
            Phase::Finish { deadline } if now > deadline => {
                let last = schedule_last(&self.brain).unwrap_or_default();
                anyhow::bail!(
                    "{}: batch {last} not acknowledged after {} ms ({} unacknowledged, kept in {})",
                    self.brain.id,
                    self.args.final_ack_ms,
                    self.outbox.depth(),
                    self.outbox.path().display()
                );
            }
            _ => {}
        }
        Ok(())
    }

    fn on_plan(&mut self, e: u64, (plan, bytes): (Option<Plan>, usize)) {
        self.asking = false;
        if bytes > 0 {
            self.traffic.receive("plan", bytes);
        }
        match (self.phase, plan) {
            (Phase::Plan { epoch, .. }, Some(p)) if epoch == e => {
                self.brain.set_plan(p);
                self.plan_at = Some(Instant::now());
                self.sense(e);
            }
            // Asked again at once when an ack came meanwhile.
            _ => self.ask_if_due(),
        }
    }

    /// Drive to epoch `e`'s places and wait out its steps, in a task (acks, resends and the
    /// link keep being handled meanwhile); [`Self::on_driven`] senses when it reports.
    fn sense(&mut self, e: u64) {
        self.phase = Phase::Sense { epoch: e };
        let (driver, targets, grid, timeout, tx) = (
            self.bridge.as_ref().map(|b| b.driver()),
            self.brain.targets_of(e),
            self.grid,
            self.arrival_timeout,
            self.driven.clone(),
        );
        let (plan_at, pace, closes) = (
            self.plan_at.take(),
            Duration::from_millis(self.step_ms * self.brain.schedule().steps_of(e).len() as u64),
            self.closes(e),
        );
        tokio::spawn(async move {
            let driven = drive(driver, targets, grid, timeout, plan_at).await;
            // Then the epoch's steps: until the clock closes it, or at the mission's pace.
            match closes {
                Some(at) => tokio::time::sleep_until(at).await,
                None => tokio::time::sleep(pace).await,
            }
            let _ = tx.send((e, driven));
        });
    }

    /// With mission time, when epoch `e` closes: its last step's end (and, for an instrument,
    /// [`readings::CLOSE_AFTER_S`] for the readings still on their way).
    fn closes(&self, e: u64) -> Option<tokio::time::Instant> {
        let clock = self.clock?;
        let end = clock.time_of(self.brain.schedule().steps_of(e).end as u64)
            + if self.instrument.is_some() {
                readings::CLOSE_AFTER_S
            } else {
                0.0
            };
        let wait = Duration::from_secs_f64((end - MissionClock::now()).clamp(0.0, 1e9));
        Some(tokio::time::Instant::now() + wait)
    }

    /// Epoch `e`'s batch: the instrument's readings of its steps, or what the simulated sensor
    /// draws from the truth at the fixes.
    fn batch_of(
        &mut self,
        e: u64,
        fixes: &std::collections::BTreeMap<u64, fleet_mission::vehicle::Fix>,
        truth: Option<&Frames>,
    ) -> anyhow::Result<Option<protocol::MeasurementBatch>> {
        if let Some(i) = &mut self.instrument {
            let steps = self.brain.schedule().steps_of(e);
            let samples = i.take(steps.start as u64..steps.end as u64);
            let samples = match self.brain.kind {
                protocol::VehicleKind::Boat => samples,
                protocol::VehicleKind::Aerial => {
                    i.log_fixes(fixes.iter().map(|(&k, f)| (k, f.position)));
                    self.brain.seen_from_targets(e, samples, fixes)
                }
            };
            return Ok(self.brain.batch_of(e, samples));
        }
        // (A simulated sensor without a truth is refused when the source is chosen.)
        let truth = truth.ok_or_else(|| anyhow::anyhow!("{}: the simulated sensor has no truth", self.brain.id))?;
        // The frames of the epoch's sampling steps, read first: a frame the disk will not give
        // back is an error here, not a value drawn from nothing.
        let mut frames = std::collections::BTreeMap::new();
        for k in self.brain.schedule().sample_steps(self.brain.kind, e) {
            frames.insert(k, truth.frame(k)?);
        }
        // (Only those steps are sampled; another would read as a truth without values.)
        let truth_at =
            |k: usize| -> Vec<f64> { frames.get(&k).cloned().unwrap_or_else(|| vec![f64::NAN; truth.dim()]) };
        Ok(self.brain.sense_epoch_at(e, truth_at, fixes)?)
    }

    /// A line or frame from the instrument.
    fn on_input(&mut self, input: Input) {
        if let Some(i) = &mut self.instrument {
            i.on_input(input, MissionClock::now());
        }
    }

    /// Epoch `e` driven: sense it, commit the batch (durable first, then sent: a crash in
    /// between re-sends it after the restart), send it, go on.
    async fn on_driven(&mut self, (e, (fixes, guided)): Driven, truth: Option<&Frames>) -> anyhow::Result<()> {
        self.guided_ms.extend(guided);
        self.step = self.brain.schedule().steps_of(e).end.saturating_sub(1) as u64;
        if let Some(batch) = self.batch_of(e, &fixes, truth)? {
            let bytes = protocol::encode(&Body::Batch(batch.clone()));
            let state: BrainState = self.brain.state(e + 1);
            if self.outbox.commit(batch.seq, &bytes, &state).map_err(outbox_error)? {
                warn!(
                    depth = self.outbox.depth(),
                    limit = self.args.outbox_limit_mb << 20,
                    "outbox at 80% of its bound: the vehicle will pause sensing when it is full"
                );
            }
            let key = self.keys.measurements(&self.brain.id);
            self.traffic.send("batch", bytes.len());
            if let Err(err) = fleet_net::put_bytes(&self.session, &key, bytes, Traffic::Batch).await {
                warn!("sending batch {}: {err} (kept in the outbox)", batch.seq);
            }
            self.outbox.mark_sent(batch.seq, Instant::now());
            self.in_flight.insert(batch.seq, (Instant::now(), false));
        }
        self.telemetry().await;
        self.begin(e + 1);
        Ok(())
    }

    async fn telemetry(&mut self) {
        let autopilot = self.bridge.as_ref().map(Bridge::status);
        if let Some(s) = &autopilot {
            self.shown.note(s);
        }
        let t = Telemetry {
            vehicle: self.brain.id.clone(),
            step: self.step,
            // Where the autopilot says it is (it may have gone home on a failsafe; held to the
            // workspace, as the wire requires), else where it last sensed.
            position: self
                .bridge
                .as_ref()
                .and_then(|b| b.position())
                .map(|(x, y)| (x.clamp(0.0, self.grid.width_m()), y.clamp(0.0, self.grid.height_m())))
                .or(self.brain.position())
                .map_or([0.0, 0.0], |p| [p.0, p.1]),
            autopilot,
            heading: self.bridge.as_ref().and_then(|b| b.heading()).unwrap_or(0.0),
            // The autopilot's battery; without one, a stand-in draining linearly over the mission.
            battery: self.bridge.as_ref().and_then(|b| b.battery()).unwrap_or_else(|| {
                (1.0 - 0.5 * self.step as f64 / self.brain.schedule().frames.max(1) as f64).clamp(0.0, 1.0)
            }),
            link: if self.server_alive {
                LinkState::Up
            } else {
                LinkState::Down
            },
            outbox_depth: self.outbox.depth(),
            acked: self.outbox.acked(),
            readings: self.instrument.as_ref().map(readings::Instrument::counts),
            traffic: Some(self.traffic_now()),
            sensor: self.sensor.clone(),
        };
        let bytes = protocol::encode(&Body::Telemetry(t.clone())).len();
        self.traffic.send("telemetry", bytes);
        if let Err(e) = fleet_net::put(&self.session, &self.keys.telemetry(&self.brain.id), &Body::Telemetry(t)).await {
            warn!("telemetry: {e}");
        }
    }
}

impl Vehicle {
    /// The link's traffic so far, the MAVLink pipe's included.
    fn traffic_now(&self) -> protocol::LinkTraffic {
        let mut t = self.traffic.clone();
        let (n, bytes) = self.mavlink_out.get();
        if n > 0 {
            t.sent.insert("mavlink".into(), [n, bytes]);
        }
        t
    }
}

/// The last batch this vehicle sends (none: it senses nothing in this mission).
fn schedule_last(brain: &VehicleBrain) -> Option<u64> {
    brain.schedule().last_seq(brain.kind)
}

impl Vehicle {
    /// The autopilot's status changed: telemetry at once when the link, GUIDED or the mode did.
    async fn on_autopilot(&mut self, status: AutopilotStatus) {
        if self.shown.note(&status) {
            self.telemetry().await;
        }
    }

    /// A ground station's frame for this vehicle's autopilot.
    fn on_gcs(&mut self, sample: &zenoh::sample::Sample) {
        self.traffic.receive("gcs", sample.payload().len());
        if let Some(b) = &mut self.bridge {
            if let Err(e) = b.from_gcs(&sample.payload().to_bytes()) {
                debug!("ground-station frame refused: {e}");
            }
        }
    }

    /// The MAVLink link's counters, at the end.
    fn log_link(&self) {
        let Some(b) = &self.bridge else { return };
        let c = b.counters();
        let p = fleet_mission::events::Percentiles::of(&self.guided_ms);
        info!(
            received = c.received,
            sent = c.sent,
            unreadable = c.unreadable,
            from_gcs = c.from_gcs,
            refused_from_gcs = c.refused_from_gcs,
            refused_signing = c.refused_signing,
            plan_to_guided_p50_ms = format!("{:.3}", p.p50),
            plan_to_guided_max_ms = format!("{:.3}", p.max),
            targets = p.count,
            "MAVLink link to the autopilot"
        );
    }
}

/// What the node's loop listens to: the server's acks and liveliness, the ground station's
/// frames, the autopilot's status, and its own tasks' replies (plans, drives).
struct Inputs {
    acks: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    links: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    gcs: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    autopilot: Option<watch::Receiver<AutopilotStatus>>,
    plans: mpsc::UnboundedReceiver<(u64, (Option<Plan>, usize))>,
    driven: mpsc::UnboundedReceiver<Driven>,
    /// The instrument's lines or frames (none for the simulated sensor).
    lines: Option<mpsc::Receiver<Input>>,
}

/// The instrument's next line or frame (never, without one or once its stream has ended).
async fn next_input(rx: &mut Option<mpsc::Receiver<Input>>) -> Input {
    if let Some(r) = rx {
        if let Some(line) = r.recv().await {
            return line;
        }
        tracing::info!("the instrument's stream ended");
    }
    *rx = None;
    std::future::pending().await
}

/// The autopilot's next status (never, without one; a stopped bridge is not heard again).
async fn autopilot_changed(rx: &mut Option<watch::Receiver<AutopilotStatus>>) -> AutopilotStatus {
    if let Some(r) = rx {
        if r.changed().await.is_ok() {
            return r.borrow_and_update().clone();
        }
    }
    *rx = None;
    std::future::pending().await
}

fn closed(what: &str) -> impl Fn(zenoh::Error) -> anyhow::Error + '_ {
    move |e| anyhow::anyhow!("{what} subscriber closed: {e}")
}

/// Everything the vehicle's loop reacts to, one at a time, as it arrives.
enum Event {
    /// A message on this vehicle's ack key (the server's ack of a batch).
    Ack(zenoh::sample::Sample),
    /// The server's liveliness token, put or deleted.
    ServerLink(zenoh::sample::Sample),
    /// A ground station's MAVLink frame for this vehicle's autopilot.
    Gcs(zenoh::sample::Sample),
    /// The autopilot's status changed.
    Autopilot(AutopilotStatus),
    /// The resend and deadline tick ([`ASK_EVERY`]).
    Tick,
    /// A plan query's answer for an epoch: the plan, if there was one, and its bytes.
    Plan(u64, (Option<Plan>, usize)),
    /// An epoch's drive ended.
    Driven(Driven),
    /// The instrument's next line or frame.
    Input(Input),
}

impl Inputs {
    /// The next event (an error once one of the Zenoh subscribers is closed).
    async fn next(&mut self, tick: &mut tokio::time::Interval) -> anyhow::Result<Event> {
        Ok(tokio::select! {
            r = self.acks.recv_async() => Event::Ack(r.map_err(closed("ack"))?),
            r = self.links.recv_async() => Event::ServerLink(r.map_err(closed("liveliness"))?),
            r = self.gcs.recv_async() => Event::Gcs(r.map_err(closed("ground-station"))?),
            status = autopilot_changed(&mut self.autopilot) => Event::Autopilot(status),
            _ = tick.tick() => Event::Tick,
            Some((e, plan)) = self.plans.recv() => Event::Plan(e, plan),
            Some(d) = self.driven.recv() => Event::Driven(d),
            input = next_input(&mut self.lines) => Event::Input(input),
        })
    }
}

impl Vehicle {
    /// The node's one loop: every event, one at a time, until every batch is acknowledged.
    async fn run_loop(&mut self, mut inputs: Inputs, truth: Option<&Frames>) -> anyhow::Result<()> {
        // Resends, the next plan query and the deadlines are checked at this rate; everything
        // else wakes the loop when it happens.
        let mut tick = tokio::time::interval(ASK_EVERY);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        while self.phase != Phase::Done {
            let event = inputs.next(&mut tick).await?;
            self.on_event(event, truth).await?;
        }
        Ok(())
    }

    async fn on_event(&mut self, event: Event, truth: Option<&Frames>) -> anyhow::Result<()> {
        match event {
            Event::Ack(sample) => self.on_ack(&sample)?,
            Event::ServerLink(sample) => self.on_link(&sample),
            Event::Gcs(sample) => self.on_gcs(&sample),
            Event::Autopilot(status) => self.on_autopilot(status).await,
            Event::Tick => self.on_tick().await?,
            Event::Plan(e, plan) => self.on_plan(e, plan),
            Event::Driven(d) => self.on_driven(d, truth).await?,
            Event::Input(input) => self.on_input(input),
        }
        Ok(())
    }
}

/// The brain of this vehicle, from the mission.
fn brain_of(setup: &Setup, mission: &MissionConfig) -> VehicleBrain {
    VehicleBrain::new(
        &setup.id,
        setup.kind,
        setup.grid,
        mission.schedule(setup.frames),
        mission.noise(setup.kind),
        vehicle_rng(mission.team.seed, setup.index),
        mission.speed(setup.kind),
    )
}

/// Whether a vehicle whose server was last seen `lost_at` (or never, since it started then) is
/// cut off at `now`: gone, and for at least `grace`.
fn link_cut_off(alive: bool, lost_at: Instant, grace: Duration, now: Instant) -> bool {
    !alive && now.saturating_duration_since(lost_at) >= grace
}

/// The Zenoh side: the session, this vehicle's liveliness token and its subscriptions, and how
/// long the server's token may be gone before the vehicle counts itself out of range.
async fn join(
    args: &Args,
    mission: &MissionConfig,
    keys: &Keys,
) -> anyhow::Result<(
    zenoh::Session,
    zenoh::liveliness::LivelinessToken,
    [SampleSub; 3],
    Duration,
)> {
    let network = mission.network.for_node(&args.id);
    let zenoh_config = args.node.zenoh_config(Role::Vehicle, &network, &mission.link)?;
    let grace = 2 * fleet_net::lease(&zenoh_config);
    fleet_net::exit_when_refused("vehicle", &zenoh_config, args.node.zenoh_file(Role::Vehicle, &network));
    let session = fleet_net::open(zenoh_config).await?;
    let e = |e: zenoh::Error| anyhow::anyhow!("{e}");
    let token = session
        .liveliness()
        .declare_token(keys.alive(&args.id))
        .await
        .map_err(e)?;
    let acks = session.declare_subscriber(keys.ack(&args.id)).await.map_err(e)?;
    let alive = keys.alive("server");
    let links = session
        .liveliness()
        .declare_subscriber(alive)
        .history(true)
        .await
        .map_err(e)?;
    let gcs = session.declare_subscriber(keys.gcs(&args.id)).await.map_err(e)?;
    Ok((session, token, [acks, links, gcs], grace))
}

type SampleSub = zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

pub async fn run(args: Args) -> anyhow::Result<()> {
    let (mission, truth) = args.node.load()?;
    let setup = Setup::resolve(&args, &mission, truth.as_ref())?;
    let grid = setup.grid;
    let keys = Keys::new(&mission.mission)?;
    let brain = brain_of(&setup, &mission);
    let mut ctx = Context::new(grid);
    ctx.vehicles = mission.vehicles().into_iter().map(|v| v.id).collect();

    // Local state first: a damaged outbox is refused before anything goes on the network.
    let path = args.state_dir.join(format!("{}.redb", args.id));
    let outbox = Outbox::open(&path, &args.id, args.outbox_limit_mb << 20).map_err(outbox_error)?;
    let state: Option<BrainState> = outbox.state().map_err(outbox_error)?;
    let bridge = compose::open_bridge(&setup, &args, &mission)?;
    let (session, _token, [acks, links, gcs], grace) = join(&args, &mission, &keys).await?;
    let mavlink_out = compose::Counted::default();
    let bridge = bridge.map(|(b, frames)| {
        let linger = mission.link.mavlink_linger();
        compose::pipe_to_gateway(&session, &keys, &args.id, frames, linger, mavlink_out.clone());
        b
    });
    let instrument = instrument_of(&setup, &args, &mission, &brain, truth.is_some())?;
    let source = setup.sensor.clone();
    let lines = open_source(&source, bridge.as_ref(), &mission, grid)?;
    let (plans_tx, plans) = mpsc::unbounded_channel();
    let (driven_tx, driven) = mpsc::unbounded_channel();
    let inputs = Inputs {
        acks,
        links,
        gcs,
        autopilot: bridge.as_ref().map(Bridge::status_changes),
        plans,
        driven,
        lines,
    };
    let pace = mission.pace.clone();
    let mut v = Vehicle {
        session: session.clone(),
        keys,
        ctx,
        grid,
        brain,
        outbox,
        server_alive: false,
        sensor: None,
        link_lost_at: None,
        link_failsafe: false,
        started: Instant::now(),
        link_grace: grace,
        mavlink: mission.mavlink.clone(),
        link: mission.link.clone(),
        resend: fleet_net::rto::Retransmit::new(Duration::from_millis(pace.resend_ms)),
        in_flight: Default::default(),
        plan_timeout: Duration::from_millis(pace.plan_timeout_ms),
        arrival_timeout: Duration::from_millis(mission.mavlink.arrival_timeout_ms),
        step_ms: pace.step_ms,
        step: 0,
        phase: Phase::Done,
        asking: false,
        plans: plans_tx,
        driven: driven_tx,
        args,
        bridge,
        shown: shown::Shown::default(),
        plan_at: None,
        guided_ms: vec![],
        clock: mission.clock(),
        instrument,
        traffic: protocol::LinkTraffic::default(),
        mavlink_out,
    };
    v.telemetry().await;
    v.resume(state);
    v.run_loop(inputs, truth.as_ref()).await?;
    v.finish().await
}

/// The instrument's stream: NAMED_VALUE_FLOAT from the bridge for `mavlink:NAME`, else the
/// source's own reader (none for the simulated sensor).
fn open_source(
    source: &SensorSource,
    bridge: Option<&Bridge>,
    mission: &MissionConfig,
    grid: Grid,
) -> anyhow::Result<Option<mpsc::Receiver<Input>>> {
    match (source, bridge) {
        // (A mavlink source without an autopilot link was refused when it was chosen.)
        (SensorSource::Mavlink(name), Some(b)) => Ok(Some(b.named_values(name, vehicles::sensor::QUEUE))),
        _ => vehicles::sensor::open(source, mission.mavlink.site(&grid), grid)
            .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("sensor source {source}: {e}"))),
    }
}

/// Unless the sensor source is the simulated one, this vehicle's instrument (the source
/// checked against the mission first).
fn instrument_of(
    setup: &Setup,
    args: &Args,
    mission: &MissionConfig,
    brain: &VehicleBrain,
    has_truth: bool,
) -> anyhow::Result<Option<readings::Instrument>> {
    let source = &setup.sensor;
    let m = fleet_mission::instrument::source::Mission {
        timed: mission.clock().is_some(),
        truth: has_truth,
        autopilot: setup.has_autopilot(),
    };
    check_source(source, brain.kind, m)
        .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("sensor source {source} for {}: {e}", setup.id)))?;
    if *source == SensorSource::Sim && !has_truth {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "sensor source sim for {}: the simulated sensor samples a truth; the mission has no [truth] and no \
             --truth was given",
            setup.id
        )));
    }
    let instrument = if *source == SensorSource::Sim {
        None
    } else {
        let path = args.state_dir.join(format!("{}.readings.ndjson", setup.id));
        let log = readings_log::ReadingsLog::open(&path, &setup.id)
            .map_err(|e| anyhow::anyhow!("the readings log {}: {e}", path.display()))?;
        readings::Instrument::new(
            mission,
            (setup.grid, setup.frames),
            brain.kind,
            brain.first_sensed_step(),
            Some(log),
        )
    };
    info!(vehicle = %setup.id, %source, "sensor source");
    Ok(instrument)
}

impl Vehicle {
    /// Start from the outbox's state (a restart) or from the first epoch.
    fn resume(&mut self, state: Option<BrainState>) {
        let first = match state {
            Some(state) => {
                let e = state.next_epoch;
                self.brain.restore(state);
                let open = self.brain.schedule().steps_of(e).start as u64;
                if let Some(i) = &mut self.instrument {
                    i.reopen(open, MissionClock::now());
                }
                let unacknowledged = self.outbox.depth();
                info!(
                    vehicle = %self.brain.id,
                    epoch = e,
                    unacknowledged,
                    "resuming from the outbox"
                );
                e
            }
            None => 0,
        };
        let (kind, epochs) = (self.brain.kind, self.brain.schedule().epochs());
        info!(vehicle = %self.brain.id, ?kind, epochs, "vehicle up");
        self.begin(first);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A token gone for less than the grace is a moment's loss (the vehicle keeps waiting for
    /// the server's plan); gone for the grace, or never seen in that time, it is out of range.
    #[test]
    fn a_server_token_lost_for_a_moment_is_not_out_of_range() {
        let (t0, grace) = (Instant::now(), Duration::from_secs(10));
        let at = |s: u64| t0 + Duration::from_secs(s);
        assert!(
            !link_cut_off(false, t0, grace, at(0)),
            "cut off the moment the token went"
        );
        assert!(!link_cut_off(false, t0, grace, at(9)));
        assert!(link_cut_off(false, t0, grace, at(10)));
        assert!(
            !link_cut_off(true, t0, grace, at(60)),
            "a server that is here is not gone"
        );
        // A clock read before the loss was noted does not count as time gone.
        assert!(!link_cut_off(false, at(5), grace, t0));
    }
}
