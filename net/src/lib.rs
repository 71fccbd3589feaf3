//! hetfleet's Zenoh glue, shared by the model server and the vehicle nodes: open a session in
//! the role a node plays (DESIGN.md "Facts about the dependencies": the server is a router,
//! vehicles are clients that keep retrying), and put or read [`fleet_mission::protocol`] messages with
//! the protocol's encoding; the durable state ([`store`], and a vehicle's [`outbox`] over it). Nothing
//! here knows the math; nodes stay thin.

use fleet_mission::config::{ConfigError, Link, Network};
use fleet_mission::protocol::{self, Body, Context, ProtocolError, ENCODING};
use std::path::Path;
use zenoh::bytes::Encoding;
use zenoh::sample::Sample;
use zenoh::Session;

pub mod outbox;
pub mod rto;
pub mod store;

pub use zenoh;

/// What can go wrong on the network side of a node. Zenoh's own errors are opaque (a boxed
/// error without a source chain), so they are kept as their message, with what was being done.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// A Zenoh JSON5 file that Zenoh refuses (bad input: the operator's file).
    #[error("the Zenoh config {}", path.display())]
    ConfigFile {
        path: std::path::PathBuf,
        #[source]
        source: fleet_exit::BadInput,
    },
    /// A setting we derive that Zenoh refuses.
    #[error("Zenoh config {key} = {value}: {reason}")]
    ConfigKey { key: String, value: String, reason: String },
    /// Something Zenoh was asked to do: open a session, declare a subscriber, a token or a
    /// queryable, put, close.
    #[error("{what}: {reason}")]
    Zenoh { what: String, reason: String },
    /// The mission file (bad input).
    #[error("{0}")]
    Mission(#[source] ConfigError),
    /// A node's `--truth` (bad input).
    #[error("--truth {}", path.display())]
    Truth {
        path: std::path::PathBuf,
        #[source]
        source: fleet_exit::BadInput,
    },
    /// The mission's own truth could not be made.
    #[error("the mission's truth: {0}")]
    MissionTruth(#[source] fleet_math::process::truth::TruthError),
    #[error("{what}: {source}")]
    Io {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
}

impl NetError {
    /// A Zenoh error, with what was being done: `.map_err(NetError::zenoh("declaring ..."))`.
    pub fn zenoh(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> NetError {
        let what = what.into();
        move |e| NetError::Zenoh {
            what,
            reason: e.to_string(),
        }
    }
}

/// What a node is on the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The model server: a Zenoh router listening on the mission's endpoints, so vehicles on
    /// other hosts reach it directly (no separate `zenohd` needed).
    Server,
    /// A vehicle: a client connecting to the server or a router, retrying forever when the
    /// link is down instead of exiting.
    Vehicle,
}

/// Endpoints given on a node's command line, which replace the mission file's.
#[derive(Debug, Clone, Default)]
pub struct Endpoints {
    pub listen: Vec<String>,
    pub connect: Vec<String>,
}

fn json_list(v: &[String]) -> String {
    serde_json::to_string(v).expect("a list of strings serialises")
}

/// Transport settings for links that may be radios (unless a JSON5 file says otherwise), from
/// the mission's `[link]`. A TCP socket's own send buffer is first in, first out and, by
/// Linux's default, holds tens of seconds of a 64 kbit/s radio: what Zenoh wrote into it waits
/// there whatever its priority (an ack behind a minute of ground-station MAVLink, a keep-alive
/// behind both), and a session whose keep-alives wait longer than its lease is declared lost.
/// So the send buffer holds about a second of the link (between 4 and 16 kB asked; Linux
/// doubles it; on loopback or a LAN, round trips of a millisecond, it still carries megabytes a
/// second) and the queue stays in Zenoh's own queues, where priorities order it and droppable
/// messages are dropped; and the lease is at least four times what that buffer takes to drain
/// (Zenoh's 10 s at 64 kbit/s, 27 s at 9.6), so a slow link is slow, not down. A blocking
/// message (a batch) may wait a minute for room before the session is closed, rather than
/// Zenoh's 5 s: on a radio a backlog takes that long to drain, and closing the session would
/// only start it over.
fn radio_transport(link: &Link) -> [(&'static str, String); 3] {
    let bytes_per_s = link.rate_kbps * 1000.0 / 8.0;
    let sndbuf = bytes_per_s.clamp(4096.0, 16384.0);
    let drain_s = 2.0 * sndbuf / bytes_per_s;
    let lease_ms = (4.0 * drain_s * 1000.0).max(10_000.0);
    [
        ("transport/link/tcp/so_sndbuf", format!("{}", sndbuf as u64)),
        ("transport/link/tx/lease", format!("{}", lease_ms.ceil() as u64)),
        (
            "transport/link/tx/queue/congestion_control/block/wait_before_close",
            "60000000".into(),
        ),
    ]
}

/// The link lease a configuration sets (Zenoh's 10 s if it sets none): how long a silent link
/// lasts before it counts as lost.
pub fn lease(cfg: &zenoh::Config) -> std::time::Duration {
    let ms = cfg
        .get_json("transport/link/tx/lease")
        .ok()
        .and_then(|j| j.trim_matches('"').parse::<u64>().ok())
        .unwrap_or(10_000);
    std::time::Duration::from_millis(ms)
}

/// The Zenoh configuration of a node: its role's JSON5 file (from the command line or the
/// mission, if any), then the role's mode (the server a router, vehicles clients that retry
/// forever) and endpoints.
pub fn config(
    role: Role,
    net: &Network,
    link: &Link,
    base: Option<&Path>,
    cli: &Endpoints,
) -> Result<zenoh::Config, NetError> {
    let file = base.map(Path::to_path_buf).or_else(|| match role {
        Role::Server => net.server_config.clone(),
        Role::Vehicle => net.vehicle_config.clone(),
    });
    let mut cfg = match &file {
        Some(p) => zenoh::Config::from_file(p).map_err(|e| NetError::ConfigFile {
            path: p.clone(),
            source: fleet_exit::BadInput(anyhow::anyhow!("{e}")),
        })?,
        None => zenoh::Config::default(),
    };
    let set = |cfg: &mut zenoh::Config, key: &str, value: &str| {
        cfg.insert_json5(key, value).map_err(|e| NetError::ConfigKey {
            key: key.into(),
            value: value.into(),
            reason: e.to_string(),
        })
    };
    // No multicast scouting: a fleet finds its router by its endpoints, and a shared network
    // must not see our nodes join its peers.
    set(&mut cfg, "scouting/multicast/enabled", "false")?;
    // Endpoints: the command line's, else the JSON5 file's, else the mission's.
    let pick = |cfg: &zenoh::Config, key: &str, cli: &[String], mission: &[String]| -> Option<String> {
        if !cli.is_empty() {
            return Some(json_list(cli));
        }
        let in_file = file.is_some() && cfg.get_json(key).is_ok_and(|j| j.contains("/"));
        (!in_file && !mission.is_empty()).then(|| json_list(mission))
    };
    let (mode, listen, connect) = match role {
        Role::Server => (
            "\"router\"",
            pick(&cfg, "listen/endpoints", &cli.listen, &net.listen),
            pick(&cfg, "connect/endpoints", &cli.connect, &[]),
        ),
        Role::Vehicle => (
            "\"client\"",
            None,
            pick(&cfg, "connect/endpoints", &cli.connect, &net.connect),
        ),
    };
    set(&mut cfg, "mode", mode)?;
    if let Some(l) = listen {
        set(&mut cfg, "listen/endpoints", &l)?;
    }
    if let Some(c) = connect {
        set(&mut cfg, "connect/endpoints", &c)?;
    }
    if file.is_none() {
        for (key, value) in radio_transport(link) {
            set(&mut cfg, key, &value)?;
        }
    }
    if let Some(lease) = net.lease_ms {
        set(&mut cfg, "transport/link/tx/lease", &lease.to_string())?;
    }
    if role == Role::Vehicle {
        set(&mut cfg, "connect/timeout_ms", "-1")?;
        set(&mut cfg, "connect/exit_on_failure", "false")?;
        // Back on the link within a second of the radio returning (Zenoh's default backs off
        // to 4 s between attempts), unless a config file says otherwise.
        if file.is_none() {
            set(
                &mut cfg,
                "connect/retry",
                "{ period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2 }",
            )?;
        }
    }
    Ok(cfg)
}

/// Open a session.
pub async fn open(cfg: zenoh::Config) -> Result<Session, NetError> {
    zenoh::open(cfg)
        .await
        .map_err(NetError::zenoh("opening the Zenoh session"))
}

/// How long closing a session may take before the node goes without it.
pub const CLOSE_WITHIN: std::time::Duration = std::time::Duration::from_secs(5);

/// Close a session, within [`CLOSE_WITHIN`]: what a node had to say is said by then (its
/// acknowledgements are in), and a close that waits on a peer that went away (a link just cut)
/// must not keep the process from exiting. A close that fails is no failure of the node either:
/// Zenoh's own close gives up on a peer behind a slow, lossy link (it timed out on a 9.6 kbit/s
/// radio at 5% loss, after every batch of the mission had been acknowledged). Past the bound,
/// or on such an error, the node goes on, with a warning naming it: so nothing is returned.
pub async fn close(session: &Session) {
    if let Some(why) = unclean_close(std::future::IntoFuture::into_future(session.close()), CLOSE_WITHIN).await {
        tracing::warn!(%why, "the Zenoh session did not close cleanly: leaving it");
    }
}

/// Why a close did not end cleanly within `bound` (its error, or the bound passed), or `None`
/// when it did: [`close`]'s verdict, apart from the session so that a test can hand it a close
/// that fails.
async fn unclean_close<E: std::fmt::Display>(
    close: impl std::future::Future<Output = Result<(), E>>,
    bound: std::time::Duration,
) -> Option<String> {
    match tokio::time::timeout(bound, close).await {
        Ok(Ok(())) => None,
        Ok(Err(e)) => Some(e.to_string()),
        Err(_) => Some(format!("not closed within {} s", bound.as_secs_f64())),
    }
}

/// The protocol's encoding, as Zenoh carries it.
pub fn encoding() -> Encoding {
    Encoding::from(ENCODING)
}

/// What a message is to the link it crosses: how urgent, and whether Zenoh may drop it when
/// the link is congested. On a thin radio the mission's own data (batches, their acks, plans)
/// goes first and is never dropped; what is only a view (telemetry, the server's status, the
/// ground stations' MAVLink) goes after it and is dropped rather than queued behind it.
/// Liveliness is Zenoh's own control traffic, above all of these.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Traffic {
    /// A measurement batch (also kept in the outbox until acknowledged).
    Batch,
    /// An acknowledgement of batches.
    Ack,
    /// A plan query and its reply.
    Plan,
    /// The model update, for observers at the base.
    Model,
    /// A vehicle's telemetry, the server's status.
    Telemetry,
    /// MAVLink frames between an autopilot and the ground stations.
    Mavlink,
}

impl Traffic {
    pub fn priority(self) -> zenoh::qos::Priority {
        use zenoh::qos::Priority;
        match self {
            Self::Plan => Priority::InteractiveHigh,
            Self::Ack | Self::Batch => Priority::DataHigh,
            Self::Model => Priority::Data,
            Self::Telemetry => Priority::DataLow,
            Self::Mavlink => Priority::Background,
        }
    }

    pub fn congestion(self) -> zenoh::qos::CongestionControl {
        use zenoh::qos::CongestionControl;
        match self {
            Self::Plan | Self::Ack | Self::Batch | Self::Model => CongestionControl::Block,
            Self::Telemetry | Self::Mavlink => CongestionControl::Drop,
        }
    }

    /// The class of a protocol message.
    pub fn of(body: &Body) -> Self {
        match body {
            Body::Batch(_) => Self::Batch,
            Body::Ack(_) => Self::Ack,
            Body::Plan(_) => Self::Plan,
            Body::Model(_) => Self::Model,
            _ => Self::Telemetry,
        }
    }
}

/// Put one message on `key`, with its class's priority and congestion control.
pub async fn put(session: &Session, key: &str, body: &Body) -> Result<(), NetError> {
    put_bytes(session, key, protocol::encode(body), Traffic::of(body)).await
}

/// Put encoded bytes on `key` as `traffic`.
pub async fn put_bytes(session: &Session, key: &str, bytes: Vec<u8>, traffic: Traffic) -> Result<(), NetError> {
    let put = session
        .put(key, bytes)
        .priority(traffic.priority())
        .congestion_control(traffic.congestion());
    let put = if traffic == Traffic::Mavlink {
        put
    } else {
        put.encoding(encoding())
    };
    put.await.map_err(NetError::zenoh(format!("put on {key}")))
}

/// Decode and validate a received sample (refusing oversized payloads before copying them).
pub fn decode(sample: &Sample, ctx: &Context) -> Result<Body, ProtocolError> {
    let payload = sample.payload();
    if payload.len() > ctx.max_payload {
        return Err(ProtocolError::TooLarge {
            size: payload.len(),
            limit: ctx.max_payload,
        });
    }
    protocol::decode(&payload.to_bytes(), ctx)
}

/// Set-up every node does first: the linear algebra's threads as the `fleet` binary sets them
/// (so a node computes bit for bit what the offline loop computes), and logging: `RUST_LOG`
/// (default `info`) to stderr, plus [`session_refusals`]'s watch on Zenoh's handshakes.
pub fn init_node() {
    use tracing_subscriber::layer::SubscriberExt as _;
    use tracing_subscriber::util::SubscriberInitExt as _;
    use tracing_subscriber::Layer as _;
    fleet_math::configure_linalg_threads();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,zenoh=warn"));
    // Colour only on a terminal: a log file gets plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let fmt = tracing_subscriber::fmt::layer()
        .with_ansi(ansi)
        .with_writer(std::io::stderr)
        .with_filter(filter);
    let watch = SessionWatch.with_filter(
        tracing_subscriber::filter::Targets::new()
            .with_target("zenoh_transport::unicast::establishment", tracing::Level::DEBUG),
    );
    let _ = tracing_subscriber::registry().with(fmt).with(watch).try_init();
}

/// A session refused at Zenoh's handshake, as Zenoh reports it to its own log (it tells no
/// one else): on a router, a client's credentials were wrong; on a client, the router closed
/// its session as invalid.
#[derive(Debug, Clone, PartialEq)]
pub enum SessionRefusal {
    /// (Router side.) A client gave a password that does not match its user's.
    InvalidPassword,
    /// (Router side.) A client gave a user the dictionary does not have.
    UnknownUser,
    /// (Router side.) A client gave no credentials where they are required.
    NoCredentials,
    /// (Client side.) The router closed this session's handshake after it sent its
    /// credentials (Zenoh 1.10 says "reason GENERIC" for a wrong password).
    RefusedByRouter,
}

static REFUSALS: std::sync::Mutex<Vec<SessionRefusal>> = std::sync::Mutex::new(Vec::new());

/// The session refusals seen since the last call.
pub fn session_refusals() -> Vec<SessionRefusal> {
    std::mem::take(&mut *REFUSALS.lock().unwrap_or_else(|p| p.into_inner()))
}

/// Reads Zenoh's handshake events (debug level on the router side, error on the client side)
/// for the refusals above; never prints anything itself.
struct SessionWatch;

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for SessionWatch {
    fn on_event(&self, event: &tracing::Event<'_>, _: tracing_subscriber::layer::Context<'_, S>) {
        struct Message(String);
        impl tracing::field::Visit for Message {
            fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
                if field.name() == "message" {
                    self.0 = format!("{value:?}");
                }
            }
        }
        let mut m = Message(String::new());
        event.record(&mut m);
        let r = if m.0.contains("UsrPwd extension - Recv OpenSyn. Invalid password") {
            SessionRefusal::InvalidPassword
        } else if m.0.contains("UsrPwd extension - Recv OpenSyn. Invalid user") {
            SessionRefusal::UnknownUser
        } else if m.0.contains("UsrPwd extension - Recv OpenSyn. Expected extension")
            || m.0.contains("UsrPwd extension - Recv InitSyn. Expected extension")
        {
            SessionRefusal::NoCredentials
        } else if m.0.contains("Received a close message (reason")
            && m.0.contains("in response to an OpenSyn")
            && !m.0.contains("MAX_LINKS")
        {
            SessionRefusal::RefusedByRouter
        } else {
            return;
        };
        REFUSALS.lock().unwrap_or_else(|p| p.into_inner()).push(r);
    }
}

/// Refusals of this client's session since it was last known connected.
static REFUSED_SINCE_CONNECTED: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

/// A client node says it is connected (it heard the server): earlier refusals were passing.
pub fn mark_connected() {
    REFUSED_SINCE_CONNECTED.store(0, std::sync::atomic::Ordering::Relaxed);
}

/// A client node's watch for a router that refuses its credentials: they never fix
/// themselves, so instead of retrying forever on a generic close the node says so (naming the
/// user and its config file) and exits as bad input. Armed only for a node with credentials;
/// three refusals with no connection between them (Zenoh also closes a handshake as invalid
/// when a link breaks mid-way, which a retry gets past).
pub fn exit_when_refused(node: &'static str, cfg: &zenoh::Config, file: Option<std::path::PathBuf>) {
    use std::sync::atomic::Ordering;
    let user = cfg
        .get_json("transport/auth/usrpwd/user")
        .ok()
        .map(|u| u.trim_matches('"').to_string())
        .filter(|u| !u.is_empty() && u != "null");
    let Some(user) = user else { return };
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            let refused = session_refusals()
                .iter()
                .filter(|r| **r == SessionRefusal::RefusedByRouter)
                .count() as u32;
            if REFUSED_SINCE_CONNECTED.fetch_add(refused, Ordering::Relaxed) + refused >= 3 {
                let from = file
                    .as_ref()
                    .map_or_else(String::new, |f| format!(" of {}", f.display()));
                let e = fleet_exit::bad_input(anyhow::anyhow!(
                    "the router refused this node's session 3 \
                    times after it sent its credentials (user {user:?}{from}): a wrong password, a user it does not \
                    know, or a certificate it does not accept; fix the credentials and start it again"
                ));
                fleet_exit::fail(node, &e);
            }
        }
    });
}

/// Command-line options every node takes.
#[derive(Debug, Clone, clap::Args)]
pub struct NodeArgs {
    /// The mission file (default: the bundled default mission).
    #[arg(long)]
    pub mission: Option<std::path::PathBuf>,
    /// The mixed-reality truth as .npy (default: generate it from the mission's [truth]).
    #[arg(long)]
    pub truth: Option<std::path::PathBuf>,
    /// Zenoh endpoints to listen on (server) instead of the mission's.
    #[arg(long)]
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to instead of the mission's.
    #[arg(long)]
    pub connect: Vec<String>,
    /// A Zenoh JSON5 config file applied before the endpoints (TLS, auth, tuning).
    #[arg(long)]
    pub zenoh_config: Option<std::path::PathBuf>,
}

impl NodeArgs {
    /// The mission and its truth on the model grid (`--truth`, else the mission's `[truth]`;
    /// `None`: a mission in the field, without one). A `--truth` file is read a frame at a time
    /// as the node asks for one ([`Frames`](fleet_math::process::frames::Frames)), after a
    /// check of the whole file; a truth made here (the simulator) is held in memory.
    pub fn load(
        &self,
    ) -> Result<
        (
            fleet_mission::config::MissionConfig,
            Option<fleet_math::process::frames::Frames>,
        ),
        NetError,
    > {
        use fleet_math::process::frames::Frames;
        let mut mission =
            fleet_mission::config::MissionConfig::load(self.mission.as_deref()).map_err(NetError::Mission)?;
        let truth = match &self.truth {
            Some(p) => {
                // The time between frames from the sidecar `fleet up` and `fleet simulate` write.
                let dt = fleet_math::process::dataset::sidecar_dt(p).unwrap_or(1.0);
                let t = Frames::open_npy(p, dt).map_err(|e| NetError::Truth {
                    path: p.clone(),
                    source: fleet_exit::BadInput(e.into()),
                })?;
                mission.check_truth(t.shape(), p).map_err(NetError::Mission)?;
                Some(t)
            }
            None => mission
                .truth(|_| {})
                .map_err(NetError::MissionTruth)?
                .map(Frames::in_memory),
        };
        mission.adopt_land(truth.as_ref().map_or_else(Vec::new, |t| t.land().to_vec()));
        Ok((mission, truth))
    }

    pub fn endpoints(&self) -> Endpoints {
        Endpoints {
            listen: self.listen.clone(),
            connect: self.connect.clone(),
        }
    }

    /// This node's Zenoh configuration.
    pub fn zenoh_config(&self, role: Role, net: &Network, link: &Link) -> Result<zenoh::Config, NetError> {
        config(role, net, link, self.zenoh_config.as_deref(), &self.endpoints())
    }

    /// The Zenoh JSON5 file this node's configuration starts from, if any.
    pub fn zenoh_file(&self, role: Role, net: &Network) -> Option<std::path::PathBuf> {
        self.zenoh_config.clone().or_else(|| match role {
            Role::Server => net.server_config.clone(),
            Role::Vehicle => net.vehicle_config.clone(),
        })
    }
}

/// The stop signals a node obeys (SIGTERM, SIGINT, SIGHUP), registered once so none is
/// missed between two polls of an event loop.
pub struct StopSignals {
    term: tokio::signal::unix::Signal,
    int: tokio::signal::unix::Signal,
    hup: tokio::signal::unix::Signal,
}

impl StopSignals {
    pub fn new() -> Result<Self, NetError> {
        use tokio::signal::unix::{signal, SignalKind};
        let io = |source| NetError::Io {
            what: "registering the stop signals",
            source,
        };
        Ok(Self {
            term: signal(SignalKind::terminate()).map_err(io)?,
            int: signal(SignalKind::interrupt()).map_err(io)?,
            hup: signal(SignalKind::hangup()).map_err(io)?,
        })
    }

    /// The next stop signal's name.
    pub async fn recv(&mut self) -> &'static str {
        tokio::select! {
            _ = self.term.recv() => "SIGTERM",
            _ = self.int.recv() => "SIGINT",
            _ = self.hup.recv() => "SIGHUP",
        }
    }
}

/// Run a node's async main on a multi-threaded runtime (Zenoh refuses the current-thread
/// one) after [`init_node`]; an error is one line on stderr and the exit status of
/// [`fleet_exit`] (2 bad input, 1 internal).
pub fn run_node<F: std::future::Future<Output = anyhow::Result<()>>>(name: &str, workers: usize, main: F) {
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .worker_threads(workers)
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => fleet_exit::fail(name, &anyhow::Error::new(e).context("starting the runtime")),
    };
    let result = rt.block_on(main);
    // Do not wait for blocking readers (a MAVLink socket) to notice the end.
    rt.shutdown_timeout(std::time::Duration::from_millis(200));
    if let Err(e) = result {
        fleet_exit::fail(name, &e);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A close that fails (Zenoh's own "close operation timed out!" on a 9.6 kbit/s radio,
    /// which once made a boat exit 1 after every batch was acknowledged) or that hangs is
    /// named, never an error of the node; one that ends cleanly says nothing.
    #[test]
    fn a_close_that_fails_or_hangs_is_named_not_fatal() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap();
        let bound = std::time::Duration::from_millis(50);
        let failed = async { Err::<(), _>("close operation timed out!") };
        assert_eq!(
            rt.block_on(unclean_close(failed, bound)).as_deref(),
            Some("close operation timed out!")
        );
        let hangs = std::future::pending::<Result<(), String>>();
        assert_eq!(
            rt.block_on(unclean_close(hangs, bound)).as_deref(),
            Some("not closed within 0.05 s")
        );
        assert_eq!(rt.block_on(unclean_close(async { Ok::<(), String>(()) }, bound)), None);
    }

    fn root() -> std::path::PathBuf {
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .parent()
            .unwrap()
            .to_path_buf()
    }

    #[test]
    fn a_slow_radio_gets_a_small_send_buffer_and_a_lease_it_can_keep() {
        let radio = |kbps: f64| {
            let link = Link {
                rate_kbps: kbps,
                ..Link::default()
            };
            let c = config(Role::Vehicle, &Network::default(), &link, None, &Endpoints::default()).unwrap();
            let get = |k: &str| c.get_json(k).unwrap().trim_matches('"').parse::<u64>().unwrap();
            (get("transport/link/tcp/so_sndbuf"), get("transport/link/tx/lease"))
        };
        // 64 kbit/s: 8 kB a second asked (16 kB with Linux's doubling, 2 s), Zenoh's 10 s lease.
        assert_eq!(radio(64.0), (8000, 10_000));
        // 9.6 kbit/s: the 4 kB floor, 6.8 s to drain the doubled buffer, four times that.
        assert_eq!(radio(9.6), (4096, 27_307));
        // A LAN: the 16 kB ceiling, Zenoh's lease.
        assert_eq!(radio(100_000.0), (16384, 10_000));
        // What a node reads back as its lease.
        let slow = Link {
            rate_kbps: 9.6,
            ..Link::default()
        };
        let c = config(Role::Vehicle, &Network::default(), &slow, None, &Endpoints::default()).unwrap();
        assert_eq!(lease(&c), std::time::Duration::from_millis(27_307));
        // The mission's own lease wins.
        let net = Network {
            lease_ms: Some(3_000),
            ..Network::default()
        };
        let c = config(Role::Server, &net, &Link::default(), None, &Endpoints::default()).unwrap();
        assert_eq!(c.get_json("transport/link/tx/lease").unwrap(), "3000");
    }

    #[test]
    fn bundled_zenoh_configs_load_and_endpoints_take_precedence() {
        let net = Network::default();
        for f in [
            "router",
            "client",
            "peer",
            "secure-example/router",
            "secure-example/boat-1",
        ] {
            zenoh::Config::from_file(root().join(format!("config/zenoh/{f}.json5")))
                .unwrap_or_else(|e| panic!("{f}.json5: {e}"));
        }
        let client = root().join("config/zenoh/client.json5");
        // The file's endpoints beat the mission's; the command line's beat both.
        let c = config(
            Role::Vehicle,
            &net,
            &Link::default(),
            Some(&client),
            &Endpoints::default(),
        )
        .unwrap();
        assert!(c.get_json("connect/endpoints").unwrap().contains("192.0.2.10"));
        assert!(c.get_json("mode").unwrap().contains("client"));
        let c = config(
            Role::Vehicle,
            &net,
            &Link::default(),
            Some(&client),
            &Endpoints {
                listen: vec![],
                connect: vec!["tcp/10.0.0.1:7000".into()],
            },
        )
        .unwrap();
        assert!(c.get_json("connect/endpoints").unwrap().contains("10.0.0.1"));
        let c = config(Role::Server, &net, &Link::default(), None, &Endpoints::default()).unwrap();
        assert!(c.get_json("listen/endpoints").unwrap().contains("127.0.0.1:7447"));
        assert!(c.get_json("mode").unwrap().contains("router"));
        assert!(config(
            Role::Server,
            &net,
            &Link::default(),
            Some(Path::new("/nonexistent.json5")),
            &Endpoints::default()
        )
        .is_err());
    }
}
