//! An epoch's drive and the plan's query, each a task of its own that reports to the node's
//! loop: the drive sends the autopilot to each sensing place and wakes on the autopilot's
//! changes of state (its position at the rate it reports it), never on a polling timer.

use fleet_math::grid::Grid;
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
/// A vehicle driven this long without coming [`PROGRESS_M`] closer to its target is not
/// following it: an autopilot that refuses a position target says nothing (ArduCopter outside
/// its fence), so the drive stops waiting and the vehicle senses where it is.
const STALL: Duration = Duration::from_secs(10);
const PROGRESS_M: f64 = 0.5;
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
        if b.outside_fence(goal) {
            warn!(
                ?goal,
                "a place outside the site's fence: not sent; the vehicle senses where it is"
            );
        } else {
            follow(&mut b, goal, deadline, &mut plan_at, &mut guided).await;
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

/// Send `goal` (again every second) until the autopilot is there, the deadline, it is no
/// longer ours to drive, or it has not come closer for [`STALL`]; `guided` gets when the
/// first target left after the plan.
async fn follow(
    b: &mut Driver,
    goal: (f64, f64),
    deadline: Instant,
    plan_at: &mut Option<std::time::Instant>,
    guided: &mut Option<f64>,
) {
    let mut sent: Option<Instant> = None;
    // The nearest the vehicle has come (to the leg it drives now) and when it got there.
    let mut closest: Option<(f64, Instant)> = None;
    while !b.arrived(goal) && Instant::now() < deadline && b.drivable() {
        // Again every second (and at once at a corner of a way routed round the fence).
        let corner = b.at_corner();
        if sent.is_none_or(|s| s.elapsed() >= RESEND_TARGET) || corner {
            if b.goto(goal) {
                if let Some(t) = plan_at.take() {
                    *guided = Some(t.elapsed().as_secs_f64() * 1e3);
                }
            }
            sent = Some(Instant::now());
        }
        let to_go = b.to_go(goal);
        closest = match (closest, to_go) {
            (Some((d, _)), Some(now)) if corner || now < d - PROGRESS_M => Some((now, Instant::now())),
            (None, Some(now)) => Some((now, Instant::now())),
            (c, _) => c,
        };
        if let Some((d, since)) = closest.filter(|(_, since)| since.elapsed() >= STALL) {
            warn!(
                ?goal,
                to_go_m = d,
                "the autopilot is not following its target: no closer in {} s; the vehicle senses where it is",
                (Instant::now() - since).as_secs()
            );
            return;
        }
        let due = sent.map_or(deadline, |s| (s + RESEND_TARGET).min(deadline));
        if !wake(b, due).await {
            return;
        }
    }
}

/// Until the autopilot's state changes or `until`, whichever is first; `false` when the bridge
/// has stopped.
async fn wake(b: &mut Driver, until: Instant) -> bool {
    tokio::select! {
        alive = b.changed() => alive,
        _ = tokio::time::sleep_until(until) => true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_mission::config::MavlinkConfig;
    use mavlink::dialects::ardupilotmega::*;
    use mavlink::MavHeader;
    use std::net::UdpSocket;
    use vehicles::autopilot::modes::Frame;
    use vehicles::autopilot::sim::SimSpec;
    use vehicles::bridge::{Bridge, BridgeSpec};
    use vehicles::link::frame_bytes;

    /// An autopilot that shows GUIDED, armed, at one place, and never moves: as ArduCopter
    /// ignoring a position target outside its fence, which it does without an answer.
    fn unmoving_autopilot(ap: UdpSocket, peer: std::net::SocketAddr, at: (f64, f64, f64)) {
        let header = MavHeader {
            system_id: 7,
            component_id: 1,
            sequence: 0,
        };
        let heartbeat = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 15,
            mavtype: MavType::MAV_TYPE_SURFACE_BOAT,
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED,
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        });
        let position = MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            lat: (at.0 * 1e7).round() as i32,
            lon: (at.1 * 1e7).round() as i32,
            hdg: u16::MAX,
            ..Default::default()
        });
        std::thread::spawn(move || {
            for _ in 0..400 {
                for m in [&heartbeat, &position] {
                    let _ = ap.send_to(&frame_bytes(header, m), peer);
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        });
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn a_target_the_autopilot_does_not_follow_is_given_up_long_before_the_timeout() {
        let grid = Grid::new(24, 48, 1.0).unwrap();
        let site = MavlinkConfig::default().site(&grid);
        let ap = UdpSocket::bind("127.0.0.1:0").unwrap();
        ap.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let spec = BridgeSpec {
            ready_timeout: Duration::from_secs(5),
            ..BridgeSpec::plain(SimSpec::from_config(Frame::Boat, 7, site, &MavlinkConfig::default()))
        };
        let bridge = Bridge::connect(&format!("udpout:{}", ap.local_addr().unwrap()), spec, None).unwrap();
        let mut buf = [0u8; 512];
        let (_, peer) = ap.recv_from(&mut buf).expect("the bridge's heartbeat");
        unmoving_autopilot(ap, peer, site.global_of(&site.ned_of((5.0, 5.0), 0.0)));
        let driver = bridge.driver();
        let until = Instant::now() + Duration::from_secs(10);
        while !(driver.drivable() && driver.position().is_some()) {
            assert!(Instant::now() < until, "the scripted autopilot is never drivable");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let target = Target {
            epoch: 0,
            step: 3,
            position: [30.0, 15.0],
            radius: 2.0,
            cells: vec![1],
        };
        let start = Instant::now();
        let (fixes, _) = drive(Some(driver), vec![target], grid, Duration::from_secs(120), None).await;
        let took = start.elapsed();
        assert!(
            took < STALL + Duration::from_secs(3),
            "waited {took:?} for a target never followed"
        );
        assert!(
            fixes.get(&3).is_some_and(|f| !f.arrived),
            "sensed where it is: {fixes:?}"
        );
    }
}
