//! The vehicle's loop over the mission's epochs, one `select!` over what can happen: an ack
//! (trim the outbox; the model moved, so ask for the plan again), the server's liveliness (a
//! returned link sends the whole backlog), the resend tick (re-send what is due; ask for the
//! plan every 250 ms; after `plan_timeout_ms` without an answer, follow the horizon of the plan
//! held), a plan reply (drive and sense the epoch) and the end of an epoch's drive and step
//! timer (commit the batch, send it, go on). Every batch is kept until the server's ack covers
//! it.

use crate::Args;
use anyhow::Context as _;
use fleet_mission::config::MissionConfig;
use fleet_mission::grid::Grid;
use fleet_mission::protocol::{self, keys::Keys, Body, Context, LinkState, Plan, Target, Telemetry};
use fleet_mission::signing_key::SigningKey;
use fleet_mission::site::Site;
use fleet_mission::vehicle::{BrainState, Fix, VehicleBrain};
use fleet_mission::vehicle_rng;
use fleet_net::outbox::{Outbox, OutboxError};
use fleet_net::{zenoh, Role};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::{debug, info, warn};
use vehicles::autopilot::modes::{Frame, Role as Mode};
use vehicles::autopilot::safety::Action;
use vehicles::autopilot::sim::SimSpec;
use vehicles::bridge::{Bridge, BridgeSpec};
use zenoh::sample::SampleKind;

/// How often the plan is asked for while none has come (an ack asks at once).
const ASK_EVERY: Duration = Duration::from_millis(250);

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
    /// Every epoch sensed: waiting until the last batch is acknowledged.
    Finish {
        deadline: Instant,
    },
    Done,
}

/// What a drive task reports: the epoch, where the autopilot was at each sampling step, and
/// how long after the plan the first guided target left (ms).
type Driven = (u64, BTreeMap<u64, Fix>, Option<f64>);

struct Vehicle {
    args: Args,
    session: zenoh::Session,
    keys: Keys,
    ctx: Context,
    grid: Grid,
    brain: VehicleBrain,
    outbox: Outbox,
    server_alive: bool,
    /// When the link to the server went down, and whether the link-loss failsafe acted.
    link_lost_at: Option<Instant>,
    link_failsafe: bool,
    mavlink: fleet_mission::config::MavlinkConfig,
    resend: Duration,
    plan_timeout: Duration,
    arrival_timeout: Duration,
    step_ms: u64,
    step: u64,
    phase: Phase,
    /// A plan query is out (one at a time).
    asking: bool,
    plans: mpsc::UnboundedSender<(u64, Option<Plan>)>,
    driven: mpsc::UnboundedSender<Driven>,
    bridge: Option<Arc<Bridge>>,
    /// The newest telemetry (the autopilot watch re-sends it when the autopilot changes).
    last_telemetry: Arc<Mutex<Option<Telemetry>>>,
    /// When the epoch's plan came in, and how long after it each first guided target left (ms).
    plan_at: Option<Instant>,
    guided_ms: Vec<f64>,
}

fn outbox_error(e: OutboxError) -> anyhow::Error {
    const RECOVERY: &str = "to go on, move the file aside (keep it for inspection) and start the vehicle again: it \
        starts over from the first epoch, senses again what the plans say and the server keeps what it already has \
        (batches held only in this outbox are lost)";
    match e {
        OutboxError::Store(e @ fleet_net::store::StoreError::InUse { .. }) => {
            fleet_mission::exit::bad_input(anyhow::anyhow!("the outbox {e}: is this vehicle already running?"))
        }
        e if e.is_bad_file() => fleet_mission::exit::bad_input(anyhow::anyhow!("the outbox {e}; {RECOVERY}")),
        e => anyhow::Error::new(e).context("the outbox"),
    }
}

impl Vehicle {
    fn on_ack(&mut self, sample: &zenoh::sample::Sample) -> anyhow::Result<()> {
        match fleet_net::decode(sample, &self.ctx) {
            Ok(Body::Ack(a)) if a.vehicle == self.brain.id => {
                if let Err(e) = self.outbox.ack(a.seq) {
                    warn!("recording ack {}: {e:#}", a.seq);
                }
                match self.phase {
                    // The model moved on: its plan may be there now.
                    Phase::Plan { ref mut next_ask, .. } => *next_ask = Instant::now(),
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
                // Back in range: the whole backlog is due now, oldest first.
                self.outbox.resend_all();
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
        for (seq, bytes) in self.outbox.due(Instant::now(), self.resend).map_err(outbox_error)? {
            debug!(seq, "sending from the outbox");
            if let Err(e) = self.session.put(&key, bytes).encoding(fleet_net::encoding()).await {
                warn!("sending batch {seq}: {e}");
            }
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
    }

    fn finish_if_acknowledged(&mut self) {
        if schedule_last(&self.brain).is_none_or(|last| self.outbox.covers(last)) {
            self.phase = Phase::Done;
        }
    }

    /// Ask the server for the plan from epoch `e`, in a task; the reply comes on `plans`.
    fn ask_plan(&mut self, e: u64) {
        self.asking = true;
        let (session, ctx, tx) = (self.session.clone(), self.ctx.clone(), self.plans.clone());
        let selector = format!("{}?epoch={e}", self.keys.plan(&self.brain.id));
        tokio::spawn(async move {
            let _ = tx.send((e, query_plan(&session, &selector, &ctx, e).await));
        });
    }

    /// The resend tick: what is due goes out; the plan is asked for again, or, past the
    /// timeout (or with the server gone), the held plan's horizon is followed.
    /// Out of range for longer than the mission allows: the link-loss failsafe's action.
    fn check_link_loss(&mut self) {
        let m = &self.mavlink;
        let role = match m.link_loss_action.as_str() {
            "rtl" => Mode::Return,
            "hold" => Mode::Hold,
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
        self.resend_due().await?;
        let now = Instant::now();
        match self.phase {
            Phase::Plan {
                epoch,
                deadline,
                warned,
                next_ask,
            } => {
                // Cut off from the server (its liveliness token gone): no use waiting out the
                // timeout, the held horizon says where to sense, at the mission's pace.
                if (now > deadline || !self.server_alive) && self.brain.covers(epoch) {
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
                let next_ask = if !self.asking && now >= next_ask {
                    self.ask_plan(epoch);
                    now + ASK_EVERY
                } else {
                    next_ask
                };
                self.phase = Phase::Plan {
                    epoch,
                    deadline,
                    warned: warned || now > deadline,
                    next_ask,
                };
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

    fn on_plan(&mut self, e: u64, plan: Option<Plan>) {
        self.asking = false;
        match (self.phase, plan) {
            (Phase::Plan { epoch, .. }, Some(p)) if epoch == e => {
                self.brain.set_plan(p);
                self.plan_at = Some(Instant::now());
                self.sense(e);
            }
            // Asked again at once when an ack came meanwhile.
            _ => {}
        }
    }

    /// Drive to epoch `e`'s places and wait out its steps, in a task (acks, resends and the
    /// link keep being handled meanwhile); [`Self::on_driven`] senses when it reports.
    fn sense(&mut self, e: u64) {
        self.phase = Phase::Sense { epoch: e };
        let (bridge, targets, grid, timeout, tx) = (
            self.bridge.clone(),
            self.brain.targets_of(e),
            self.grid,
            self.arrival_timeout,
            self.driven.clone(),
        );
        let (plan_at, pace) = (
            self.plan_at.take(),
            Duration::from_millis(self.step_ms * self.brain.schedule().steps_of(e).len() as u64),
        );
        tokio::spawn(async move {
            let (fixes, guided) = drive(bridge, targets, grid, timeout, plan_at).await;
            tokio::time::sleep(pace).await;
            let _ = tx.send((e, fixes, guided));
        });
    }

    /// Epoch `e` driven: sense it, commit the batch (durable first, then sent: a crash in
    /// between re-sends it after the restart), send it, go on.
    async fn on_driven(
        &mut self,
        (e, fixes, guided): Driven,
        truth: &fleet_mission::process::FieldSeries,
    ) -> anyhow::Result<()> {
        self.guided_ms.extend(guided);
        self.step = self.brain.schedule().steps_of(e).end.saturating_sub(1) as u64;
        let truth_at = |k: usize| -> Vec<f64> { truth.snapshots.col(k).iter().copied().collect() };
        if let Some(batch) = self.brain.sense_epoch_at(e, truth_at, &fixes)? {
            let bytes = protocol::encode(&Body::Batch(batch.clone()));
            let state: BrainState = self.brain.state(e + 1);
            if self.outbox.commit(batch.seq, &bytes, &state).map_err(outbox_error)? {
                warn!(
                    depth = self.outbox.depth(),
                    limit = self.args.outbox_limit_mb << 20,
                    "outbox at 80% of its bound: the vehicle will pause sensing when it is full"
                );
            }
            if let Err(err) = self
                .session
                .put(self.keys.measurements(&self.brain.id), bytes)
                .encoding(fleet_net::encoding())
                .await
            {
                warn!("sending batch {}: {err} (kept in the outbox)", batch.seq);
            }
            self.outbox.mark_sent(batch.seq, Instant::now());
        }
        self.telemetry().await;
        self.begin(e + 1);
        Ok(())
    }

    async fn telemetry(&self) {
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
            autopilot: self.bridge.as_ref().map(|b| b.status()),
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
        };
        *self.last_telemetry.lock().unwrap_or_else(|p| p.into_inner()) = Some(t.clone());
        if let Err(e) = fleet_net::put(&self.session, &self.keys.telemetry(&self.brain.id), &Body::Telemetry(t)).await {
            warn!("telemetry: {e}");
        }
    }
}

/// The last batch this vehicle sends (none: it senses nothing in this mission).
fn schedule_last(brain: &VehicleBrain) -> Option<u64> {
    brain.schedule().last_seq(brain.kind)
}

/// The plan from epoch `e`, or none yet.
async fn query_plan(session: &zenoh::Session, selector: &str, ctx: &Context, e: u64) -> Option<Plan> {
    let replies = match session.get(selector).timeout(Duration::from_secs(2)).await {
        Ok(r) => r,
        Err(err) => {
            warn!("asking for the plan: {err}");
            return None;
        }
    };
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => match fleet_net::decode(sample, ctx) {
                Ok(Body::Plan(p)) if p.epoch == e => return Some(p),
                Ok(_) => warn!("a plan reply for another epoch or of another type"),
                Err(err) => warn!("refused a plan: {err}"),
            },
            Err(err) => debug!("no plan yet: {}", String::from_utf8_lossy(&err.payload().to_bytes())),
        }
    }
    None
}

/// Drive the autopilot to each place of `targets` and wait (up to the arrival timeout) until
/// it is there; the fixes say where it was. Without an autopilot: none.
async fn drive(
    bridge: Option<Arc<Bridge>>,
    targets: Vec<Target>,
    grid: Grid,
    timeout: Duration,
    mut plan_at: Option<Instant>,
) -> (BTreeMap<u64, Fix>, Option<f64>) {
    let (mut fixes, mut guided) = (BTreeMap::new(), None);
    let Some(b) = bridge else { return (fixes, guided) };
    for t in targets.iter().filter(|t| !t.cells.is_empty()) {
        let goal = (t.position[0], t.position[1]);
        let deadline = Instant::now() + timeout;
        // Still being armed and set to GUIDED (the first epoch): wait for it.
        while b.link() == protocol::AutopilotLink::Connecting && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let mut sent: Option<Instant> = None;
        while !b.arrived(goal) && Instant::now() < deadline && b.drivable() {
            // Again every second: a guided target on a lossy radio may not arrive.
            // (and at once at a corner of a way routed round the fence).
            if sent.is_none_or(|s| s.elapsed() >= Duration::from_secs(1)) || b.at_corner() {
                if b.goto(goal) {
                    if let Some(t) = plan_at.take() {
                        guided = Some(t.elapsed().as_secs_f64() * 1e3);
                    }
                }
                sent = Some(Instant::now());
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        if let Some(p) = b.position() {
            // Sensing happens on the grid, wherever the autopilot drifted.
            let (w, h) = (grid.width_m(), grid.height_m());
            let position = (p.0.clamp(0.0, w - 1e-9), p.1.clamp(0.0, h - 1e-9));
            fixes.insert(
                t.step,
                Fix {
                    position,
                    arrived: b.arrived(goal),
                },
            );
        }
    }
    (fixes, guided)
}

/// The MAVLink bridge, unless the autopilot is `none`; its frames go to `gcs`.
fn open_bridge(
    args: &Args,
    mission: &MissionConfig,
    grid: &Grid,
    gcs: vehicles::bridge::GcsSink,
) -> anyhow::Result<Option<Arc<Bridge>>> {
    let m = &mission.mavlink;
    let address = args.autopilot.clone().unwrap_or_else(|| m.autopilot.clone());
    if address == "none" {
        return Ok(None);
    }
    let (index, kind) = mission.vehicle(&args.id)?;
    let site = Site::new(m, grid);
    // Launched from points along the south shore.
    let n = mission.vehicles().len() as f64;
    let launch = |i: usize| site.ned_of(((i as f64 + 0.5) * grid.width_m() / n, 0.5 * grid.cell_m), 0.0);
    let home = launch(index);
    // The fence: the mission's boundary, or the site's extent.
    let fence_m = match &mission.team.fence {
        Some(f) => f.polygon_m.clone(),
        None => {
            let corner = site.ned_of((grid.width_m(), grid.height_m()), 0.0);
            vec![[0.0, 0.0], [corner.y, 0.0], [corner.y, corner.x], [0.0, corner.x]]
        }
    };
    let mut vehicle = SimSpec::from_config(Frame::of(kind), mission.sysid(&args.id)?, site, m);
    if let Some(mah) = args.sim_battery_start_mah {
        if !(mah.is_finite() && (0.0..=m.battery_mah).contains(&mah)) {
            return Err(fleet_mission::exit::bad_input(anyhow::anyhow!(
                "--sim-battery-start-mah {mah}: must be within 0..{} (the mission's battery_mah)",
                m.battery_mah
            )));
        }
        vehicle.safety.battery_start_mah = Some(mah);
    }
    let spec = BridgeSpec {
        vehicle,
        acceptance_m: m.acceptance_m,
        heartbeat_timeout: Duration::from_millis(m.heartbeat_timeout_ms),
        home,
        fence_m,
        // (The mission file's name was checked when it was read.)
        fence_action: Action::from_name(&m.fence_action).unwrap_or(Action::Continue) as u8 as f32,
        rally: (0..mission.vehicles().len()).map(launch).collect(),
        signing: match m.autopilot_key_of(&args.id) {
            Some(p) => Some((
                SigningKey::read(&p)
                    .map_err(fleet_mission::exit::bad_input)
                    .context("[mavlink] autopilot_signing_key")?,
                m.accept_unsigned_telemetry,
            )),
            None => None,
        },
    };
    Ok(Some(Arc::new(Bridge::connect(&address, spec, Some(gcs))?)))
}

/// The MAVLink side's tasks: the autopilot's frames out to the ground-station gateway, the
/// gateway's frames in to the autopilot, and telemetry again whenever the autopilot's link or
/// mode changes (so the server leaves a held vehicle out of the next allocation).
fn spawn_mavlink_tasks(
    session: &zenoh::Session,
    keys: &Keys,
    id: &str,
    bridge: Arc<Bridge>,
    mut frames: tokio::sync::mpsc::UnboundedReceiver<Vec<u8>>,
    last: Arc<Mutex<Option<Telemetry>>>,
) {
    let (s, key) = (session.clone(), keys.mavlink(id));
    tokio::spawn(async move {
        while let Some(f) = frames.recv().await {
            let _ = s.put(&key, f).await;
        }
    });
    let (s, key, b) = (session.clone(), keys.gcs(id), bridge.clone());
    tokio::spawn(async move {
        let Ok(sub) = s.declare_subscriber(&key).await else {
            return warn!("cannot subscribe to {key}");
        };
        while let Ok(sample) = sub.recv_async().await {
            if let Err(e) = b.from_gcs(&sample.payload().to_bytes()) {
                debug!("ground-station frame refused: {e}");
            }
        }
    });
    let (s, key) = (session.clone(), keys.telemetry(id));
    tokio::spawn(async move {
        let mut shown = None;
        loop {
            tokio::time::sleep(Duration::from_millis(100)).await;
            let status = bridge.status();
            let now = (status.link, status.guided, status.mode.clone());
            if shown.as_ref() == Some(&now) {
                continue;
            }
            let base = last.lock().unwrap_or_else(|p| p.into_inner()).clone();
            if let Some(mut t) = base {
                info!(link = ?status.link, mode = status.mode, armed = status.armed, "autopilot");
                t.autopilot = Some(status);
                if fleet_net::put(&s, &key, &Body::Telemetry(t)).await.is_ok() {
                    shown = Some(now);
                }
            }
        }
    });
}

pub async fn run(args: Args) -> anyhow::Result<()> {
    let (mission, truth) = args.node.load()?;
    let (grid, frames) = mission.workspace(&truth)?;
    let (index, kind) = mission.vehicle(&args.id)?;
    let keys = Keys::new(&mission.mission)?;
    let schedule = mission.schedule(frames);
    let brain = VehicleBrain::new(
        &args.id,
        kind,
        grid,
        schedule,
        mission.noise(kind),
        vehicle_rng(mission.team.seed, index),
        mission.speed(kind),
    );
    let mut ctx = Context::new(grid);
    ctx.vehicles = mission.vehicles().into_iter().map(|v| v.id).collect();

    // Local state first: a damaged outbox is refused before anything goes on the network.
    let outbox = Outbox::open(
        &args.state_dir.join(format!("{}.redb", args.id)),
        &args.id,
        args.outbox_limit_mb << 20,
    )
    .map_err(outbox_error)?;
    let state: Option<BrainState> = outbox.state().map_err(outbox_error)?;
    let (gcs_tx, gcs_rx) = tokio::sync::mpsc::unbounded_channel();
    let bridge = open_bridge(&args, &mission, &grid, gcs_tx)?;
    let last_telemetry = Arc::new(Mutex::new(None));
    let network = mission.network.for_node(&args.id);
    let zenoh_config = args.node.zenoh_config(Role::Vehicle, &network)?;
    fleet_net::exit_when_refused("vehicle", &zenoh_config, args.node.zenoh_file(Role::Vehicle, &network));
    let session = fleet_net::open(zenoh_config).await?;
    if let Some(b) = &bridge {
        spawn_mavlink_tasks(&session, &keys, &args.id, b.clone(), gcs_rx, last_telemetry.clone());
    }
    let _token = session
        .liveliness()
        .declare_token(keys.alive(&args.id))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let acks = session
        .declare_subscriber(keys.ack(&args.id))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let links = session
        .liveliness()
        .declare_subscriber(keys.alive("server"))
        .history(true)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let (plans_tx, mut plans) = mpsc::unbounded_channel();
    let (driven_tx, mut driven) = mpsc::unbounded_channel();
    let pace = mission.pace.clone();
    let mut v = Vehicle {
        session: session.clone(),
        keys,
        ctx,
        grid,
        brain,
        outbox,
        server_alive: false,
        link_lost_at: None,
        link_failsafe: false,
        mavlink: mission.mavlink.clone(),
        resend: Duration::from_millis(pace.resend_ms),
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
        last_telemetry,
        plan_at: None,
        guided_ms: vec![],
    };
    v.telemetry().await;
    let first = match state {
        Some(state) => {
            let e = state.next_epoch;
            v.brain.restore(state);
            info!(
                vehicle = v.brain.id,
                epoch = e,
                unacknowledged = v.outbox.depth(),
                "resuming from the outbox"
            );
            e
        }
        None => 0,
    };
    info!(vehicle = v.brain.id, ?kind, epochs = schedule.epochs(), "vehicle up");
    v.begin(first);

    let mut tick = tokio::time::interval(Duration::from_millis(20));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    while v.phase != Phase::Done {
        tokio::select! {
            r = acks.recv_async() => {
                let sample = r.map_err(|e| anyhow::anyhow!("ack subscriber closed: {e}"))?;
                v.on_ack(&sample)?;
            }
            r = links.recv_async() => {
                let sample = r.map_err(|e| anyhow::anyhow!("liveliness subscriber closed: {e}"))?;
                v.on_link(&sample);
            }
            _ = tick.tick() => v.on_tick().await?,
            Some((e, plan)) = plans.recv() => v.on_plan(e, plan),
            Some(d) = driven.recv() => v.on_driven(d, &truth).await?,
        }
    }
    v.telemetry().await;
    if let Some(b) = &v.bridge {
        let c = b.counters();
        let p = fleet_mission::events::Percentiles::of(&v.guided_ms);
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
    info!(
        vehicle = v.brain.id,
        off_target = v.brain.off_target,
        "mission done, every batch acknowledged"
    );
    session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}
