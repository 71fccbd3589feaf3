//! The vehicle's loop over the mission's epochs: get the plan of the epoch (asking again when
//! an ack says the model moved on; after `plan_timeout_ms` without an answer, follow the
//! horizon of the plan it holds), sense, publish, and keep every batch until the server's ack
//! covers it (re-sent every `resend_ms`).

use crate::Args;
use fleet::mission::vehicle::VehicleBrain;
use fleet::mission::vehicle_rng;
use fleet::protocol::{self, keys::Keys, Body, Context, LinkState, Telemetry};
use fleet_net::{zenoh, Role};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};
use tracing::{debug, info, warn};
use zenoh::sample::SampleKind;

/// Batches sent and not yet acknowledged, by seq. (Kept in memory here; the durable outbox
/// is its own issue.)
struct Outbox {
    batches: BTreeMap<u64, (Vec<u8>, Instant)>,
    acked: Option<u64>,
}

impl Outbox {
    fn ack(&mut self, seq: u64) {
        if self.acked.is_none_or(|a| seq > a) {
            self.acked = Some(seq);
        }
        self.batches.retain(|&s, _| s > seq);
    }

    fn covers(&self, seq: u64) -> bool {
        self.acked.is_some_and(|a| a >= seq)
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
}

impl Vehicle {
    /// Take what arrived: acks and the server's liveliness. Returns whether an ack came.
    fn absorb(&mut self, acks: &zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>, links: &zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>) -> bool {
        let mut got = false;
        while let Ok(Some(s)) = acks.try_recv() {
            match fleet_net::decode(&s, &self.ctx) {
                Ok(Body::Ack(a)) if a.vehicle == self.brain.id => {
                    self.outbox.ack(a.seq);
                    got = true;
                }
                Ok(_) => warn!("ignored a message on the ack key that is not our ack"),
                Err(e) => warn!("refused an ack: {e}"),
            }
        }
        while let Ok(Some(s)) = links.try_recv() {
            let up = s.kind() == SampleKind::Put;
            if up != self.server_alive {
                info!(server_alive = up, "link to the model server");
            }
            self.server_alive = up;
        }
        got
    }

    async fn resend_due(&mut self, session: &zenoh::Session) {
        let key = self.keys.measurements(&self.brain.id);
        for (seq, (bytes, sent)) in self.outbox.batches.iter_mut() {
            if sent.elapsed() >= self.resend {
                debug!(seq, "re-sending");
                if let Err(e) = session.put(&key, bytes.clone()).encoding(fleet_net::encoding()).await {
                    warn!("re-sending batch {seq}: {e}");
                }
                *sent = Instant::now();
            }
        }
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
            heading: 0.0,
            // A simulated battery: linear drain over the mission.
            battery: (1.0 - 0.5 * self.step as f64 / self.brain.schedule().frames.max(1) as f64).clamp(0.0, 1.0),
            link: if self.server_alive { LinkState::Up } else { LinkState::Down },
            outbox_depth: self.outbox.batches.len() as u64,
        };
        if let Err(e) = fleet_net::put(session, &self.keys.telemetry(&self.brain.id), &Body::Telemetry(t)).await {
            warn!("telemetry: {e}");
        }
    }
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

    let session = fleet_net::open(args.node.zenoh_config(Role::Vehicle, &mission.network)?).await?;
    let _token = session.liveliness().declare_token(keys.alive(&args.id)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let acks = session.declare_subscriber(keys.ack(&args.id)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let links = session.liveliness().declare_subscriber(keys.alive("server")).history(true).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let pace = mission.pace.clone();
    let mut v = Vehicle { keys, ctx, brain, outbox: Outbox { batches: BTreeMap::new(), acked: None }, server_alive: false, resend: Duration::from_millis(pace.resend_ms), step: 0, args };
    info!(vehicle = v.brain.id, ?kind, epochs = schedule.epochs(), "vehicle up");

    let truth_at = |k: usize| -> Vec<f64> { truth.snapshots.col(k).iter().copied().collect() };
    for e in 0..schedule.epochs() {
        if schedule.seq_of(kind, e).is_none() {
            continue;
        }
        // The plan of this epoch: asked when an ack says the model moved, or every 250 ms.
        let deadline = Instant::now() + Duration::from_millis(pace.plan_timeout_ms);
        let mut warned = false;
        loop {
            if v.query_plan(&session, e).await? {
                break;
            }
            if Instant::now() > deadline && v.brain.covers(e) {
                warn!(epoch = e, "no plan from the server in time: following the held plan's horizon");
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
                v.resend_due(&session).await;
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        }
        let steps = schedule.steps_of(e);
        if pace.step_ms > 0 {
            tokio::time::sleep(Duration::from_millis(pace.step_ms * steps.len() as u64)).await;
        }
        v.step = steps.end.saturating_sub(1) as u64;
        if let Some(batch) = v.brain.sense_epoch(e, truth_at)? {
            let bytes = protocol::encode(&Body::Batch(batch.clone()));
            session.put(v.keys.measurements(&v.brain.id), bytes.clone()).encoding(fleet_net::encoding()).await.map_err(|err| anyhow::anyhow!("{err}"))?;
            v.outbox.batches.insert(batch.seq, (bytes, Instant::now()));
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
            anyhow::bail!("{}: batch {last} not acknowledged after {} ms ({} unacknowledged)", v.brain.id, v.args.final_ack_ms, v.outbox.batches.len());
        }
        v.resend_due(&session).await;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    v.telemetry(&session).await;
    info!(vehicle = v.brain.id, off_target = v.brain.off_target, "mission done, every batch acknowledged");
    session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}
