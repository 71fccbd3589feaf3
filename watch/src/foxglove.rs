//! `--foxglove ADDR`: the mission live in Foxglove. The same channels a recording carries
//! ([`fleet_records::foxglove`]) are served over Foxglove's WebSocket protocol by the Foxglove
//! SDK's own server, as the view hears them.
//!
//! The SDK's server has no authentication, so it listens on an ephemeral loopback port and
//! clients reach it through [`gate`]: our listener on ADDR, which checks the credential on
//! the WebSocket upgrade (HTTP Basic, or `?credential=user:password` in the URL, since a browser
//! cannot set headers on a WebSocket) and then passes the connection through untouched. The SDK
//! names its subprotocol `foxglove.sdk.v1`; clients that offer the protocol's older name,
//! `foxglove.websocket.v1` (the same protocol), are let through under that name.
//!
//! Every channel the mission can have ([`FoxgloveView::channels`]) is made before the gate opens.
//! The SDK (0.30.3) sends a channel's advertisement to a client before it records the channel as
//! advertised to that client, so a client quick to subscribe can be told "unknown channel" and
//! never get it (seen in CI, on a loaded machine). Made at start, the channels reach each client
//! in the advertisement that follows its handshake, not one by one while it is subscribing.

use fleet_mission::protocol::Body;
use fleet_records::foxglove::{FoxChannel, FoxMessage, FoxgloveView};
use foxglove::{ChannelBuilder, Context, RawChannel, Schema};
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tracing::{info, warn};

/// The subprotocol the SDK's server speaks, and the protocol's older name for it.
const SDK_SUBPROTOCOL: &str = "foxglove.sdk.v1";
const OLD_SUBPROTOCOL: &str = "foxglove.websocket.v1";

/// The live Foxglove channels: what the view hears, translated and logged to the SDK's server.
pub struct FoxLive {
    view: FoxgloveView,
    ctx: Arc<Context>,
    channels: Mutex<BTreeMap<String, Arc<RawChannel>>>,
    _server: foxglove::WebSocketServerHandle,
}

impl FoxLive {
    /// Start the SDK's server on loopback and the gate on `addr`.
    pub async fn start(addr: SocketAddr, credential: Option<String>, view: FoxgloveView) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("--foxglove {addr}: cannot listen there ({e})")))?;
        let ctx = Context::new();
        let server = foxglove::WebSocketServer::new()
            .name("hetfleet")
            .context(&ctx)
            .bind("127.0.0.1", 0)
            .start()
            .await?;
        let backend = SocketAddr::from(([127, 0, 0, 1], server.port()));
        let live = Self {
            view,
            ctx,
            channels: Mutex::new(BTreeMap::new()),
            _server: server,
        };
        for FoxChannel {
            topic,
            encoding,
            schema,
        } in live.view.channels()
        {
            live.channel(&topic, &encoding, &schema);
        }
        let now = fleet_records::recording::now_ns();
        for m in live.view.start() {
            live.log(&m, now);
        }
        info!(url = %format!("ws://{}", listener.local_addr()?), "serving Foxglove (WebSocket)");
        tokio::spawn(gate(listener, backend, credential));
        Ok(live)
    }

    /// A message the view heard, on the Foxglove channels (the site again with each model, for
    /// clients that connected since).
    pub fn heard(&self, body: &Body) {
        let now = fleet_records::recording::now_ns();
        if matches!(body, Body::Model(_)) {
            for m in self.view.start() {
                self.log(&m, now);
            }
        }
        for m in self.view.of(body, now) {
            self.log(&m, now);
        }
    }

    fn log(&self, m: &FoxMessage, ns: u64) {
        let c = &m.channel;
        if let Some(channel) = self.channel(&c.topic, &c.encoding, &c.schema) {
            channel.log_with_meta(&m.data, foxglove::PartialMetadata { log_time: Some(ns) });
        }
    }

    /// The channel on `topic`, made the first time (`None`, with a warning, if the SDK refuses it).
    fn channel(&self, topic: &str, encoding: &str, schema: &Schema) -> Option<Arc<RawChannel>> {
        let mut channels = self.channels.lock().expect("channels lock");
        if let Some(made) = channels.get(topic) {
            return Some(made.clone());
        }
        let built = ChannelBuilder::new(topic)
            .message_encoding(encoding)
            .schema(schema.clone())
            .context(&self.ctx)
            .build_raw();
        match built {
            Ok(made) => Some(channels.entry(topic.to_string()).or_insert(made).clone()),
            Err(e) => {
                warn!("Foxglove channel {topic}: {e}");
                None
            }
        }
    }
}

/// Accept clients on `listener`, each checked and passed through to `backend`.
async fn gate(listener: TcpListener, backend: SocketAddr, credential: Option<String>) {
    loop {
        let Ok((client, peer)) = listener.accept().await else {
            continue;
        };
        let credential = credential.clone();
        tokio::spawn(async move {
            if let Err(e) = pass(client, backend, credential.as_deref()).await {
                info!(%peer, "Foxglove client: {e}");
            }
        });
    }
}

/// The longest upgrade request the gate reads.
const MAX_HEAD: usize = 16 * 1024;

/// One client: its upgrade request read and checked, then the connection spliced to `backend`.
async fn pass(mut client: TcpStream, backend: SocketAddr, credential: Option<&str>) -> anyhow::Result<()> {
    let (head, rest) = tokio::time::timeout(std::time::Duration::from_secs(10), read_head(&mut client)).await??;
    if let Some(c) = credential {
        if !authorised(&head, c) {
            client
                .write_all(
                    b"HTTP/1.1 401 Unauthorized\r\nWWW-Authenticate: Basic realm=\"hetfleet\"\r\n\
                    Content-Length: 0\r\nConnection: close\r\n\r\n",
                )
                .await?;
            anyhow::bail!("refused: no valid credential");
        }
    }
    let (head, old_name) = sdk_subprotocol(&head);
    let mut server = TcpStream::connect(backend).await?;
    server.write_all(head.as_bytes()).await?;
    server.write_all(&rest).await?;
    if old_name {
        let (answer, rest) = read_head(&mut server).await?;
        client
            .write_all(answer.replace(SDK_SUBPROTOCOL, OLD_SUBPROTOCOL).as_bytes())
            .await?;
        client.write_all(&rest).await?;
    }
    tokio::io::copy_bidirectional(&mut client, &mut server).await?;
    Ok(())
}

/// An HTTP head (through the blank line), and what came after it.
async fn read_head(s: &mut TcpStream) -> anyhow::Result<(String, Vec<u8>)> {
    let mut buf = vec![];
    let mut chunk = [0u8; 2048];
    loop {
        if let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let rest = buf.split_off(end + 4);
            return Ok((String::from_utf8(buf)?, rest));
        }
        anyhow::ensure!(buf.len() < MAX_HEAD, "an HTTP head over {MAX_HEAD} bytes");
        let n = s.read(&mut chunk).await?;
        anyhow::ensure!(n > 0, "closed before its HTTP head ended");
        buf.extend_from_slice(&chunk[..n]);
    }
}

/// The request offers only the protocol's older name: asked of the SDK by its new one.
fn sdk_subprotocol(head: &str) -> (String, bool) {
    let offers_old = head
        .lines()
        .any(|l| is_header(l, "sec-websocket-protocol") && l.contains(OLD_SUBPROTOCOL));
    let offers_new = head
        .lines()
        .any(|l| is_header(l, "sec-websocket-protocol") && l.contains(SDK_SUBPROTOCOL));
    if offers_old && !offers_new {
        (head.replace(OLD_SUBPROTOCOL, SDK_SUBPROTOCOL), true)
    } else {
        (head.to_string(), false)
    }
}

fn is_header(line: &str, name: &str) -> bool {
    line.split_once(':')
        .is_some_and(|(k, _)| k.trim().eq_ignore_ascii_case(name))
}

/// HTTP Basic in the `Authorization` header, or `credential=user:password` in the query.
fn authorised(head: &str, credential: &str) -> bool {
    let basic = head
        .lines()
        .filter(|l| is_header(l, "authorization"))
        .filter_map(|l| l.split_once(':').map(|(_, v)| v.trim().to_string()))
        .any(|v| crate::http::basic_matches(&v, credential));
    let target = head
        .lines()
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .unwrap_or("");
    let query = target.split_once('?').map_or("", |(_, q)| q);
    let in_query = query
        .split('&')
        .filter_map(|kv| kv.strip_prefix("credential="))
        .any(|v| crate::http::same(percent_decoded(v).as_bytes(), credential.as_bytes()));
    basic || in_query
}

/// `%XX` escapes decoded (a password's `:` or `@` in a URL); anything malformed kept as is.
fn percent_decoded(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = b.get(i + 1..i + 3).and_then(|h| std::str::from_utf8(h).ok());
        match (b[i], hex.and_then(|h| u8::from_str_radix(h, 16).ok())) {
            (b'%', Some(v)) => {
                out.push(v);
                i += 3;
            }
            (c, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEAD: &str = "GET /?credential=ops%3Asecret%40sea HTTP/1.1\r\nHost: x\r\n\
        Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n";

    #[test]
    fn the_credential_is_taken_from_the_query_or_basic_and_nothing_else() {
        assert!(authorised(HEAD, "ops:secret@sea"));
        assert!(!authorised(HEAD, "ops:secret"));
        let basic = "GET / HTTP/1.1\r\nAuthorization: Basic b3BzOnNlY3JldA==\r\n\r\n";
        assert!(authorised(basic, "ops:secret"));
        assert!(!authorised("GET / HTTP/1.1\r\n\r\n", "ops:secret"));
    }

    #[test]
    fn the_older_subprotocol_name_is_asked_of_the_sdk_by_its_new_one() {
        let (head, old) = sdk_subprotocol(HEAD);
        assert!(old && head.contains("Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n"));
        let both = HEAD.replace("foxglove.websocket.v1", "foxglove.websocket.v1, foxglove.sdk.v1");
        assert!(!sdk_subprotocol(&both).1);
    }
}
