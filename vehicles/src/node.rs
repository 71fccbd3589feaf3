//! The vehicle's loop over the mission's epochs: get the plan of the epoch (asking again when
//! an ack says the model moved on; after `plan_timeout_ms` without an answer, follow the
//! horizon of the plan it holds), sense, publish, and keep every batch until the server's ack
//! covers it (re-sent every `resend_ms`).

use crate::Args;
use fleet_mission::config::MissionConfig;
use fleet_mission::grid::Grid;
use fleet_mission::protocol::{self, keys::Keys, Body, Context, LinkState, Telemetry};
use fleet_mission::vehicle::{BrainState, Fix, VehicleBrain};
use fleet_mission::vehicle_rng;
use fleet_net::store::{Store, StoreError};
use fleet_net::{zenoh, Role};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tracing::{debug, info, warn};
use vehicles::autopilot::modes::Frame;
use vehicles::autopilot::sim::SimSpec;
use vehicles::autopilot::site::Site;
use vehicles::bridge::{Bridge, BridgeSpec};
use zenoh::sample::SampleKind;

/// Batches not yet acknowledged, on disk: each is committed (with the vehicle's state) before
/// it is sent, re-sent until the server's ack covers it, and removed only then. It survives
/// `kill -9`; past `limit` bytes the vehicle stops sensing until acks make room (no batch is
/// ever dropped), with a warning at 80%.
struct Outbox {
    store: Store,
    id: String,
    acked: Option<u64>,
    /// Seqs held on disk, and when each was last sent (restored ones: never, so they go at
    /// once).
    held: std::collections::BTreeSet<u64>,
    sent: BTreeMap<u64, Instant>,
    limit: u64,
    warned: bool,
}

impl Outbox {
    fn open(path: &std::path::Path, id: &str, limit: u64) -> anyhow::Result<Self> {
        const RECOVERY: &str = "to go on, move the file aside (keep it for inspection) and start the vehicle again: it starts over from the first epoch, senses again what the plans say and the server keeps what it already has (batches held only in this outbox are lost)";
        let store = Store::open(path).map_err(|e| match e {
            e @ (StoreError::Damaged { .. } | StoreError::Empty { .. }) => fleet_mission::exit::bad_input(anyhow::anyhow!("the outbox {e}; {RECOVERY}")),
            e @ StoreError::InUse { .. } => fleet_mission::exit::bad_input(anyhow::anyhow!("the outbox {e}: is this vehicle already running?")),
            e => anyhow::Error::new(e).context("opening the outbox"),
        })?;
        let acked = store.meta("acked")?.and_then(|b| String::from_utf8(b).ok()).and_then(|s| s.parse().ok());
        let held = store.messages()?.into_iter().map(|((_, seq), _)| seq).collect();
        Ok(Self { store, id: id.into(), acked, held, sent: BTreeMap::new(), limit, warned: false })
    }

    fn state(&self) -> anyhow::Result<Option<BrainState>> {
        match self.store.meta("state")? {
            Some(b) => Ok(Some(
                ciborium::from_reader(&b[..])
                    .map_err(|e| fleet_mission::exit::bad_input(anyhow::anyhow!("the outbox {}: the vehicle state in it is unreadable ({e})", self.store.path().display())))?,
            )),
            None => Ok(None),
        }
    }

    /// Commit a batch and the state after it, in one transaction.
    fn commit(&mut self, seq: u64, bytes: &[u8], state: &BrainState) -> anyhow::Result<()> {
        let mut st = vec![];
        ciborium::into_writer(state, &mut st).expect("state serialises");
        self.store.commit(&[((self.id.as_str(), seq), bytes)], &[("state", &st)])?;
        self.held.insert(seq);
        let (used, _) = self.store.size();
        if used * 5 >= self.limit * 4 && !self.warned {
            warn!(used, limit = self.limit, "outbox at 80% of its bound: the vehicle will pause sensing when it is full");
            self.warned = true;
        }
        Ok(())
    }

    fn ack(&mut self, seq: u64) -> anyhow::Result<()> {
        if self.acked.is_some_and(|a| seq <= a) {
            return Ok(());
        }
        self.store.remove_through(&self.id, seq, &[("acked", seq.to_string().as_bytes())])?;
        self.acked = Some(seq);
        self.held.retain(|&s| s > seq);
        self.sent.retain(|&s, _| s > seq);
        if self.store.size().0 * 5 < self.limit * 4 {
            self.warned = false;
        }
        Ok(())
    }

    fn covers(&self, seq: u64) -> bool {
        self.acked.is_some_and(|a| a >= seq)
    }

    fn depth(&self) -> u64 {
        self.store.size().1
    }

    fn full(&self) -> bool {
        self.store.size().0 >= self.limit
    }
}

struct Vehicle {
    args: Args,
    keys: Keys,
    ctx: Context,
    brain: VehicleBrain,
    outbox: Outbox,
    server_alive: bool,
    resend: Duration,
    step: u64,
    bridge: Option<Arc<Bridge>>,
    /// The newest telemetry (the autopilot watch re-sends it when the autopilot changes).
    last_telemetry: Arc<Mutex<Option<Telemetry>>>,
    /// When the epoch's plan came in, and how long after it each first guided target left (ms).
    plan_at: Option<Instant>,
    guided_ms: Vec<f64>,
}

impl Vehicle {
    /// Take what arrived: acks and the server's liveliness. Returns whether an ack came.
    fn absorb(&mut self, acks: &zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>, links: &zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>) -> bool {
        let mut got = false;
        while let Ok(Some(s)) = acks.try_recv() {
            match fleet_net::decode(&s, &self.ctx) {
                Ok(Body::Ack(a)) if a.vehicle == self.brain.id => {
                    if let Err(e) = self.outbox.ack(a.seq) {
                        warn!("recording ack {}: {e:#}", a.seq);
                    }
                    got = true;
                }
                Ok(_) => warn!("ignored a message on the ack key that is not our ack"),
                Err(e) => warn!("refused an ack: {e}"),
            }
        }
        while let Ok(Some(s)) = links.try_recv() {
            let up = s.kind() == SampleKind::Put;
            if up {
                fleet_net::mark_connected();
            }
            if up != self.server_alive {
                info!(server_alive = up, backlog = self.outbox.depth(), "link to the model server");
                if up {
                    // Back in range: the whole backlog is due now, oldest first.
                    self.outbox.sent.clear();
                }
            }
            self.server_alive = up;
        }
        got
    }

    async fn resend_due(&mut self, session: &zenoh::Session) -> anyhow::Result<()> {
        let due: Vec<u64> = self.outbox.held.iter().copied().filter(|s| self.outbox.sent.get(s).is_none_or(|t| t.elapsed() >= self.resend)).collect();
        if due.is_empty() {
            return Ok(());
        }
        let key = self.keys.measurements(&self.brain.id);
        for ((_, seq), bytes) in self.outbox.store.messages()?.into_iter().filter(|((_, s), _)| due.contains(s)) {
            debug!(seq, "sending from the outbox");
            if let Err(e) = session.put(&key, bytes).encoding(fleet_net::encoding()).await {
                warn!("sending batch {seq}: {e}");
            }
            self.outbox.sent.insert(seq, Instant::now());
        }
        Ok(())
    }

    /// Ask the server for the plan from epoch `e`; `Ok(false)` when it has none yet.
    async fn query_plan(&mut self, session: &zenoh::Session, e: u64) -> anyhow::Result<bool> {
        let selector = format!("{}?epoch={e}", self.keys.plan(&self.brain.id));
        let replies = session.get(&selector).timeout(Duration::from_secs(2)).await.map_err(|err| anyhow::anyhow!("{err}"))?;
        while let Ok(reply) = replies.recv_async().await {
            match reply.result() {
                Ok(sample) => match fleet_net::decode(sample, &self.ctx) {
                    Ok(Body::Plan(p)) if p.epoch == e => {
                        self.brain.set_plan(p);
                        return Ok(true);
                    }
                    Ok(_) => warn!("a plan reply for another epoch or of another type"),
                    Err(err) => warn!("refused a plan: {err}"),
                },
                Err(err) => debug!("no plan yet: {}", String::from_utf8_lossy(&err.payload().to_bytes())),
            }
        }
        Ok(false)
    }

    async fn telemetry(&self, session: &zenoh::Session) {
        let t = Telemetry {
            vehicle: self.brain.id.clone(),
            step: self.step,
            position: self.brain.position().map_or([0.0, 0.0], |p| [p.0, p.1]),
            autopilot: self.bridge.as_ref().map(|b| b.status()),
            heading: 0.0,
            // A simulated battery: linear drain over the mission.
            battery: (1.0 - 0.5 * self.step as f64 / self.brain.schedule().frames.max(1) as f64).clamp(0.0, 1.0),
            link: if self.server_alive { LinkState::Up } else { LinkState::Down },
            outbox_depth: self.outbox.depth(),
            acked: self.outbox.acked,
        };
        *self.last_telemetry.lock().unwrap_or_else(|p| p.into_inner()) = Some(t.clone());
        if let Err(e) = fleet_net::put(session, &self.keys.telemetry(&self.brain.id), &Body::Telemetry(t)).await {
            warn!("telemetry: {e}");
        }
    }

    /// Drive the autopilot to each place epoch `e` senses and wait (up to the arrival timeout)
    /// until it is there; the fixes say where it was. Without an autopilot: none.
    async fn drive(&mut self, e: u64, grid: &Grid, timeout: Duration) -> BTreeMap<u64, Fix> {
        let mut fixes = BTreeMap::new();
        let Some(b) = self.bridge.clone() else { return fixes };
        for t in self.brain.targets_of(e).iter().filter(|t| !t.cells.is_empty()) {
            let goal = (t.position[0], t.position[1]);
            let deadline = Instant::now() + timeout;
            // Still being armed and set to GUIDED (the first epoch): wait for it.
            while b.link() == protocol::AutopilotLink::Connecting && Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            let mut sent: Option<Instant> = None;
            while !b.arrived(goal) && Instant::now() < deadline && b.drivable() {
                // Again every second: a guided target on a lossy radio may not arrive.
                if sent.is_none_or(|s| s.elapsed() >= Duration::from_secs(1)) {
                    if b.goto(goal) {
                        if let Some(t) = self.plan_at.take() {
                            self.guided_ms.push(t.elapsed().as_secs_f64() * 1e3);
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
                fixes.insert(t.step, Fix { position, arrived: b.arrived(goal) });
            }
        }
        fixes
    }
}

/// The MAVLink bridge, unless the autopilot is `none`; its frames go to `gcs`.
fn open_bridge(args: &Args, mission: &MissionConfig, grid: &Grid, gcs: vehicles::bridge::GcsSink) -> anyhow::Result<Option<Arc<Bridge>>> {
    let m = &mission.mavlink;
    let address = args.autopilot.clone().unwrap_or_else(|| m.autopilot.clone());
    if address == "none" {
        return Ok(None);
    }
    let (index, kind) = mission.vehicle(&args.id)?;
    let site = Site::new(m, grid);
    // Launched from points along the south shore.
    let n = mission.vehicles().len() as f64;
    let home = site.ned_of(((index as f64 + 0.5) * grid.width_m() / n, 0.5 * grid.cell_m), 0.0);
    let spec = BridgeSpec {
        vehicle: SimSpec::from_config(Frame::of(kind), mission.sysid(&args.id)?, site, m),
        acceptance_m: m.acceptance_m,
        heartbeat_timeout: Duration::from_millis(m.heartbeat_timeout_ms),
        home,
    };
    Ok(Some(Arc::new(Bridge::connect(&address, spec, Some(gcs))?)))
}

/// The MAVLink side's tasks: the autopilot's frames out to the ground-station gateway, the
/// gateway's frames in to the autopilot, and telemetry again whenever the autopilot's link or
/// mode changes (so the server leaves a held vehicle out of the next allocation).
fn spawn_mavlink_tasks(session: &zenoh::Session, keys: &Keys, id: &str, bridge: Arc<Bridge>, mut frames: tokio::sync::mpsc::UnboundedReceiver<Vec<u8>>, last: Arc<Mutex<Option<Telemetry>>>) {
    let (s, key) = (session.clone(), keys.mavlink(id));
    tokio::spawn(async move {
        while let Some(f) = frames.recv().await {
            let _ = s.put(&key, f).await;
        }
    });
    let (s, key, b) = (session.clone(), keys.gcs(id), bridge.clone());
    tokio::spawn(async move {
        let Ok(sub) = s.declare_subscriber(&key).await else { return warn!("cannot subscribe to {key}") };
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
    let brain = VehicleBrain::new(&args.id, kind, grid, schedule, mission.noise(kind), vehicle_rng(mission.team.seed, index), mission.speed(kind));
    let mut ctx = Context::new(grid);
    ctx.vehicles = mission.vehicles().into_iter().map(|v| v.id).collect();

    // Local state first: a damaged outbox is refused before anything goes on the network.
    let outbox = Outbox::open(&args.state_dir.join(format!("{}.redb", args.id)), &args.id, args.outbox_limit_mb << 20)?;
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
    let _token = session.liveliness().declare_token(keys.alive(&args.id)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let acks = session.declare_subscriber(keys.ack(&args.id)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let links = session.liveliness().declare_subscriber(keys.alive("server")).history(true).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let pace = mission.pace.clone();
    let arrival_timeout = Duration::from_millis(mission.mavlink.arrival_timeout_ms);
    let mut v = Vehicle { keys, ctx, brain, outbox, server_alive: false, resend: Duration::from_millis(pace.resend_ms), step: 0, args, bridge, last_telemetry, plan_at: None, guided_ms: vec![] };
    v.telemetry(&session).await;
    let first = match v.outbox.state()? {
        Some(state) => {
            let e = state.next_epoch;
            v.brain.restore(state);
            info!(vehicle = v.brain.id, epoch = e, unacknowledged = v.outbox.depth(), "resuming from the outbox");
            e
        }
        None => 0,
    };
    info!(vehicle = v.brain.id, ?kind, epochs = schedule.epochs(), "vehicle up");

    let truth_at = |k: usize| -> Vec<f64> { truth.snapshots.col(k).iter().copied().collect() };
    for e in first..schedule.epochs() {
        if schedule.seq_of(kind, e).is_none() {
            continue;
        }
        // What came while driving and sensing; a returned link sends the backlog before this
        // epoch's work.
        v.absorb(&acks, &links);
        v.resend_due(&session).await?;
        // A full outbox holds sensing until acks make room (nothing is dropped).
        let mut said = false;
        while v.outbox.full() {
            if !said {
                warn!(depth = v.outbox.depth(), "outbox full: holding until the server acknowledges");
                said = true;
            }
            v.absorb(&acks, &links);
            v.resend_due(&session).await?;
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        // The plan of this epoch: asked when an ack says the model moved, or every 250 ms.
        let deadline = Instant::now() + Duration::from_millis(pace.plan_timeout_ms);
        let mut warned = false;
        loop {
            if v.query_plan(&session, e).await? {
                v.plan_at = Some(Instant::now());
                break;
            }
            // Cut off from the server (its liveliness token gone): no use waiting out the
            // timeout, the held horizon says where to sense, at the mission's pace.
            if (Instant::now() > deadline || !v.server_alive) && v.brain.covers(e) {
                warn!(epoch = e, server_alive = v.server_alive, "no plan from the server: following the held plan's horizon");
                break;
            }
            if Instant::now() > deadline && !warned {
                warn!(epoch = e, "no plan from the server and none held: still asking");
                warned = true;
            }
            let wait = Instant::now() + Duration::from_millis(250);
            while Instant::now() < wait {
                if v.absorb(&acks, &links) {
                    break;
                }
                v.resend_due(&session).await?;
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        }
        let fixes = v.drive(e, &grid, arrival_timeout).await;
        let steps = schedule.steps_of(e);
        if pace.step_ms > 0 {
            tokio::time::sleep(Duration::from_millis(pace.step_ms * steps.len() as u64)).await;
        }
        v.step = steps.end.saturating_sub(1) as u64;
        if let Some(batch) = v.brain.sense_epoch_at(e, truth_at, &fixes)? {
            let bytes = protocol::encode(&Body::Batch(batch.clone()));
            // Durable first, then sent: a crash in between re-sends it after the restart.
            v.outbox.commit(batch.seq, &bytes, &v.brain.state(e + 1))?;
            if let Err(err) = session.put(v.keys.measurements(&v.brain.id), bytes).encoding(fleet_net::encoding()).await {
                warn!("sending batch {}: {err} (kept in the outbox)", batch.seq);
            }
            v.outbox.sent.insert(batch.seq, Instant::now());
        }
        v.absorb(&acks, &links);
        v.telemetry(&session).await;
    }

    // Stay until the server has everything.
    let last = schedule.last_seq(kind);
    let deadline = Instant::now() + Duration::from_millis(v.args.final_ack_ms);
    while let Some(last) = last {
        v.absorb(&acks, &links);
        if v.outbox.covers(last) {
            break;
        }
        if Instant::now() > deadline {
            anyhow::bail!("{}: batch {last} not acknowledged after {} ms ({} unacknowledged, kept in {})", v.brain.id, v.args.final_ack_ms, v.outbox.depth(), v.outbox.store.path().display());
        }
        v.resend_due(&session).await?;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    v.telemetry(&session).await;
    if let Some(b) = &v.bridge {
        let c = b.counters();
        let p = fleet_mission::events::Percentiles::of(&v.guided_ms);
        info!(
            received = c.received,
            sent = c.sent,
            unreadable = c.unreadable,
            from_gcs = c.from_gcs,
            refused_from_gcs = c.refused_from_gcs,
            plan_to_guided_p50_ms = format!("{:.3}", p.p50),
            plan_to_guided_max_ms = format!("{:.3}", p.max),
            targets = p.count,
            "MAVLink link to the autopilot"
        );
    }
    info!(vehicle = v.brain.id, off_target = v.brain.off_target, "mission done, every batch acknowledged");
    session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}
