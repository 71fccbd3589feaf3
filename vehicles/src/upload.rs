//! The bridge's side of the mission protocol: one list (the site's fence, the rally points)
//! uploaded to the autopilot as MAVLink's mission protocol and ArduPilot's
//! `libraries/GCS_MAVLink/MissionItemProtocol.cpp` define it, then read back. Pure: the bridge
//! sends what this returns, and calls [`Upload::tick`] once a second.
//!
//! | state | sent | on the autopilot's answer | each second without one |
//! |---|---|---|---|
//! | counted | MISSION_COUNT | a MISSION_REQUEST_INT: the item, now sending | the count again, from the second on |
//! | sending | each item asked for | MISSION_ACK accepted: read back; INVALID_SEQUENCE: nothing (the upload is still open); any other: started again | after [`QUIET_S`], started again |
//! | reading | MISSION_REQUEST_LIST, then MISSION_REQUEST_INT each | the count and every item as sent: confirmed; else started again | the request again; after [`QUIET_S`], started again |
//!
//! Why the count is sent again only while it has no answer: ArduPilot restarts an upload on
//! each MISSION_COUNT from the same sender, so a count sent while items are in flight doubles
//! the requests and items, and a duplicate item is answered MISSION_ACK INVALID_SEQUENCE while
//! the upload stays open. Why INVALID_SEQUENCE is not an end: ArduPilot sends it for any item
//! but the one it asked for and goes on asking. Why the list is read back: an accepted upload
//! is the autopilot's word for the items it stored, and reading them is the only way the bridge
//! knows the fence is the one it meant. An upload started [`TRIES`] times without that is
//! failed, with the reason, and the vehicle is not driven (see the bridge).

use mavlink::dialects::ardupilotmega::*;

/// An upload is started at most this many times.
pub const TRIES: u32 = 5;
/// Seconds without an answer before an open upload or read-back is started again: longer than
/// ArduPilot's own 8 s upload timeout (`upload_timeout_ms`), after which it has closed its side.
pub const QUIET_S: u32 = 10;

#[derive(Debug, Clone, PartialEq)]
pub enum State {
    /// Not started.
    Idle,
    /// MISSION_COUNT sent, nothing asked for since.
    Counted,
    /// The autopilot is asking for items.
    Sending,
    /// Accepted; the list's count asked for (MISSION_REQUEST_LIST).
    ReadingCount,
    /// Read back up to (not including) this item.
    Reading(u16),
    /// Read back as sent.
    Confirmed,
    /// Started [`TRIES`] times without a confirmed list: why, the last time.
    Failed(String),
}

#[derive(Debug, Clone)]
pub struct Upload {
    pub kind: MavMissionType,
    items: Vec<MISSION_ITEM_INT_DATA>,
    pub state: State,
    /// How many times the upload has been started.
    starts: u32,
    /// Seconds since the autopilot last answered.
    quiet: u32,
}

impl Upload {
    pub fn new(kind: MavMissionType, items: Vec<MISSION_ITEM_INT_DATA>) -> Self {
        Self {
            kind,
            items,
            state: State::Idle,
            starts: 0,
            quiet: 0,
        }
    }

    pub fn finished(&self) -> bool {
        matches!(self.state, State::Confirmed | State::Failed(_))
    }

    pub fn confirmed(&self) -> bool {
        self.state == State::Confirmed
    }

    /// How many times it has been started (1 when nothing went wrong).
    pub fn starts(&self) -> u32 {
        self.starts
    }

    /// The upload's first MISSION_COUNT (nothing once started).
    pub fn start(&mut self, target: u8) -> Vec<MavMessage> {
        if self.state != State::Idle {
            return vec![];
        }
        self.restart(target, "")
    }

    /// A second has passed: what to send again.
    pub fn tick(&mut self, target: u8) -> Vec<MavMessage> {
        if self.state == State::Idle {
            return self.start(target);
        }
        if self.finished() {
            return vec![];
        }
        self.quiet += 1;
        match self.state {
            _ if self.quiet >= QUIET_S => self.restart(target, "no answer"),
            // From the second tick on: the first may come at once after the count.
            State::Counted if self.quiet >= 2 => self.restart(target, "no answer to MISSION_COUNT"),
            // ArduPilot asks again by itself each second.
            State::Counted | State::Sending => vec![],
            State::ReadingCount => vec![self.request_list(target)],
            State::Reading(seq) => vec![self.request(seq, target)],
            _ => vec![],
        }
    }

    /// The item the autopilot asks for, if the request is for this list and it is uploading.
    pub fn on_request(&mut self, kind: MavMissionType, seq: u16, target: u8) -> Option<MavMessage> {
        if kind != self.kind || !matches!(self.state, State::Counted | State::Sending) {
            return None;
        }
        let item = self.items.get(seq as usize)?;
        (self.state, self.quiet) = (State::Sending, 0);
        Some(MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
            seq,
            target_system: target,
            target_component: 1,
            mission_type: self.kind,
            ..item.clone()
        }))
    }

    /// The autopilot's MISSION_ACK.
    pub fn on_ack(&mut self, kind: MavMissionType, result: MavMissionResult, target: u8) -> Vec<MavMessage> {
        use MavMissionResult::*;
        if kind != self.kind {
            return vec![];
        }
        match (&self.state, result) {
            (State::Counted | State::Sending, MAV_MISSION_ACCEPTED) => {
                (self.state, self.quiet) = (State::ReadingCount, 0);
                vec![self.request_list(target)]
            }
            (State::Counted | State::Sending, MAV_MISSION_INVALID_SEQUENCE) => vec![],
            (State::Counted | State::Sending | State::ReadingCount | State::Reading(_), r) => {
                self.restart(target, &format!("{r:?}"))
            }
            _ => vec![],
        }
    }

    /// The autopilot's MISSION_COUNT, in answer to the read-back's MISSION_REQUEST_LIST.
    pub fn on_count(&mut self, kind: MavMissionType, count: u16, target: u8) -> Vec<MavMessage> {
        if kind != self.kind || self.state != State::ReadingCount {
            return vec![];
        }
        if usize::from(count) != self.items.len() {
            let why = format!("read back {count} items of {}", self.items.len());
            return self.restart(target, &why);
        }
        self.read_from(0, target)
    }

    /// An item the autopilot sends, in answer to the read-back's MISSION_REQUEST_INT.
    pub fn on_item(&mut self, item: &MISSION_ITEM_INT_DATA, target: u8) -> Vec<MavMessage> {
        if item.mission_type != self.kind || self.state != State::Reading(item.seq) {
            return vec![];
        }
        let Some(sent) = self.items.get(usize::from(item.seq)) else {
            return vec![];
        };
        if (item.command, item.x, item.y) != (sent.command, sent.x, sent.y) {
            let why = format!(
                "item {} read back as {:?} at ({}, {})",
                item.seq, item.command, item.x, item.y
            );
            return self.restart(target, &why);
        }
        self.read_from(item.seq + 1, target)
    }

    /// Read on from item `seq`, or confirmed (and the download closed) past the last.
    fn read_from(&mut self, seq: u16, target: u8) -> Vec<MavMessage> {
        self.quiet = 0;
        if usize::from(seq) < self.items.len() {
            self.state = State::Reading(seq);
            return vec![self.request(seq, target)];
        }
        self.state = State::Confirmed;
        vec![MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: target,
            target_component: 1,
            mavtype: MavMissionResult::MAV_MISSION_ACCEPTED,
            mission_type: self.kind,
            ..Default::default()
        })]
    }

    /// Start (again): a fresh MISSION_COUNT, or failed after [`TRIES`] starts.
    fn restart(&mut self, target: u8, why: &str) -> Vec<MavMessage> {
        if self.starts >= TRIES {
            self.state = State::Failed(why.to_string());
            return vec![];
        }
        (self.starts, self.state, self.quiet) = (self.starts + 1, State::Counted, 0);
        vec![MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: self.items.len() as u16,
            target_system: target,
            target_component: 1,
            mission_type: self.kind,
            ..Default::default()
        })]
    }

    fn request_list(&self, target: u8) -> MavMessage {
        MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: target,
            target_component: 1,
            mission_type: self.kind,
        })
    }

    fn request(&self, seq: u16, target: u8) -> MavMessage {
        MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: target,
            target_component: 1,
            mission_type: self.kind,
        })
    }
}

fn at(command: MavCmd, param1: f32, lat: f64, lon: f64) -> MISSION_ITEM_INT_DATA {
    MISSION_ITEM_INT_DATA {
        command,
        param1,
        frame: MavFrame::MAV_FRAME_GLOBAL,
        x: (lat * 1e7).round() as i32,
        y: (lon * 1e7).round() as i32,
        autocontinue: 1,
        ..Default::default()
    }
}

/// An inclusion fence of one polygon (`[lat, lon]` vertices).
pub fn fence_items(polygon: &[[f64; 2]]) -> Vec<MISSION_ITEM_INT_DATA> {
    let n = polygon.len() as f32;
    polygon
        .iter()
        .enumerate()
        .map(|(seq, &[lat, lon])| MISSION_ITEM_INT_DATA {
            seq: seq as u16,
            ..at(MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, n, lat, lon)
        })
        .collect()
}

/// Rally points (`[lat, lon]`).
pub fn rally_items(points: &[[f64; 2]]) -> Vec<MISSION_ITEM_INT_DATA> {
    points
        .iter()
        .enumerate()
        .map(|(seq, &[lat, lon])| MISSION_ITEM_INT_DATA {
            seq: seq as u16,
            ..at(MavCmd::MAV_CMD_NAV_RALLY_POINT, 0.0, lat, lon)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;
    const RALLY: MavMissionType = MavMissionType::MAV_MISSION_TYPE_RALLY;

    fn fence() -> Upload {
        let poly = [[55.0, 12.0], [55.0, 12.001], [55.001, 12.001]];
        Upload::new(FENCE, fence_items(&poly))
    }

    fn is_count(m: &[MavMessage]) -> bool {
        matches!(m, [MavMessage::MISSION_COUNT(c)] if c.count == 3 && c.mission_type == FENCE && c.target_system == 3)
    }

    /// The items as the autopilot would read them back.
    fn read_back(u: &mut Upload) -> Vec<MavMessage> {
        let items = u.items.clone();
        let mut last = u.on_count(FENCE, 3, 3);
        for i in items {
            last = u.on_item(
                &MISSION_ITEM_INT_DATA {
                    mission_type: FENCE,
                    ..i
                },
                3,
            );
        }
        last
    }

    #[test]
    fn an_upload_answers_each_request_then_reads_the_list_back() {
        let mut u = fence();
        assert!(is_count(&u.start(3)) && u.start(3).is_empty());
        let Some(MavMessage::MISSION_ITEM_INT(i)) = u.on_request(FENCE, 2, 3) else {
            panic!()
        };
        assert_eq!(
            (i.seq, i.param1, i.x, i.y, i.command),
            (
                2,
                3.0,
                550_010_000,
                120_010_000,
                MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
            )
        );
        assert!(u.on_request(RALLY, 0, 3).is_none(), "another list's request");
        assert!(u.on_request(FENCE, 3, 3).is_none(), "past the end");
        assert!(u.on_ack(RALLY, MavMissionResult::MAV_MISSION_ERROR, 3).is_empty());
        let list = u.on_ack(FENCE, MavMissionResult::MAV_MISSION_ACCEPTED, 3);
        assert!(matches!(&list[..], [MavMessage::MISSION_REQUEST_LIST(r)] if r.mission_type == FENCE));
        assert!(!u.finished(), "accepted is not yet confirmed");
        assert!(matches!(&read_back(&mut u)[..], [MavMessage::MISSION_ACK(_)]));
        assert!(u.confirmed() && u.starts() == 1);
    }

    #[test]
    fn a_count_is_sent_again_only_while_unanswered() {
        let mut u = fence();
        u.start(3);
        // tokio's interval ticks at once: the count just sent is not sent again.
        assert!(u.tick(3).is_empty());
        assert!(is_count(&u.tick(3)), "a second without an answer");
        u.on_request(FENCE, 0, 3);
        // Items in flight: ArduPilot asks again by itself; a count would restart its upload.
        assert!((0..QUIET_S - 1).all(|_| u.tick(3).is_empty()));
        assert!(is_count(&u.tick(3)), "ArduPilot has timed the upload out");
        assert_eq!(u.starts(), 3);
    }

    #[test]
    fn an_invalid_sequence_is_not_the_end_and_a_failed_upload_starts_again() {
        let mut u = fence();
        u.start(3);
        u.on_request(FENCE, 0, 3);
        assert!(u
            .on_ack(FENCE, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE, 3)
            .is_empty());
        assert_eq!(u.state, State::Sending);
        assert!(is_count(&u.on_ack(
            FENCE,
            MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
            3
        )));
        u.on_ack(FENCE, MavMissionResult::MAV_MISSION_ACCEPTED, 3);
        // Read back short: started again.
        assert!(is_count(&u.on_count(FENCE, 2, 3)));
        u.on_ack(FENCE, MavMissionResult::MAV_MISSION_ACCEPTED, 3);
        u.on_count(FENCE, 3, 3);
        let wrong = MISSION_ITEM_INT_DATA {
            mission_type: FENCE,
            x: 1,
            ..u.items[0].clone()
        };
        assert!(is_count(&u.on_item(&wrong, 3)), "an item that is not the one sent");
        assert_eq!(u.starts(), 4);
        u.on_ack(FENCE, MavMissionResult::MAV_MISSION_DENIED, 3);
        assert!(u.on_ack(FENCE, MavMissionResult::MAV_MISSION_DENIED, 3).is_empty());
        assert_eq!(u.state, State::Failed("MAV_MISSION_DENIED".into()));
        assert!(u.finished() && !u.confirmed());
    }

    #[test]
    fn nobody_answers_five_counts_then_failed() {
        let mut u = Upload::new(RALLY, rally_items(&[[55.0, 12.0]]));
        let counts = (0..60).map(|_| u.tick(3)).filter(|m| !m.is_empty()).count();
        assert_eq!((counts, u.starts()), (TRIES as usize, TRIES));
        assert!(matches!(u.state, State::Failed(_)));
    }
}
