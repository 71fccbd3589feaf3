//! A simulated autopilot on a MAVLink connection (`udpin:` as SITL does, or any other the
//! `mavlink` crate opens): its own thread ticks the physics every 10 ms (a simulator's clock,
//! as SITL's) and sends HEARTBEAT and SYS_STATUS (with BATTERY_STATUS, HOME_POSITION,
//! MISSION_CURRENT, FENCE_STATUS) at 1 Hz, GLOBAL_POSITION_INT, LOCAL_POSITION_NED (and its
//! guided target) at 10 Hz, and replies as they come (the link's reader thread hands it what
//! arrives). Frames it cannot read are counted and skipped. With a
//! signing key it signs everything it sends and obeys only frames signed with that key.
//!
//! With a companion link (as ArduPilot's second serial port, where a companion computer or an
//! instrument's driver sits) it also sends its stream there, and routes what comes from there
//! onto its main link unchanged (a NAMED_VALUE_FLOAT reaches the vehicle's bridge as a Lua
//! script's would), as ArduPilot's MAVLink routing forwards a broadcast message to its other
//! links; a frame addressed to it is obeyed too.

use super::sim::SimAutopilot;
use crate::link::{MavLink, Received};
use crate::signing::{LinkSigning, Refused};
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MavHeader, Message};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// What a served autopilot has seen.
#[derive(Debug, Default)]
pub struct ServeStats {
    pub received: AtomicU64,
    /// Frames that did not parse (bad CRC, unknown id, truncated).
    pub unreadable: AtomicU64,
    pub sent: AtomicU64,
    /// Frames refused by the signing check: unsigned, wrongly signed, replayed.
    pub unsigned: AtomicU64,
    pub bad_signature: AtomicU64,
    pub replay: AtomicU64,
}

impl ServeStats {
    fn refused(&self, r: Refused) -> &AtomicU64 {
        match r {
            Refused::Unsigned => &self.unsigned,
            Refused::BadSignature => &self.bad_signature,
            Refused::Replay => &self.replay,
        }
    }
}

/// Serve `sim` on `address` until `stop` (signed with `signing`, if given); the reader thread
/// ends with the process.
pub fn spawn(
    address: &str,
    sim: SimAutopilot,
    signing: Option<LinkSigning>,
    stop: Arc<AtomicBool>,
) -> std::io::Result<Arc<ServeStats>> {
    spawn_routed(address, None, sim, signing, stop)
}

/// [`spawn`], with a companion link at `companion` (unsigned) routed onto the main one.
pub fn spawn_routed(
    address: &str,
    companion: Option<&str>,
    sim: SimAutopilot,
    signing: Option<LinkSigning>,
    stop: Arc<AtomicBool>,
) -> std::io::Result<Arc<ServeStats>> {
    let conn = Arc::new(MavLink::open(address, signing)?);
    let stats = Arc::new(ServeStats::default());
    let rx = conn.reader("sim-autopilot-rx")?;
    let companion = match companion {
        Some(a) => {
            let c = Arc::new(MavLink::open(a, None)?);
            let rx = c.reader("sim-companion-rx")?;
            Some((c, rx))
        }
        None => None,
    };
    let st = stats.clone();
    std::thread::Builder::new()
        .name("sim-autopilot".into())
        .spawn(move || run(conn, companion, sim, rx, stop, st))?;
    Ok(stats)
}

/// The companion link and what it reads.
type Companion = (Arc<MavLink>, mpsc::UnboundedReceiver<Received>);

/// Route what the companion sent onto the main link (and obey what is addressed to `sim`).
fn route_companion(companion: &mut Option<Companion>, conn: &MavLink, sim: &mut SimAutopilot) {
    let Some((_, rx)) = companion else { return };
    while let Ok(r) = rx.try_recv() {
        if let Received::Frame(h, m, _) = r {
            if m.target_system_id() == Some(sim.spec.sysid) {
                sim.handle(&h, &m);
            }
            let _ = conn.send(&h, &m);
        }
    }
}

fn run(
    conn: Arc<MavLink>,
    mut companion: Option<Companion>,
    mut sim: SimAutopilot,
    mut rx: mpsc::UnboundedReceiver<Received>,
    stop: Arc<AtomicBool>,
    stats: Arc<ServeStats>,
) {
    let to_companion = companion.as_ref().map(|(c, _)| c.clone());
    let mut header = MavHeader {
        system_id: sim.spec.sysid as u32,
        component_id: 1,
        sequence: 0,
    };
    let mut send = |m: &MavMessage| {
        // No peer yet (udpin before the first datagram), or it went away: dropped, as on a radio.
        if conn.send(&header, m).is_ok() {
            stats.sent.fetch_add(1, Ordering::Relaxed);
        }
        if let Some(c) = &to_companion {
            let _ = c.send(&header, m);
        }
        header.sequence = header.sequence.wrapping_add(1);
    };
    let start = Instant::now();
    // `slow`: the number of once-a-second bursts sent.
    let (mut last, mut fast, mut slow) = (Instant::now(), 0u64, 0u64);
    // What the last HEARTBEAT said; a change (or the first peer) is announced at once.
    let mut shown: Option<(u32, bool)> = None;
    while !stop.load(Ordering::Relaxed) {
        let mut heard = false;
        while let Ok(r) = rx.try_recv() {
            match r {
                Received::Frame(h, m, _) => {
                    stats.received.fetch_add(1, Ordering::Relaxed);
                    sim.handle(&h, &m);
                    heard = true;
                }
                Received::Refused(r) => {
                    stats.refused(r).fetch_add(1, Ordering::Relaxed);
                }
                Received::Unreadable(_) => {
                    stats.unreadable.fetch_add(1, Ordering::Relaxed);
                }
                Received::Idle | Received::Closed => {}
            }
        }
        route_companion(&mut companion, &conn, &mut sim);
        if (heard && shown.is_none()) || shown.is_some_and(|s| s != (sim.mode, sim.armed)) {
            send(&sim.heartbeat());
            shown = Some((sim.mode, sim.armed));
        }
        let now = Instant::now();
        sim.step(now.duration_since(last).as_secs_f64());
        last = now;
        for m in sim.take() {
            send(&m);
        }
        let ms = start.elapsed().as_millis() as u64;
        if ms / 100 >= fast {
            fast = ms / 100 + 1;
            for m in sim.position() {
                send(&m);
            }
        }
        if ms >= second_due(slow, sim.spec.sysid) {
            slow += 1;
            send(&sim.heartbeat());
            shown = shown.map(|_| (sim.mode, sim.armed));
            send(&sim.sys_status());
            for m in sim.slow() {
                send(&m);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// When the once-a-second burst of `second` is due, in ms since the start: on the second, up
/// to 20 ms early or late. ArduPilot's scheduler runs its stream tasks when the loop reaches
/// them, so a real autopilot's 1 Hz HEARTBEAT comes with milliseconds of jitter, and a ground
/// link that thinned by the exact period would drop every early one (issue 83). A hash of the
/// second and the system id, not a clock: the same run gives the same times.
fn second_due(second: u64, sysid: u8) -> u64 {
    const JITTER_MS: u64 = 20;
    let h = second.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ u64::from(sysid).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    (second * 1000 + (h >> 32) % (2 * JITTER_MS + 1)).saturating_sub(JITTER_MS)
}

#[cfg(test)]
mod tests {
    use super::second_due;

    #[test]
    fn the_heartbeat_is_due_each_second_within_twenty_ms_and_not_on_the_dot() {
        let gaps: Vec<i64> = (1..200)
            .map(|k| second_due(k + 1, 7) as i64 - second_due(k, 7) as i64)
            .collect();
        assert!(gaps.iter().all(|g| (960..=1040).contains(g)), "{gaps:?}");
        assert!(
            gaps.iter().filter(|&&g| g < 1000).count() > 50,
            "about half come early: {gaps:?}"
        );
        assert!(second_due(0, 7) <= 20);
    }
}
