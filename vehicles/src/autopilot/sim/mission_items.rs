//! The mission protocol (upload, download, clear, set current) for missions, fences and rally
//! points, and running a mission in AUTO.

use super::*;

impl SimAutopilot {
    pub(super) fn mission_ack(&mut self, to: (u8, u8), result: MavMissionResult, mission_type: MavMissionType) {
        self.out.push(MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: to.0,
            target_component: to.1,
            mavtype: result,
            mission_type,
            ..Default::default()
        }));
    }

    pub(super) fn request_item(&mut self, seq: u16) {
        if let Some(u) = &mut self.upload {
            u.asked_at = self.wall_s;
            let (target_system, target_component) = u.from;
            self.out.push(MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq,
                target_system,
                target_component,
                mission_type: u.kind,
            }));
        }
    }

    /// The stored items of a mission type (`None`: a type we do not keep).
    pub(super) fn items(&self, kind: MavMissionType) -> Option<&Vec<MISSION_ITEM_INT_DATA>> {
        match kind {
            MavMissionType::MAV_MISSION_TYPE_MISSION => Some(&self.mission),
            MavMissionType::MAV_MISSION_TYPE_FENCE => Some(&self.fence_items),
            MavMissionType::MAV_MISSION_TYPE_RALLY => Some(&self.rally),
            _ => None,
        }
    }

    /// Whether an uploaded item may be in a list of its type.
    pub(super) fn valid_item(kind: MavMissionType, item: &MISSION_ITEM_INT_DATA) -> Result<(), MavMissionResult> {
        use MavCmd::*;
        match kind {
            MavMissionType::MAV_MISSION_TYPE_FENCE => match item.command {
                MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
                | MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
                | MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
                | MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION
                | MAV_CMD_NAV_FENCE_RETURN_POINT => Ok(()),
                _ => Err(MavMissionResult::MAV_MISSION_UNSUPPORTED),
            },
            MavMissionType::MAV_MISSION_TYPE_RALLY if item.command != MAV_CMD_NAV_RALLY_POINT => {
                Err(MavMissionResult::MAV_MISSION_UNSUPPORTED)
            }
            MavMissionType::MAV_MISSION_TYPE_RALLY => Ok(()),
            _ => Self::flyable(item),
        }
    }

    /// Store a finished upload; a fence must describe a fence.
    pub(super) fn store(&mut self, kind: MavMissionType, items: Vec<MISSION_ITEM_INT_DATA>) -> MavMissionResult {
        match kind {
            MavMissionType::MAV_MISSION_TYPE_FENCE => match Geofence::from_items(&items, &self.spec.site) {
                Ok(f) => {
                    (self.fence, self.fence_items, self.breached) = (f, items, false);
                    // What SITL's `AC_PolyFence_loader::write_fence` says once it has stored one.
                    self.say(MavSeverity::MAV_SEVERITY_DEBUG, "Fence Indexed OK");
                }
                Err(why) => return why,
            },
            MavMissionType::MAV_MISSION_TYPE_RALLY => self.rally = items,
            _ => {
                self.mission = items;
                self.current = self.first_item();
                self.mission_run = Run::NotStarted;
            }
        }
        MavMissionResult::MAV_MISSION_ACCEPTED
    }

    /// The first item AUTO runs: 1 (item 0 is home), or 0 with no mission.
    pub(super) fn first_item(&self) -> u16 {
        u16::from(self.mission.len() > 1)
    }

    /// Whether an uploaded mission item is one we can run (item 0, home, is not run).
    pub(super) fn flyable(item: &MISSION_ITEM_INT_DATA) -> Result<(), MavMissionResult> {
        use MavFrame::*;
        match item.command {
            _ if item.seq == 0 => return Ok(()),
            MavCmd::MAV_CMD_DO_CHANGE_SPEED if item.param2.is_finite() => return Ok(()),
            MavCmd::MAV_CMD_DO_CHANGE_SPEED => return Err(MavMissionResult::MAV_MISSION_INVALID_PARAM2),
            MavCmd::MAV_CMD_NAV_WAYPOINT => {}
            _ => return Err(MavMissionResult::MAV_MISSION_UNSUPPORTED),
        }
        if !matches!(
            item.frame,
            MAV_FRAME_GLOBAL | MAV_FRAME_GLOBAL_INT | MAV_FRAME_GLOBAL_RELATIVE_ALT | MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        ) {
            return Err(MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME);
        }
        if item.x.unsigned_abs() > 900_000_000 || item.y.unsigned_abs() > 1_800_000_000 || !item.z.is_finite() {
            return Err(MavMissionResult::MAV_MISSION_INVALID);
        }
        Ok(())
    }

    pub(super) fn item_position(&self, item: &MISSION_ITEM_INT_DATA) -> Vector3<f64> {
        let relative = matches!(
            item.frame,
            MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        );
        let alt = if relative {
            self.spec.site.origin[2] + item.z as f64
        } else {
            item.z as f64
        };
        self.at_altitude(
            self.spec
                .site
                .ned_of_global(item.x as f64 * 1e-7, item.y as f64 * 1e-7, alt),
        )
    }

    /// An uploaded item, as ArduPilot's `MissionItemProtocol::handle_mission_item` takes it:
    /// any item but the one asked for is answered INVALID_SEQUENCE and the upload stays open;
    /// an item the list cannot hold ends it.
    pub(super) fn take_item(&mut self, sender: (u8, u8), item: &MISSION_ITEM_INT_DATA) {
        let Some(u) = &mut self.upload else { return };
        if u.kind != item.mission_type {
            return;
        }
        let (next, kind) = (u.items.len() as u16, u.kind);
        if item.seq != next {
            self.mission_ack(sender, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE, kind);
            return;
        }
        if u.from != sender {
            self.mission_ack(sender, MavMissionResult::MAV_MISSION_DENIED, kind);
            return;
        }
        if let Err(why) = Self::valid_item(kind, item) {
            self.mission_ack(sender, why, kind);
            self.upload = None;
            return;
        }
        u.items.push(item.clone());
        u.received_at = self.wall_s;
        if u.items.len() as u16 == u.count {
            let done = self.upload.take().expect("upload in progress");
            let result = self.store(kind, done.items);
            self.mission_ack(sender, result, kind);
        } else {
            self.request_item(next + 1);
        }
    }

    /// An open upload: the request asked again each second without an item, the upload
    /// cancelled after [`UPLOAD_TIMEOUT_S`] (ArduPilot's `MissionItemProtocol::update`, and
    /// its fence's and rally's `timeout` texts).
    pub(super) fn retry_upload(&mut self) {
        let Some(u) = &mut self.upload else { return };
        if self.wall_s - u.received_at > UPLOAD_TIMEOUT_S {
            let (from, kind) = (u.from, u.kind);
            self.upload = None;
            let list = match kind {
                MavMissionType::MAV_MISSION_TYPE_FENCE => "Fence",
                MavMissionType::MAV_MISSION_TYPE_RALLY => "Rally",
                _ => "Mission",
            };
            self.say(MavSeverity::MAV_SEVERITY_WARNING, &format!("{list} upload timeout"));
            self.mission_ack(from, MavMissionResult::MAV_MISSION_OPERATION_CANCELLED, kind);
        } else if self.wall_s - u.asked_at >= UPLOAD_RETRY_S {
            let next = u.items.len() as u16;
            self.request_item(next);
        }
    }

    /// An upload open from someone else: ArduPilot answers DENIED to its count, and to any
    /// download while one is open.
    fn busy(&self, sender: (u8, u8)) -> bool {
        self.upload.as_ref().is_some_and(|u| u.from != sender)
    }

    /// In AUTO, the DO items at the current place in the sequence are done at once.
    pub(super) fn run_do_items(&mut self) {
        while self.role() == Some(Control::Auto) {
            let Some(item) = self.mission.get(self.current as usize) else {
                return;
            };
            if item.command != MavCmd::MAV_CMD_DO_CHANGE_SPEED {
                return;
            }
            if item.param2 > 0.0 {
                self.spec.max_speed = item.param2 as f64;
            }
            self.advance();
        }
    }

    /// On to the next item; after the last, hold there (as ArduRover does).
    pub(super) fn advance(&mut self) {
        if (self.current as usize) + 1 < self.mission.len() {
            self.current += 1;
        } else {
            self.mission_run = Run::Complete;
            self.set_mode(self.spec.frame.hold_mode());
        }
        self.out.push(self.mission_current());
    }

    pub(super) fn item_reached(&mut self) {
        let seq = self.current;
        self.out
            .push(MavMessage::MISSION_ITEM_REACHED(MISSION_ITEM_REACHED_DATA { seq }));
        self.advance();
        self.run_do_items();
    }

    /// A message of the mission protocol (any other is ignored).
    ///
    /// Long because it is one arm per message of the mission protocol, as ArduPilot's handler has
    /// them.
    pub(super) fn mission_message(&mut self, sender: (u8, u8), msg: &MavMessage) {
        match msg {
            MavMessage::MISSION_COUNT(c) => {
                let room = match c.mission_type {
                    MavMissionType::MAV_MISSION_TYPE_MISSION | MavMissionType::MAV_MISSION_TYPE_RALLY => {
                        Some(MAX_MISSION_ITEMS)
                    }
                    MavMissionType::MAV_MISSION_TYPE_FENCE => Some(MAX_FENCE_ITEMS),
                    _ => None,
                };
                match room {
                    _ if self.busy(sender) => {
                        self.mission_ack(sender, MavMissionResult::MAV_MISSION_DENIED, c.mission_type)
                    }
                    None => self.mission_ack(sender, MavMissionResult::MAV_MISSION_UNSUPPORTED, c.mission_type),
                    Some(_) if c.count == 0 => {
                        let r = self.store(c.mission_type, vec![]);
                        self.mission_ack(sender, r, c.mission_type);
                    }
                    Some(n) if c.count > n => {
                        self.mission_ack(sender, MavMissionResult::MAV_MISSION_NO_SPACE, c.mission_type)
                    }
                    // A second count from the same sender restarts its upload.
                    Some(_) => {
                        self.upload = Some(Upload {
                            kind: c.mission_type,
                            count: c.count,
                            items: vec![],
                            from: sender,
                            asked_at: self.wall_s,
                            received_at: self.wall_s,
                        });
                        self.request_item(0);
                    }
                }
            }
            MavMessage::MISSION_ITEM_INT(item) => self.take_item(sender, item),
            MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA { mission_type, .. })
            | MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA { mission_type, .. })
                if self.upload.as_ref().is_some_and(|u| u.kind == *mission_type) =>
            {
                self.mission_ack(sender, MavMissionResult::MAV_MISSION_DENIED, *mission_type)
            }
            MavMessage::MISSION_REQUEST_LIST(r) => {
                let mission_type = r.mission_type;
                match self.items(mission_type).map(|v| v.len() as u16) {
                    Some(count) => self.out.push(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                        count,
                        target_system: sender.0,
                        target_component: sender.1,
                        mission_type,
                        ..Default::default()
                    })),
                    None => self.mission_ack(sender, MavMissionResult::MAV_MISSION_UNSUPPORTED, mission_type),
                }
            }
            MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA { seq, mission_type, .. })
            | MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA { seq, mission_type, .. }) => {
                match self.items(*mission_type).and_then(|v| v.get(*seq as usize)) {
                    Some(item) => {
                        let mut item = item.clone();
                        if *mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION && *seq == 0 {
                            // Item 0 reads back as home, as ArduPilot keeps it.
                            let (lat, lon, alt) = self.spec.site.global_of(&self.home);
                            (item.command, item.frame, item.x, item.y, item.z) = (
                                MavCmd::MAV_CMD_NAV_WAYPOINT,
                                MavFrame::MAV_FRAME_GLOBAL,
                                (lat * 1e7).round() as i32,
                                (lon * 1e7).round() as i32,
                                alt as f32,
                            );
                        }
                        let current = *mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION && *seq == self.current;
                        (
                            item.target_system,
                            item.target_component,
                            item.current,
                            item.mission_type,
                        ) = (sender.0, sender.1, u8::from(current), *mission_type);
                        self.out.push(MavMessage::MISSION_ITEM_INT(item));
                    }
                    None => self.mission_ack(sender, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE, *mission_type),
                }
            }
            MavMessage::MISSION_CLEAR_ALL(c) => {
                let all = c.mission_type == MavMissionType::MAV_MISSION_TYPE_ALL;
                for kind in [
                    MavMissionType::MAV_MISSION_TYPE_MISSION,
                    MavMissionType::MAV_MISSION_TYPE_FENCE,
                    MavMissionType::MAV_MISSION_TYPE_RALLY,
                ] {
                    if all || kind == c.mission_type {
                        self.store(kind, vec![]);
                    }
                }
                self.mission_ack(sender, MavMissionResult::MAV_MISSION_ACCEPTED, c.mission_type);
            }
            MavMessage::MISSION_SET_CURRENT(s) if (s.seq as usize) < self.mission.len() => {
                self.current = s.seq;
                self.out.push(self.mission_current());
            }
            _ => {}
        }
    }
}
