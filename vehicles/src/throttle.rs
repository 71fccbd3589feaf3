//! The autopilot's stream as it goes to the ground stations over a thin link. An autopilot
//! streams its position, attitude and status many times a second; over a radio shared by the
//! fleet that alone fills it (five boats' full streams are more than a 64 kbit/s SiK radio
//! carries). So each periodic message goes on at most `hz` times a second, and what is not
//! periodic (text, command and mission-protocol replies, parameters, the flight log) always goes:
//! a ground station's own questions are answered in full. The whole stream stays on the vehicle
//! (the bridge reads all of it).

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::Message;
use std::collections::HashMap;
use std::time::{Duration, Instant};

pub struct Throttle {
    /// At most one of each periodic message this often (`None`: none of them).
    every: Option<Duration>,
    last: HashMap<u32, Instant>,
}

impl Throttle {
    /// At most `hz` of each periodic message a second (0: none; infinite: all).
    pub fn new(hz: f64) -> Self {
        let every = (hz > 0.0).then(|| Duration::from_secs_f64(if hz.is_finite() { 1.0 / hz } else { 0.0 }));
        Self {
            every,
            last: HashMap::new(),
        }
    }

    /// Whether `m`, at `now`, goes on to the ground stations.
    pub fn pass(&mut self, m: &MavMessage, now: Instant) -> bool {
        if is_event(m) {
            return true;
        }
        let Some(every) = self.every else { return false };
        let id = m.message_id();
        match self.last.get(&id) {
            Some(&t) if now.duration_since(t) < every => false,
            _ => {
                self.last.insert(id, now);
                true
            }
        }
    }
}

/// Messages an autopilot sends once, in answer or on an event, rather than streams.
pub fn is_event(m: &MavMessage) -> bool {
    #[allow(deprecated)]
    let event = matches!(
        m,
        MavMessage::STATUSTEXT(_)
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

    #[test]
    fn periodic_messages_go_at_the_rate_and_events_always() {
        let mut t = Throttle::new(1.0);
        let t0 = Instant::now();
        let pos = MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA::default());
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        let text = MavMessage::STATUSTEXT(STATUSTEXT_DATA::default());
        // Ten seconds of a 10 Hz position stream, a 1 Hz heartbeat and a text every 100 ms.
        let (mut pos_n, mut hb_n, mut text_n) = (0, 0, 0);
        for i in 0..100u64 {
            let now = t0 + Duration::from_millis(100 * i);
            pos_n += t.pass(&pos, now) as u32;
            if i % 10 == 0 {
                hb_n += t.pass(&hb, now) as u32;
            }
            text_n += t.pass(&text, now) as u32;
        }
        assert_eq!((pos_n, hb_n, text_n), (10, 10, 100));
        let mut none = Throttle::new(0.0);
        assert!(!none.pass(&pos, t0) && none.pass(&text, t0));
        let mut all = Throttle::new(f64::INFINITY);
        assert!(all.pass(&pos, t0) && all.pass(&pos, t0));
    }
}
