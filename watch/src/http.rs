//! The page and its API, read-only: `GET /` (the page, every asset inside the binary),
//! `GET /api/state` (JSON), `GET /api/events` (server-sent events: `state` on every change,
//! `fields` when the model changes, `plans` when they do), `GET /api/estimate.npy` and `/api/variance.npy`, and
//! `GET /api/report.md` (the finished run's report). Anything else is a 4xx.

use crate::state::View;
use axum::extract::State;
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use futures_util::stream::{self, Stream};
use npyz::WriterBuilder;
use std::convert::Infallible;
use std::sync::{Arc, Mutex};
use tokio::sync::watch;

const PAGE: &str = include_str!("../assets/index.html");

/// The JSON the pages are sent, serialised once per change however many pages are open.
pub struct Snapshot {
    /// The state pages are pushed (without the plans; `/api/state` is serialised on request).
    pub pushed: String,
    /// How many plans the view has taken, and every current plan's JSON.
    pub plans: (u64, String),
    /// The model version the fields are of, and their JSON.
    pub fields: Option<(u64, String)>,
}

impl Snapshot {
    pub fn of(view: &View) -> Self {
        let mut st = view.state();
        st.plans = None;
        let pushed = serde_json::to_string(&st).expect("the state serialises");
        let (taken, plans) = view.plans();
        let plans = (taken, serde_json::to_string(&plans).expect("the plans serialise"));
        let fields = view.fields().map(|f| {
            (
                f.version,
                serde_json::to_string(&FieldsWire::of(f)).expect("the fields serialise"),
            )
        });
        Self { pushed, plans, fields }
    }
}

/// The fields as pushed to pages: little-endian f32, base64 (7 significant digits, more than
/// a colour scale can show; the `.npy` exports keep double): a quarter of the bytes of f64 text.
#[derive(serde::Serialize)]
struct FieldsWire {
    version: u64,
    step: u64,
    rows: usize,
    cols: usize,
    estimate: String,
    variance: String,
    truth: Option<String>,
}

impl FieldsWire {
    fn of(f: &crate::state::Fields) -> Self {
        use base64::Engine as _;
        let packed = |v: &[f64]| {
            base64::engine::general_purpose::STANDARD
                .encode(v.iter().flat_map(|&x| (x as f32).to_le_bytes()).collect::<Vec<u8>>())
        };
        Self {
            version: f.version,
            step: f.step,
            rows: f.rows,
            cols: f.cols,
            estimate: packed(&f.estimate),
            variance: packed(&f.variance),
            truth: f.truth.as_deref().map(packed),
        }
    }
}

#[derive(Clone)]
pub struct Shared {
    pub view: Arc<Mutex<View>>,
    pub snapshots: watch::Receiver<Arc<Snapshot>>,
    /// `user:password` the page requires (HTTP Basic), if any.
    pub credential: Option<String>,
    pub run_dir: Option<std::path::PathBuf>,
}

pub fn router(shared: Shared) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/index.html", get(page))
        .route("/api/state", get(state))
        .route("/api/events", get(events))
        .route("/api/estimate.npy", get(estimate_npy))
        .route("/api/variance.npy", get(variance_npy))
        .route("/api/report.md", get(report))
        .fallback(not_found)
        .layer(axum::middleware::from_fn_with_state(shared.clone(), guard))
        .with_state(shared)
}

/// Read-only, and behind the credential when there is one.
async fn guard(State(s): State<Shared>, req: axum::extract::Request, next: axum::middleware::Next) -> Response {
    if req.method() != Method::GET && req.method() != Method::HEAD {
        return (
            StatusCode::METHOD_NOT_ALLOWED,
            [(header::ALLOW, "GET, HEAD")],
            "read-only\n",
        )
            .into_response();
    }
    if let Some(c) = &s.credential {
        if !authorised(req.headers(), c) {
            return (
                StatusCode::UNAUTHORIZED,
                [(header::WWW_AUTHENTICATE, "Basic realm=\"hetfleet\", charset=\"UTF-8\"")],
                "credential required\n",
            )
                .into_response();
        }
    }
    next.run(req).await
}

fn authorised(headers: &HeaderMap, credential: &str) -> bool {
    headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| basic_matches(v, credential))
}

/// Whether an `Authorization` value is HTTP Basic with exactly `credential` (`user:password`).
pub fn basic_matches(value: &str, credential: &str) -> bool {
    use base64::Engine as _;
    let Some(given) = value.strip_prefix("Basic ") else {
        return false;
    };
    let Ok(decoded) = base64::engine::general_purpose::STANDARD.decode(given.trim()) else {
        return false;
    };
    same(&decoded, credential.as_bytes())
}

/// Length-independent comparison of equal-length inputs: no early exit on the first byte.
pub fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn page() -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        PAGE,
    )
        .into_response()
}

async fn not_found() -> Response {
    (StatusCode::NOT_FOUND, "not found\n").into_response()
}

async fn state(State(s): State<Shared>) -> Response {
    let json = serde_json::to_string(&s.view.lock().expect("view lock").state()).expect("the state serialises");
    ([(header::CONTENT_TYPE, "application/json")], json).into_response()
}

/// Every change as it happens: the current state at once (a page opened mid-mission), then
/// one event per change. A page that falls behind gets the newest state, not a backlog.
async fn events(State(s): State<Shared>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let mut rx = s.snapshots.clone();
    rx.mark_changed();
    let stream = stream::unfold(
        (rx, None::<u64>, None::<u64>),
        |(mut rx, mut sent_version, mut sent_plans)| async move {
            rx.changed().await.ok()?;
            let snap = rx.borrow_and_update().clone();
            let mut events = vec![Ok(Event::default().event("state").data(snap.pushed.clone()))];
            if let Some((v, json)) = &snap.fields {
                if sent_version != Some(*v) {
                    sent_version = Some(*v);
                    events.push(Ok(Event::default().event("fields").data(json.clone())));
                }
            }
            if sent_plans != Some(snap.plans.0) {
                sent_plans = Some(snap.plans.0);
                events.push(Ok(Event::default().event("plans").data(snap.plans.1.clone())));
            }
            Some((stream::iter(events), (rx, sent_version, sent_plans)))
        },
    );
    Sse::new(futures_util::StreamExt::flatten(stream)).keep_alive(KeepAlive::default())
}

fn npy(s: &Shared, pick: fn(&crate::state::Fields) -> &[f64], name: &str) -> Response {
    let view = s.view.lock().expect("view lock");
    let Some(f) = view.fields() else {
        return (StatusCode::NOT_FOUND, "no model yet\n").into_response();
    };
    let bytes = npy_bytes(&[f.rows, f.cols], pick(f));
    let disposition = format!("attachment; filename=\"{name}-v{}.npy\"", f.version);
    (
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_string()),
            (header::CONTENT_DISPOSITION, disposition),
        ],
        bytes,
    )
        .into_response()
}

/// A float64 C-order `.npy` in memory (numpy's own format, written by `npyz`).
pub fn npy_bytes(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let mut out = vec![];
    let mut w = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&shape)
        .writer(&mut out)
        .begin_nd()
        .expect("writing .npy to memory cannot fail");
    w.extend(data.iter().copied())
        .expect("writing .npy to memory cannot fail");
    w.finish().expect("writing .npy to memory cannot fail");
    out
}

async fn estimate_npy(State(s): State<Shared>) -> Response {
    npy(&s, |f| &f.estimate, "estimate")
}

async fn variance_npy(State(s): State<Shared>) -> Response {
    npy(&s, |f| &f.variance, "variance")
}

async fn report(State(s): State<Shared>) -> Response {
    let Some(dir) = &s.run_dir else {
        return (
            StatusCode::NOT_FOUND,
            "no run directory (start the watch with --run-dir)\n",
        )
            .into_response();
    };
    match std::fs::read_to_string(dir.join("report.md")) {
        Ok(md) => ([(header::CONTENT_TYPE, "text/markdown; charset=utf-8")], md).into_response(),
        Err(_) => (StatusCode::NOT_FOUND, "no report yet: the run has not finished\n").into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_npy_export_reads_back_with_its_shape_and_values() {
        let data = [0.0, 1.5, -2.0, 3.0, 4.0, 5e-300];
        let back = fleet_math::npy::from_bytes(&npy_bytes(&[2, 3], &data), "export").unwrap();
        assert_eq!((back.shape, back.data), (vec![2, 3], data.to_vec()));
    }

    #[test]
    fn basic_credentials_are_checked_exactly() {
        use base64::Engine as _;
        let mut h = HeaderMap::new();
        assert!(!authorised(&h, "lead:secret"));
        let enc = |s: &str| format!("Basic {}", base64::engine::general_purpose::STANDARD.encode(s));
        h.insert(header::AUTHORIZATION, enc("lead:secret").parse().unwrap());
        assert!(authorised(&h, "lead:secret"));
        for wrong in ["lead:secreT", "lead:secret2", "lead:", ""] {
            h.insert(header::AUTHORIZATION, enc(wrong).parse().unwrap());
            assert!(!authorised(&h, "lead:secret"), "{wrong}");
        }
        h.insert(header::AUTHORIZATION, "Basic !!!not-base64".parse().unwrap());
        assert!(!authorised(&h, "lead:secret"));
    }
}
