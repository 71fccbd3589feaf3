//! The watch's one event loop: joins the mission over Zenoh like any client (the observer role
//! under the secure configs), feeds what it hears into the [`View`], and publishes a fresh
//! [`Snapshot`] for the pages after each change (at most [`PUSH_EVERY`] apart).

use crate::http::{self, Snapshot};
use crate::state::{Geo, View};
use anyhow::Context as _;
use fleet_math::grid::Grid;
use fleet_math::process::frames::Frames;
use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::{keys::Keys, Body, Context};
use fleet_net::Role;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tracing::{info, warn};

/// Pushes to the pages are coalesced to at most one per this interval.
pub const PUSH_EVERY: Duration = Duration::from_millis(250);

#[derive(clap::Parser, Debug)]
#[command(
    name = "fleet-watch",
    version,
    about = "hetfleet's live operations view: joins a mission over Zenoh and serves it to a browser"
)]
pub struct Args {
    #[command(flatten)]
    pub node: fleet_net::NodeArgs,
    /// Where to serve the page (loopback unless told otherwise).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub http: SocketAddr,
    /// `user:password` the page asks for (HTTP Basic). Required when `--http` is not loopback.
    /// Or a file holding it: `--credential @path`.
    #[arg(long)]
    pub credential: Option<String>,
    /// Also serve the mission to Foxglove here (its WebSocket protocol; e.g. 127.0.0.1:8765):
    /// the vehicles, the site, the plans, the fields and the counters, on the channels a
    /// recording has. Behind `--credential` as the page is; a non-loopback address needs one.
    #[arg(long)]
    pub foxglove: Option<SocketAddr>,
    /// A run directory (`fleet up --out`): the page offers its report.md once it exists.
    #[arg(long)]
    pub run_dir: Option<std::path::PathBuf>,
}

/// The credential from `--credential` (inline or `@file`), checked against the bind address.
fn credential(args: &Args) -> anyhow::Result<Option<String>> {
    let c = match &args.credential {
        None => None,
        Some(c) => Some(match c.strip_prefix('@') {
            Some(path) => std::fs::read_to_string(path)
                .with_context(|| format!("--credential: reading {path}"))
                .map_err(fleet_exit::bad_input)?
                .trim()
                .to_string(),
            None => c.clone(),
        }),
    };
    if let Some(c) = &c {
        if !c.contains(':') || c.starts_with(':') || c.ends_with(':') {
            return Err(fleet_exit::bad_input(anyhow::anyhow!(
                "--credential: expected user:password"
            )));
        }
    }
    if c.is_none() && !args.http.ip().is_loopback() {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "--http {}: a non-loopback address needs \
            --credential user:password (the page is readable by anyone who can reach it)",
            args.http
        )));
    }
    if let Some(addr) = args.foxglove.filter(|a| c.is_none() && !a.ip().is_loopback()) {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "--foxglove {addr}: a non-loopback address needs \
            --credential user:password (the mission is readable by anyone who can reach it)"
        )));
    }
    Ok(c)
}

/// The view of the mission before anything is heard: the site on the Earth, the roster, the
/// link lease, the truth when there is one; and the context messages are checked against.
fn view_of(mission: &MissionConfig, grid: Grid, truth: Option<Arc<Frames>>) -> (View, Context) {
    let site = mission.mavlink.site(&grid);
    let ne = site.map_of(&site.ned_of((grid.width_m(), grid.height_m()), 0.0));
    let geo = Geo {
        south_west: [mission.mavlink.origin[0], mission.mavlink.origin[1]],
        north_east: [ne.0, ne.1],
        size_m: [grid.width_m() * site.scale.x, grid.height_m() * site.scale.y],
    };
    let specs: Vec<_> = mission.vehicles().into_iter().map(|v| (v.id, v.kind)).collect();
    let lease_s = mission.network.lease_ms.unwrap_or(10_000) as f64 / 1000.0;
    let mut ctx = Context::new(grid);
    ctx.vehicles = specs.iter().map(|(id, _)| id.clone()).collect();
    let view = View::new(&mission.mission, grid, geo, lease_s, &specs, truth).with_clock(mission.clock());
    (view, ctx)
}

/// The pages' server, on its own task.
async fn serve_http(
    args: &Args,
    view: Arc<Mutex<View>>,
    snapshots: tokio::sync::watch::Receiver<Arc<Snapshot>>,
    credential: Option<String>,
) -> anyhow::Result<tokio::task::JoinHandle<std::io::Result<()>>> {
    let listener = tokio::net::TcpListener::bind(args.http)
        .await
        .with_context(|| format!("--http {}: cannot listen there", args.http))
        .map_err(fleet_exit::bad_input)?;
    let app = http::router(http::Shared {
        view,
        snapshots,
        credential,
        run_dir: args.run_dir.clone(),
    });
    info!(url = %format!("http://{}/", listener.local_addr()?), "serving the view");
    Ok(tokio::spawn(async move { axum::serve(listener, app).await }))
}

type Samples = fleet_net::zenoh::pubsub::Subscriber<
    fleet_net::zenoh::handlers::FifoChannelHandler<fleet_net::zenoh::sample::Sample>,
>;

/// Where what is heard goes: the view, and Foxglove's channels when served.
#[derive(Clone, Copy)]
struct Sinks<'a> {
    view: &'a Mutex<View>,
    fox: Option<&'a crate::foxglove::FoxLive>,
}

/// What the view listens to: telemetry, models, the server's status, and the links (the
/// vehicles' liveliness tokens: Zenoh drops one when its session says nothing within the
/// link lease).
struct Inputs {
    telemetry: Samples,
    models: Samples,
    status: Samples,
    links: Samples,
}

impl Inputs {
    async fn declare(session: &fleet_net::zenoh::Session, keys: &Keys) -> Result<Self, fleet_net::NetError> {
        let e = fleet_net::NetError::zenoh;
        let links = session
            .liveliness()
            .declare_subscriber(keys.all_alive())
            .history(true)
            .await;
        Ok(Self {
            telemetry: session
                .declare_subscriber(keys.telemetry("*"))
                .await
                .map_err(e("the telemetry"))?,
            models: session
                .declare_subscriber(keys.model_latest())
                .await
                .map_err(e("the models"))?,
            status: session
                .declare_subscriber(keys.server_status())
                .await
                .map_err(e("the status"))?,
            links: links.map_err(e("the liveliness"))?,
        })
    }
}

pub async fn run(args: Args) -> anyhow::Result<()> {
    let credential = credential(&args)?;
    let (mission, truth) = args.node.load()?;
    let (grid, _frames) = mission.workspace(truth.as_ref().map(Frames::shape))?;
    let keys = Keys::new(&mission.mission)?;
    let truth = truth.map(Arc::new);
    let (view, ctx) = view_of(&mission, grid, truth.clone());
    let view = Arc::new(Mutex::new(view));
    let (tx, rx) = tokio::sync::watch::channel(Arc::new(Snapshot::of(&view.lock().expect("view lock"))));
    let fox = match args.foxglove {
        Some(addr) => {
            let fv = fleet_records::foxglove::FoxgloveView::new(&mission, grid, truth.clone());
            Some(crate::foxglove::FoxLive::start(addr, credential.clone(), fv).await?)
        }
        None => None,
    };
    let server = serve_http(&args, view.clone(), rx, credential).await?;
    // A client like any vehicle; under the secure configs, as the observer (read-only).
    let network = mission.network.for_node(fleet_mission::security::OBSERVER);
    let session = fleet_net::open(args.node.zenoh_config(Role::Vehicle, &network, &mission.link)?).await?;
    let inputs = Inputs::declare(&session, &keys).await?;
    let sinks = Sinks {
        view: &view,
        fox: fox.as_ref(),
    };
    follow(&session, &keys, &ctx, sinks, &inputs, &tx).await?;
    server.abort();
    Ok(())
}

/// The mission as it goes, into the view; a snapshot for the pages at most every
/// [`PUSH_EVERY`], when something changed.
async fn follow(
    session: &fleet_net::zenoh::Session,
    keys: &Keys,
    ctx: &Context,
    sinks: Sinks<'_>,
    inputs: &Inputs,
    tx: &tokio::sync::watch::Sender<Arc<Snapshot>>,
) -> anyhow::Result<()> {
    let view = sinks.view;
    let mut stop = fleet_net::StopSignals::new()?;
    let t0 = Instant::now();
    let mut tick = tokio::time::interval(PUSH_EVERY);
    // A page opened mid-mission sees the current model at once: ask for it.
    let mut dirty = ask(session, keys.model_latest(), sinks, ctx).await;
    loop {
        tokio::select! {
            s = inputs.telemetry.recv_async() => if let Ok(s) = s { dirty |= take(sinks, fleet_net::decode(&s, ctx)) },
            s = inputs.status.recv_async() => if let Ok(s) = s {
                let body = fleet_net::decode(&s, ctx);
                let behind = |v: u64| view.lock().expect("view lock").behind(v);
                let missed = matches!(&body, Ok(Body::Status(st)) if behind(st.version));
                dirty |= take(sinks, body);
                // A model put while this view could not hear it (it joined as the mission
                // ended, or its link's lease ran out): no put comes again, so ask for it.
                if missed {
                    dirty |= ask(session, keys.model_latest(), sinks, ctx).await;
                    dirty |= ask_plans(session, keys, ctx, sinks).await;
                }
            },
            s = inputs.models.recv_async() => if let Ok(s) = s {
                // The model is shown at once; its plans follow when the server answers (a
                // server gone away must not hold the view).
                if take(sinks, fleet_net::decode(&s, ctx)) {
                    tx.send_replace(Arc::new(Snapshot::of(&view.lock().expect("view lock"))));
                }
                dirty |= ask_plans(session, keys, ctx, sinks).await;
            },
            s = inputs.links.recv_async() => if let Ok(s) = s {
                if let Some(id) = keys.id_after(s.key_expr().as_str(), "alive") {
                    let alive = s.kind() == fleet_net::zenoh::sample::SampleKind::Put;
                    dirty |= view.lock().expect("view lock").liveliness(&id, alive, t0.elapsed().as_secs_f64());
                }
            },
            _ = tick.tick() => {
                if std::mem::take(&mut dirty) {
                    let snap = Snapshot::of(&view.lock().expect("view lock"));
                    tx.send_replace(Arc::new(snap));
                }
            }
            sig = stop.recv() => {
                info!(signal = sig, "stopping");
                return Ok(());
            }
        }
    }
}

/// The plans that go with a new model: from the epoch after its own (the server answers one
/// vehicle's key at a time). Returns whether the view changed.
async fn ask_plans(session: &fleet_net::zenoh::Session, keys: &Keys, ctx: &Context, sinks: Sinks<'_>) -> bool {
    let next = sinks.view.lock().expect("view lock").state().model.map(|m| m.epoch + 1);
    let Some(next) = next else { return false };
    let asks = ctx
        .vehicles
        .iter()
        .map(|id| ask(session, format!("{}?epoch={next}", keys.plan(id)), sinks, ctx));
    futures_util::future::join_all(asks).await.into_iter().any(|c| c)
}

/// How long the view waits for the server's answer (it is at the base, on the server's side of
/// any radio): a server gone away costs this, not Zenoh's default 10 s a query.
const ASK_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(2);

/// Query `selector` and apply every reply. Returns whether the view changed.
async fn ask(session: &fleet_net::zenoh::Session, selector: String, sinks: Sinks<'_>, ctx: &Context) -> bool {
    let mut changed = false;
    if let Ok(replies) = session.get(selector).timeout(ASK_TIMEOUT).await {
        while let Ok(r) = replies.recv_async().await {
            if let Ok(s) = r.result() {
                changed |= take(sinks, fleet_net::decode(s, ctx));
            }
        }
    }
    changed
}

/// Apply one decoded message; a message that does not decode is counted, never fatal.
fn take(sinks: Sinks<'_>, body: Result<Body, fleet_mission::protocol::ProtocolError>) -> bool {
    if let (Some(fox), Ok(b)) = (sinks.fox, &body) {
        fox.heard(b);
    }
    let mut v = sinks.view.lock().expect("view lock");
    match body {
        Ok(b) => v.apply(b),
        Err(e) => {
            warn!("refused a message: {e}");
            v.refuse();
            true
        }
    }
}
