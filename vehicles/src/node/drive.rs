//! An epoch's drive and the plan's query, each a task of its own that reports to the node's
//! loop: the drive sends the autopilot to each sensing place and wakes on the autopilot's
//! changes of state (its position at the rate it reports it), never on a polling timer.

use fleet_mission::grid::Grid;
use fleet_mission::protocol::{AutopilotLink, Body, Context, Plan, Target};
use fleet_mission::vehicle::Fix;
use fleet_net::zenoh;
use std::collections::BTreeMap;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, warn};
use vehicles::bridge::Driver;

/// A guided target on a lossy radio may not arrive: it is sent again this often.
const RESEND_TARGET: Duration = Duration::from_secs(1);
/// The plan from epoch `e`, or none yet, asked on `selector` and waited for up to `timeout`
/// (the server holds the query until the plan exists, if the selector asks it to wait); and
/// the bytes the replies carried.
pub async fn query_plan(
    session: &zenoh::Session,
    selector: &str,
    ctx: &Context,
    e: u64,
    timeout: Duration,
) -> (Option<Plan>, usize) {
    let traffic = fleet_net::Traffic::Plan;
    let get = session
        .get(selector)
        .timeout(timeout)
        .priority(traffic.priority())
        .congestion_control(traffic.congestion());
    let replies = match get.await {
        Ok(r) => r,
        Err(err) => {
            warn!("asking for the plan: {err}");
            return (None, 0);
        }
    };
    let mut bytes = 0;
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => {
                bytes += sample.payload().len();
                match fleet_net::decode(sample, ctx) {
                    Ok(Body::Plan(p)) if p.epoch == e => return (Some(p), bytes),
                    Ok(_) => warn!("a plan reply for another epoch or of another type"),
                    Err(err) => warn!("refused a plan: {err}"),
                }
            }
            Err(err) => {
                bytes += err.payload().len();
                debug!("no plan yet: {}", String::from_utf8_lossy(&err.payload().to_bytes()));
            }
        }
    }
    (None, bytes)
}

/// Where the autopilot was at each sampling step, and how long after the plan the first
/// guided target left (ms).
pub type Drive = (BTreeMap<u64, Fix>, Option<f64>);

/// Drive the autopilot to each place of `targets` and wait (up to the arrival timeout) until
/// it is there; the fixes say where it was. Without an autopilot: none.
pub async fn drive(
    driver: Option<Driver>,
    targets: Vec<Target>,
    grid: Grid,
    timeout: Duration,
    mut plan_at: Option<std::time::Instant>,
) -> Drive {
    let (mut fixes, mut guided) = (BTreeMap::new(), None);
    let Some(mut b) = driver else { return (fixes, guided) };
    for t in targets.iter().filter(|t| !t.cells.is_empty()) {
        let goal = (t.position[0], t.position[1]);
        let deadline = Instant::now() + timeout;
        // Still being armed and set to GUIDED (the first epoch): wait for it.
        while b.link() == AutopilotLink::Connecting && Instant::now() < deadline {
            if !wake(&mut b, deadline).await {
                break;
            }
        }
        let mut sent: Option<Instant> = None;
        while !b.arrived(goal) && Instant::now() < deadline && b.drivable() {
            // Again every second (and at once at a corner of a way routed round the fence).
            if sent.is_none_or(|s| s.elapsed() >= RESEND_TARGET) || b.at_corner() {
                if b.goto(goal) {
                    if let Some(t) = plan_at.take() {
                        guided = Some(t.elapsed().as_secs_f64() * 1e3);
                    }
                }
                sent = Some(Instant::now());
            }
            let due = sent.map_or(deadline, |s| (s + RESEND_TARGET).min(deadline));
            if !wake(&mut b, due).await {
                break;
            }
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

/// Until the autopilot's state changes or `until`, whichever is first; `false` when the bridge
/// has stopped.
async fn wake(b: &mut Driver, until: Instant) -> bool {
    tokio::select! {
        alive = b.changed() => alive,
        _ = tokio::time::sleep_until(until) => true,
    }
}
