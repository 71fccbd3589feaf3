//! The bridge's side of the mission protocol: one list (the site's fence, the rally points)
//! uploaded to the autopilot as a ground station does it: MISSION_COUNT, then each item the
//! autopilot asks for (MISSION_REQUEST_INT), until its MISSION_ACK. Pure: the bridge sends what
//! this returns. A count with no answer is sent again, a few times, then given up (an
//! autopilot without fences still flies).

use mavlink::dialects::ardupilotmega::*;

/// MISSION_COUNT is sent at most this many times.
pub const TRIES: u32 = 5;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum State {
    Pending,
    Done(MavMissionResult),
    GaveUp,
}

#[derive(Debug, Clone)]
pub struct Upload {
    pub kind: MavMissionType,
    items: Vec<MISSION_ITEM_INT_DATA>,
    pub state: State,
    tries: u32,
}

impl Upload {
    pub fn new(kind: MavMissionType, items: Vec<MISSION_ITEM_INT_DATA>) -> Self {
        Self {
            kind,
            items,
            state: State::Pending,
            tries: 0,
        }
    }

    /// Whether its count has been sent.
    pub fn started(&self) -> bool {
        self.tries > 0
    }

    pub fn finished(&self) -> bool {
        self.state != State::Pending
    }

    pub fn accepted(&self) -> bool {
        self.state == State::Done(MavMissionResult::MAV_MISSION_ACCEPTED)
    }

    /// The MISSION_COUNT to send now (again), or `None` once done or out of tries.
    pub fn count(&mut self, target: u8) -> Option<MavMessage> {
        if self.finished() {
            return None;
        }
        if self.tries >= TRIES {
            self.state = State::GaveUp;
            return None;
        }
        self.tries += 1;
        Some(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: self.items.len() as u16,
            target_system: target,
            target_component: 1,
            mission_type: self.kind,
            ..Default::default()
        }))
    }

    /// The item the autopilot asks for, if the request is for this list.
    pub fn item(&self, kind: MavMissionType, seq: u16, target: u8) -> Option<MavMessage> {
        if kind != self.kind || self.finished() {
            return None;
        }
        let item = self.items.get(seq as usize)?;
        Some(MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
            seq,
            target_system: target,
            target_component: 1,
            mission_type: self.kind,
            ..item.clone()
        }))
    }

    /// The autopilot's answer.
    pub fn ack(&mut self, kind: MavMissionType, result: MavMissionResult) {
        if kind == self.kind && !self.finished() {
            self.state = State::Done(result);
        }
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

    #[test]
    fn an_upload_answers_each_request_then_ends_on_the_ack_or_after_its_tries() {
        let poly = [[55.0, 12.0], [55.0, 12.001], [55.001, 12.001]];
        let mut u = Upload::new(MavMissionType::MAV_MISSION_TYPE_FENCE, fence_items(&poly));
        let fence = MavMissionType::MAV_MISSION_TYPE_FENCE;
        assert!(matches!(u.count(3), Some(MavMessage::MISSION_COUNT(c))
                if c.count == 3 && c.mission_type == fence && c.target_system == 3));
        let Some(MavMessage::MISSION_ITEM_INT(i)) = u.item(MavMissionType::MAV_MISSION_TYPE_FENCE, 2, 3) else {
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
        assert!(
            u.item(MavMissionType::MAV_MISSION_TYPE_RALLY, 0, 3).is_none(),
            "another list's request"
        );
        assert!(
            u.item(MavMissionType::MAV_MISSION_TYPE_FENCE, 3, 3).is_none(),
            "past the end"
        );
        u.ack(
            MavMissionType::MAV_MISSION_TYPE_RALLY,
            MavMissionResult::MAV_MISSION_ERROR,
        );
        assert!(!u.finished());
        u.ack(
            MavMissionType::MAV_MISSION_TYPE_FENCE,
            MavMissionResult::MAV_MISSION_ACCEPTED,
        );
        assert!(u.accepted() && u.count(3).is_none());
        // Nobody answers: five counts, then given up.
        let mut u = Upload::new(MavMissionType::MAV_MISSION_TYPE_RALLY, rally_items(&poly));
        assert_eq!((0..10).filter_map(|_| u.count(3)).count(), TRIES as usize);
        assert_eq!(u.state, State::GaveUp);
    }
}
