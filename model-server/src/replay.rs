//! `model-server --replay <recording.mcap>`: a recorded mission played back onto Zenoh at its
//! recorded pace (times `--speed`), as the model server would have served it, so a live view
//! (`fleet-watch`) can follow it: every recorded message put on its key again, the plans
//! answered to queries from what was recorded by then, and each vehicle's liveliness token
//! declared and dropped as the recorded link events say. The models are a core's, fed the
//! recorded operations as they are played (a lean recording keeps few models; `fleet replay`
//! checks that the core's final one is the recorded one, bit for bit).

use crate::Args;
use fleet_exit::bad_input;
use fleet_mission::events::ServerEvent;
use fleet_mission::protocol::{self, keys::Keys, Body, Context};
use fleet_net::{zenoh, Role};
use fleet_records::recording::{Recording, CORE_TOPIC, EVENTS_TOPIC};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;
use tracing::{info, warn};

type Queries = zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>;

/// A replay on Zenoh: what it answers queries with (the newest model, the plans by vehicle and
/// epoch as recorded), and the liveliness tokens of the vehicles alive now.
struct Replay {
    keys: Keys,
    ctx: Context,
    session: zenoh::Session,
    plans: Queries,
    models: Queries,
    tokens: BTreeMap<fleet_mission::protocol::VehicleId, zenoh::liveliness::LivelinessToken>,
    model: Option<Vec<u8>>,
    plan_replies: BTreeMap<(String, u64), Vec<u8>>,
}

pub async fn run(args: &Args, file: &Path, speed: f64) -> anyhow::Result<()> {
    if !(speed.is_finite() && speed > 0.0) {
        return Err(bad_input(anyhow::anyhow!(
            "--speed {speed}: give a positive factor (1: the recorded pace)"
        )));
    }
    let rec = Recording::read(file).map_err(|e| {
        let bad = e.is_bad_file();
        fleet_exit::bad_input_if(e, bad)
    })?;
    let keys = Keys::new(&rec.mission.mission)?;
    let mut ctx = Context::new(rec.grid);
    ctx.vehicles = rec.mission.vehicles().into_iter().map(|v| v.id).collect();
    let session = fleet_net::open(
        args.node
            .zenoh_config(Role::Server, &rec.mission.network, &rec.mission.link)?,
    )
    .await?;
    let e = fleet_net::NetError::zenoh;
    let plans = session
        .declare_queryable(keys.all_plans())
        .await
        .map_err(e("the plans' queryable"))?;
    let models = session
        .declare_queryable(keys.model_latest())
        .await
        .map_err(e("the model's queryable"))?;
    let _server = session
        .liveliness()
        .declare_token(keys.alive("server"))
        .await
        .map_err(e("the token"))?;
    let mut r = Replay {
        keys,
        ctx,
        session,
        plans,
        models,
        tokens: BTreeMap::new(),
        model: None,
        plan_replies: BTreeMap::new(),
    };
    let first = rec.messages.first().map_or(0, |m| m.log_ns);
    let start = tokio::time::Instant::now();
    let mut stop = fleet_net::StopSignals::new()?;
    info!(recording = %file.display(), messages = rec.messages.len(), speed, "replaying onto Zenoh");
    // The models are the replayed core's, published as its version advances: a lean recording
    // keeps few of them, and `fleet replay` shows the core's are the recorded ones bit for bit.
    let mut replayer = rec.replayer(file).map_err(|e| {
        let bad = e.is_bad_file();
        fleet_exit::bad_input_if(e, bad)
    })?;
    for m in &rec.messages {
        let due = start + Duration::from_nanos(((m.log_ns.saturating_sub(first)) as f64 / speed) as u64);
        if !r.answer_until(due, &mut stop).await {
            return Ok(());
        }
        if m.topic == CORE_TOPIC {
            let before = replayer.core.version;
            replayer.apply(m, &mut |_, _| {})?;
            if replayer.core.version != before {
                r.publish_model(&replayer.core).await;
            }
        } else {
            r.play(m).await?;
        }
    }
    info!("replay done");
    // What was put last is still on its way (the final model to a view behind a small send
    // buffer), and a view asks for that model's plans: a moment more of answering before the
    // session closes and drops what it still holds.
    let _ = r
        .answer_until(tokio::time::Instant::now() + END_LINGER, &mut stop)
        .await;
    fleet_net::close(&r.session).await;
    Ok(())
}

/// How long a replay keeps answering after its last message.
const END_LINGER: Duration = Duration::from_secs(2);

impl Replay {
    /// Answer queries while waiting for a message's time; `false` on a stop signal.
    async fn answer_until(&self, due: tokio::time::Instant, stop: &mut fleet_net::StopSignals) -> bool {
        loop {
            tokio::select! {
                _ = tokio::time::sleep_until(due) => return true,
                q = self.plans.recv_async() => if let Ok(q) = q { answer_plan(&self.keys, &self.plan_replies, q).await },
                q = self.models.recv_async() => if let Ok(q) = q { answer(q, self.model.clone(), "no model yet").await },
                sig = stop.recv() => {
                    info!(signal = sig, "stopping the replay");
                    return false;
                }
            }
        }
    }

    /// The replayed core's model, put on its key and kept to answer queries with.
    async fn publish_model(&mut self, core: &fleet_mission::server::ServerCore) {
        let Some(m) = core.model_update() else { return };
        let bytes = protocol::encode(&Body::Model(m));
        let key = self.keys.model_latest();
        if let Err(e) = self
            .session
            .put(&key, bytes.clone())
            .encoding(fleet_net::encoding())
            .await
        {
            warn!("put on {key}: {e}");
        }
        self.model = Some(bytes);
    }

    /// One recorded message, played: a vehicle's link as a liveliness token, a plan kept to
    /// answer queries with, anything else put on its key.
    async fn play(&mut self, m: &fleet_records::recording::Recorded) -> anyhow::Result<()> {
        match m.topic.as_str() {
            EVENTS_TOPIC => {
                if let Ok(ServerEvent::Link { vehicle, alive }) = serde_json::from_slice(&m.data) {
                    if alive {
                        let t = self.session.liveliness().declare_token(self.keys.alive(&vehicle)).await;
                        let t = t.map_err(fleet_net::NetError::zenoh("declaring the liveliness token"))?;
                        self.tokens.insert(vehicle, t);
                    } else {
                        self.tokens.remove(&vehicle);
                    }
                }
            }
            key if self.keys.id_after(key, "plan").is_some() => {
                if let Ok(Body::Plan(p)) = protocol::decode(&m.data, &self.ctx) {
                    self.plan_replies
                        .insert((p.vehicle.to_string(), p.epoch), m.data.clone());
                }
            }
            // The models are the replayed core's (see `run`).
            key if key == self.keys.model_latest() => {}
            key => {
                if let Err(e) = self
                    .session
                    .put(key, m.data.clone())
                    .encoding(fleet_net::encoding())
                    .await
                {
                    warn!("put on {key}: {e}");
                }
            }
        }
        Ok(())
    }
}

async fn answer_plan(keys: &Keys, replies: &BTreeMap<(String, u64), Vec<u8>>, q: zenoh::query::Query) {
    let key = q.key_expr().as_str().to_string();
    let (id, epoch) = (
        keys.id_after(&key, "plan"),
        q.parameters().get("epoch").and_then(|e| e.parse::<u64>().ok()),
    );
    let found = id.zip(epoch).and_then(|(id, e)| replies.get(&(id, e)).cloned());
    answer(q, found, "no plan recorded for that epoch yet").await;
}

async fn answer(q: zenoh::query::Query, bytes: Option<Vec<u8>>, none: &str) {
    let sent = match bytes {
        Some(b) => q.reply(q.key_expr().clone(), b).encoding(fleet_net::encoding()).await,
        None => q.reply_err(none.as_bytes().to_vec()).await,
    };
    if let Err(e) = sent {
        warn!("replying to {}: {e}", q.key_expr());
    }
}
