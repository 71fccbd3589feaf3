//! The autopilot's stream as it goes to the ground stations over a thin link. An autopilot
//! streams its position, attitude and status many times a second; over a radio shared by the
//! fleet that alone fills it (five boats' full streams are more than a 64 kbit/s SiK radio
//! carries). So each periodic message goes on at most `hz` times a second, on the average, and
//! what is not periodic (text, command and mission-protocol replies, parameters, the flight log)
//! always goes: a ground station's own questions are answered in full. The whole stream stays on
//! the vehicle (the bridge reads all of it).
//!
//! HEARTBEAT and SYS_STATUS are never thinned: a ground station judges the link by them
//! (QGroundControl calls a vehicle lost after 3.5 s without a heartbeat), so they go at the
//! autopilot's own rate whatever `hz`.
//!
//! The rate is kept by a token bucket per message (refilled at `hz`, holding at most
//! [`BURST`]), not by a minimum spacing: an autopilot's 1 Hz stream arrives with a few
//! milliseconds of jitter, and a minimum spacing of exactly 1 s drops every message that comes
//! a little early (about every other one), while the bucket passes the whole stream and still
//! holds a faster one to `hz` on the average.

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::Message;
use std::collections::HashMap;
use std::time::Instant;

/// How many of one message may pass back to back after a quiet spell: the slack that absorbs
/// jitter (a stream at exactly `hz` keeps its bucket near one token).
pub const BURST: f64 = 2.0;

pub struct Throttle {
    /// Tokens per second for each periodic message (`None`: none of them pass).
    hz: Option<f64>,
    /// Each message's tokens, as of when it last arrived.
    buckets: HashMap<u32, (f64, Instant)>,
}

impl Throttle {
    /// At most `hz` of each periodic message a second on the average (0: none; infinite: all).
    pub fn new(hz: f64) -> Self {
        Self {
            hz: (hz > 0.0).then_some(hz),
            buckets: HashMap::new(),
        }
    }

    /// Whether `m`, at `now`, goes on to the ground stations.
    pub fn pass(&mut self, m: &MavMessage, now: Instant) -> bool {
        if is_event(m) || judges_the_link(m) {
            return true;
        }
        let Some(hz) = self.hz else { return false };
        if hz.is_infinite() {
            return true;
        }
        let (tokens, at) = self.buckets.entry(m.message_id()).or_insert((BURST, now));
        let refilled = *tokens + now.saturating_duration_since(*at).as_secs_f64() * hz;
        *at = now;
        *tokens = refilled.min(BURST);
        let passes = *tokens >= 1.0;
        if passes {
            *tokens -= 1.0;
        }
        passes
    }
}

/// Messages a ground station judges the link by: never thinned.
pub fn judges_the_link(m: &MavMessage) -> bool {
    matches!(m, MavMessage::HEARTBEAT(_) | MavMessage::SYS_STATUS(_))
}

/// Messages that go to the ground stations at once rather than wait to share a put with the
/// stream: what an autopilot sends once, in answer or on an event, and its HEARTBEAT, by
/// which a ground station times the link (held in a bundle for up to a period, heartbeats
/// arrived up to 2 s apart).
pub fn is_event(m: &MavMessage) -> bool {
    #[allow(deprecated)]
    let event = matches!(
        m,
        MavMessage::HEARTBEAT(_)
            | MavMessage::STATUSTEXT(_)
            | MavMessage::COMMAND_ACK(_)
            | MavMessage::COMMAND_LONG(_)
            | MavMessage::COMMAND_INT(_)
            | MavMessage::PARAM_VALUE(_)
            | MavMessage::MISSION_ACK(_)
            | MavMessage::MISSION_COUNT(_)
            | MavMessage::MISSION_ITEM(_)
            | MavMessage::MISSION_ITEM_INT(_)
            | MavMessage::MISSION_REQUEST(_)
            | MavMessage::MISSION_REQUEST_INT(_)
            | MavMessage::MISSION_ITEM_REACHED(_)
            | MavMessage::AUTOPILOT_VERSION(_)
            | MavMessage::PROTOCOL_VERSION(_)
            | MavMessage::FILE_TRANSFER_PROTOCOL(_)
            | MavMessage::LOG_ENTRY(_)
            | MavMessage::LOG_DATA(_)
            | MavMessage::TIMESYNC(_)
            | MavMessage::NAMED_VALUE_FLOAT(_)
    );
    event
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::*;
    use std::time::Duration;

    /// `n` arrivals `period_ms` apart, each moved by up to `jitter_ms` either way
    /// (deterministic: a small linear congruential sequence).
    fn jittered(t0: Instant, n: u64, period_ms: u64, jitter_ms: u64) -> Vec<Instant> {
        let mut x: u64 = 12345;
        (0..n)
            .map(|i| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let j = (x >> 33) % (2 * jitter_ms + 1);
                t0 + Duration::from_millis(1000 + i * period_ms + j - jitter_ms)
            })
            .collect()
    }

    #[test]
    fn a_jittered_stream_at_the_rate_passes_whole_and_a_faster_one_is_held_to_it() {
        let t0 = Instant::now();
        let attitude = MavMessage::ATTITUDE(ATTITUDE_DATA::default());
        // A minute of a 1 Hz stream, each message up to 20 ms early or late: a minimum spacing
        // of 1 s passed about half of these.
        let mut t = Throttle::new(1.0);
        let passed = jittered(t0, 60, 1000, 20)
            .into_iter()
            .filter(|&at| t.pass(&attitude, at))
            .count();
        assert_eq!(passed, 60);
        // A minute of a 10 Hz stream: one a second on the average (plus the burst).
        let mut t = Throttle::new(1.0);
        let passed = jittered(t0, 600, 100, 20)
            .into_iter()
            .filter(|&at| t.pass(&attitude, at))
            .count();
        assert!((60..=60 + BURST as usize).contains(&passed), "{passed}");
    }

    #[test]
    fn heartbeats_and_status_pass_whatever_the_rate() {
        let t0 = Instant::now();
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        let status = MavMessage::SYS_STATUS(SYS_STATUS_DATA::default());
        for hz in [0.0, 0.2, 1.0] {
            let mut t = Throttle::new(hz);
            let at = jittered(t0, 60, 1000, 20);
            assert!(at.iter().all(|&a| t.pass(&hb, a) && t.pass(&status, a)), "hz {hz}");
        }
    }

    #[test]
    fn periodic_messages_go_at_the_rate_and_events_always() {
        let mut t = Throttle::new(1.0);
        let t0 = Instant::now();
        let pos = MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA::default());
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        let text = MavMessage::STATUSTEXT(STATUSTEXT_DATA::default());
        // Ten seconds of a 10 Hz position stream, a 10 Hz heartbeat and a text every 100 ms:
        // positions at the rate (after the burst), every heartbeat and every text.
        let (mut pos_n, mut hb_n, mut text_n) = (0, 0, 0);
        for i in 0..100u64 {
            let now = t0 + Duration::from_millis(100 * i);
            pos_n += t.pass(&pos, now) as u32;
            hb_n += t.pass(&hb, now) as u32;
            text_n += t.pass(&text, now) as u32;
        }
        assert_eq!((pos_n, hb_n, text_n), (10 + BURST as u32 - 1, 100, 100));
        let mut none = Throttle::new(0.0);
        assert!(!none.pass(&pos, t0) && none.pass(&text, t0));
        let mut all = Throttle::new(f64::INFINITY);
        assert!(all.pass(&pos, t0) && all.pass(&pos, t0));
    }
}
