//! Modes, arming and commands (COMMAND_LONG, COMMAND_INT) and parameters, answered as
//! ArduPilot answers them.

use super::*;

/// The messages this autopilot streams (what MAV_CMD_SET_MESSAGE_INTERVAL may ask for).
const STREAMED: [u32; 12] = [
    HEARTBEAT_DATA::ID,
    SYS_STATUS_DATA::ID,
    GLOBAL_POSITION_INT_DATA::ID,
    LOCAL_POSITION_NED_DATA::ID,
    GPS_RAW_INT_DATA::ID,
    EKF_STATUS_REPORT_DATA::ID,
    BATTERY_STATUS_DATA::ID,
    HOME_POSITION_DATA::ID,
    MISSION_CURRENT_DATA::ID,
    SYSTEM_TIME_DATA::ID,
    FENCE_STATUS_DATA::ID,
    GPS_GLOBAL_ORIGIN_DATA::ID,
];

impl SimAutopilot {
    pub(super) fn ack(&mut self, command: MavCmd, ok: bool) {
        let result = if ok {
            MavResult::MAV_RESULT_ACCEPTED
        } else {
            MavResult::MAV_RESULT_DENIED
        };
        self.out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command,
            result,
            ..Default::default()
        }));
    }

    pub(super) fn set_mode(&mut self, mode: u32) -> bool {
        let Some(role) = self.spec.frame.role(mode) else {
            return false;
        };
        if role == Control::Auto && self.mode != mode {
            if self.mission_run == Run::Complete {
                // AUTO again after the end: from the start, as ArduPilot does.
                self.current = self.first_item();
            }
            self.current = self.current.clamp(
                self.first_item(),
                self.mission.len().saturating_sub(1).max(self.first_item() as usize) as u16,
            );
            self.mission_run = Run::Started;
        }
        if role != Control::Guided {
            self.goal = None;
        }
        self.mode = mode;
        true
    }

    pub(super) fn command(&mut self, command: MavCmd, p: [f32; 7], global: Option<(f64, f64, f64)>) {
        use MavCmd::*;
        let ok = match command {
            MAV_CMD_COMPONENT_ARM_DISARM => {
                let done = self.arm_disarm(p[0] >= 0.5, p[1]);
                // A refused arming is FAILED (the checks said no), as ArduPilot answers it.
                let result = if done {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_FAILED
                };
                return self.out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                    command,
                    result,
                    ..Default::default()
                }));
            }
            MAV_CMD_NAV_TAKEOFF => self.takeoff(p[6]),
            // The bridge asks for the messages it reads at the rates it needs: taken for those
            // this autopilot streams (at its own rates), unsupported for others.
            MAV_CMD_SET_MESSAGE_INTERVAL => STREAMED.contains(&(p[0] as u32)),
            MAV_CMD_DO_SET_MODE => self.set_mode(p[1] as u32),
            MAV_CMD_NAV_RETURN_TO_LAUNCH => self.set_mode(self.spec.frame.mode(Control::Return)),
            MAV_CMD_MISSION_START => self.mission.len() > 1 && self.set_mode(self.spec.frame.mode(Control::Auto)),
            MAV_CMD_DO_PAUSE_CONTINUE if p[0] < 0.5 => {
                self.mode_before_pause = Some(self.mode);
                self.set_mode(self.spec.frame.hold_mode())
            }
            MAV_CMD_DO_PAUSE_CONTINUE => {
                let back = self
                    .mode_before_pause
                    .take()
                    .unwrap_or(self.spec.frame.mode(Control::Guided));
                self.set_mode(back)
            }
            MAV_CMD_DO_REPOSITION => {
                // COMMAND_INT carries degrees * 1e7 in x, y; COMMAND_LONG degrees in params 5, 6.
                let (lat, lon, alt) = global.unwrap_or((p[4] as f64, p[5] as f64, p[6] as f64));
                if lat.is_finite() && lon.is_finite() && lat.abs() <= 90.0 && lon.abs() <= 180.0 {
                    let up = if alt.is_finite() { alt } else { self.spec.cruise_alt };
                    let ned = self.at_altitude(self.spec.site.ned_of_global(lat, lon, self.spec.site.origin[2] + up));
                    if self.fenced_out(&ned) && self.spec.frame == Frame::Multirotor {
                        // ArduCopter's guided destination outside the fence: FAILED.
                        return self.out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                            command,
                            result: MavResult::MAV_RESULT_FAILED,
                            ..Default::default()
                        }));
                    } else if self.fenced_out(&ned) {
                        false
                    } else {
                        self.set_mode(self.spec.frame.mode(Control::Guided));
                        self.goal = Some(ned);
                        true
                    }
                } else {
                    false
                }
            }
            // Ground stations ask for home on connecting (MAVProxy, QGC); the message follows
            // the ack, as ArduPilot sends it.
            MAV_CMD_GET_HOME_POSITION => return self.send_home(command),
            MAV_CMD_REQUEST_MESSAGE if p[0] as u32 == HOME_POSITION_DATA::ID => return self.send_home(command),
            // The EKF origin is said once, at the fix; asked for, again (none before the fix).
            MAV_CMD_REQUEST_MESSAGE if p[0] as u32 == GPS_GLOBAL_ORIGIN_DATA::ID => {
                let origin = self.gps_global_origin();
                self.ack(command, origin.is_some());
                return self.out.extend(origin);
            }
            _ => {
                self.out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                    command,
                    result: MavResult::MAV_RESULT_UNSUPPORTED,
                    ..Default::default()
                }));
                return;
            }
        };
        self.ack(command, ok);
    }

    /// PARAM_VALUE of parameter `index` (nothing for an index it does not have).
    pub(super) fn param_value(&mut self, index: usize) {
        if let Some((name, value)) = params::by_index(&self.spec, index) {
            self.out.push(MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
                param_value: value,
                param_count: params::count(self.spec.frame) as u16,
                param_index: index as u16,
                param_id: name.into(),
                param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
            }));
        }
    }

    /// Accept `command` and send HOME_POSITION after the ack.
    pub(super) fn send_home(&mut self, command: MavCmd) {
        self.ack(command, true);
        let home = self.home_position();
        self.out.push(home);
    }

    /// HOME_POSITION: where it booted, which RTL returns to; x, y, z from the EKF origin.
    pub(super) fn home_position(&self) -> MavMessage {
        let (lat, lon, alt) = self.spec.site.global_of(&self.home);
        let local = self.home - self.ekf_origin.unwrap_or(self.home);
        MavMessage::HOME_POSITION(HOME_POSITION_DATA {
            latitude: (lat * 1e7).round() as i32,
            longitude: (lon * 1e7).round() as i32,
            altitude: (alt * 1e3).round() as i32,
            x: local.x as f32,
            y: local.y as f32,
            z: local.z as f32,
            q: [1.0, 0.0, 0.0, 0.0],
            ..Default::default()
        })
    }

    /// PARAM_REQUEST_LIST, PARAM_REQUEST_READ, PARAM_SET.
    pub(super) fn param_message(&mut self, msg: &MavMessage) {
        match msg {
            MavMessage::PARAM_REQUEST_LIST(_) => {
                for i in 0..params::count(self.spec.frame) {
                    self.param_value(i);
                }
            }
            MavMessage::PARAM_REQUEST_READ(r) => {
                // By index, or by name when the index is -1 (the protocol's rule).
                let index = if r.param_index >= 0 {
                    Some(r.param_index as usize)
                } else {
                    r.param_id
                        .to_str()
                        .ok()
                        .and_then(|n| params::index_of(self.spec.frame, n))
                };
                if let Some(i) = index {
                    self.param_value(i);
                }
            }
            MavMessage::PARAM_SET(p) => {
                // Unknown names get no answer (as ArduPilot); a refused value is answered with
                // the one in force, so the ground station sees it did not take.
                if let Some(i) = p
                    .param_id
                    .to_str()
                    .ok()
                    .and_then(|n| params::index_of(self.spec.frame, n))
                {
                    params::set(&mut self.spec, i, p.param_value);
                    self.param_value(i);
                }
            }
            _ => {}
        }
    }
}
