//! What the autopilot reports: HEARTBEAT, SYS_STATUS, positions at 10 Hz, and the slow
//! messages (battery, home, mission, fence, UTC) at 1 Hz.

use super::*;

impl SimAutopilot {
    pub(super) fn time_boot_ms(&self) -> u32 {
        (self.wall_s * 1000.0) as u32
    }

    pub fn heartbeat(&self) -> MavMessage {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED;
        if self.armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        match self.role() {
            Some(Control::Guided) => base |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED,
            Some(Control::Auto) => {
                base |= MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
            }
            _ => {}
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: self.mode,
            mavtype: self.spec.frame.mav_type(),
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode: base,
            system_status: match (self.failsafe, self.armed) {
                (Some(_), _) => MavState::MAV_STATE_CRITICAL,
                (None, true) => MavState::MAV_STATE_ACTIVE,
                (None, false) => MavState::MAV_STATE_STANDBY,
            },
            mavlink_version: 3,
        })
    }

    /// The charge left (a fraction) and the pack's voltage (mV): a 3-cell pack, 12.6 V full,
    /// 11.0 V empty.
    pub(super) fn battery_now(&self) -> (f64, u16) {
        let fraction = self.remaining_mah() / self.spec.safety.battery_mah;
        (fraction, (11_000.0 + 1_600.0 * fraction) as u16)
    }

    pub fn sys_status(&self) -> MavMessage {
        let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_BATTERY
            | MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK;
        // The GPS is healthy with its fix, the pre-arm bit while the arming checks pass.
        let mut unhealthy = MavSysStatusSensor::empty();
        if !self.has_fix() {
            unhealthy |= MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS;
        }
        if self.arming_refusal().is_some() {
            unhealthy |= MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK;
        }
        // The geofence bit is healthy while there is no breach, whether or not a fence is
        // enabled (ArduPilot's rule): ground stations announce "fence breach" when it is not.
        let fence = MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE;
        let enforced = if self.spec.safety.fence_enable {
            fence
        } else {
            MavSysStatusSensor::empty()
        };
        MavMessage::SYS_STATUS(SYS_STATUS_DATA {
            onboard_control_sensors_present: sensors | enforced,
            onboard_control_sensors_enabled: sensors | enforced,
            onboard_control_sensors_health: (sensors - unhealthy)
                | if self.breached {
                    MavSysStatusSensor::empty()
                } else {
                    fence
                },
            load: 150,
            voltage_battery: self.battery_now().1,
            current_battery: (self.draw_a * 100.0).round() as i16,
            battery_remaining: (100.0 * self.battery_now().0).round() as i8,
            ..Default::default()
        })
    }

    /// The position messages (sent at 10 Hz), once there is a fix: LOCAL_POSITION_NED from
    /// the EKF origin, GLOBAL_POSITION_INT on the Earth.
    pub fn position(&self) -> Vec<MavMessage> {
        let Some(origin) = self.ekf_origin else {
            return vec![];
        };
        let local = self.pos - origin;
        let (lat, lon, alt) = self.spec.site.global_of(&self.pos);
        let home_alt = self.spec.site.global_of(&self.home).2;
        let hdg = (self.heading.to_degrees().rem_euclid(360.0) * 100.0) as u16;
        let t = self.time_boot_ms();
        let mut out = vec![
            MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms: t,
                lat: (lat * 1e7).round() as i32,
                lon: (lon * 1e7).round() as i32,
                alt: (alt * 1000.0).round() as i32,
                relative_alt: ((alt - home_alt) * 1000.0).round() as i32,
                vx: (self.vel.x * 100.0) as i16,
                vy: (self.vel.y * 100.0) as i16,
                vz: (self.vel.z * 100.0) as i16,
                hdg,
            }),
            MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: t,
                x: local.x as f32,
                y: local.y as f32,
                z: local.z as f32,
                vx: self.vel.x as f32,
                vy: self.vel.y as f32,
                vz: self.vel.z as f32,
            }),
        ];
        if let (Some(Control::Guided), Some(g)) = (self.role(), self.goal) {
            let g = g - origin;
            out.push(MavMessage::POSITION_TARGET_LOCAL_NED(POSITION_TARGET_LOCAL_NED_DATA {
                time_boot_ms: t,
                x: g.x as f32,
                y: g.y as f32,
                z: g.z as f32,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            }));
        }
        out
    }

    /// The messages sent once a second besides HEARTBEAT and SYS_STATUS, as ArduPilot streams
    /// them: BATTERY_STATUS, HOME_POSITION, MISSION_CURRENT, SYSTEM_TIME (its GPS's UTC against
    /// its boot clock: what times a NAMED_VALUE_FLOAT), and FENCE_STATUS while a fence is
    /// enforced (MAVSDK reads battery and home only from these).
    pub fn slow(&self) -> Vec<MavMessage> {
        let (fraction, millivolts) = self.battery_now();
        let mut cells = [u16::MAX; 10];
        cells[0] = millivolts;
        let mut out = vec![
            MavMessage::BATTERY_STATUS(BATTERY_STATUS_DATA {
                current_consumed: self.consumed_mah.round() as i32,
                energy_consumed: -1,
                temperature: i16::MAX,
                voltages: cells,
                current_battery: (self.draw_a * 100.0).round() as i16,
                battery_function: MavBatteryFunction::MAV_BATTERY_FUNCTION_ALL,
                mavtype: MavBatteryType::MAV_BATTERY_TYPE_LIPO,
                battery_remaining: (100.0 * fraction).round() as i8,
                ..Default::default()
            }),
            self.home_position(),
            self.mission_current(),
            MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
                time_unix_usec: ((self.boot_unix_s + self.wall_s) * 1e6) as u64,
                time_boot_ms: self.time_boot_ms(),
            }),
        ];
        out.extend(self.fence_status());
        out.extend(self.readiness_reports());
        out
    }

    /// FENCE_STATUS (sent at 1 Hz while a fence is enforced).
    pub fn fence_status(&self) -> Option<MavMessage> {
        self.spec.safety.fence_enable.then(|| {
            MavMessage::FENCE_STATUS(FENCE_STATUS_DATA {
                breach_status: u8::from(self.breached),
                breach_count: self.breach_count,
                breach_type: if self.breached {
                    FenceBreach::FENCE_BREACH_BOUNDARY
                } else {
                    FenceBreach::FENCE_BREACH_NONE
                },
                breach_time: (self.wall_s * 1000.0) as u32,
                ..Default::default()
            })
        })
    }

    /// MISSION_CURRENT with the mission's state, as MAVSDK reads progress from it: the total
    /// leaves out home (item 0).
    pub fn mission_current(&self) -> MavMessage {
        let auto = self.role() == Some(Control::Auto);
        let mission_state = match (self.mission.len() > 1, self.mission_run) {
            (false, _) => MissionState::MISSION_STATE_NO_MISSION,
            (true, Run::NotStarted) => MissionState::MISSION_STATE_NOT_STARTED,
            (true, Run::Complete) => MissionState::MISSION_STATE_COMPLETE,
            (true, Run::Started) if auto => MissionState::MISSION_STATE_ACTIVE,
            (true, Run::Started) => MissionState::MISSION_STATE_PAUSED,
        };
        let total = if self.mission.len() > 1 {
            self.mission.len() as u16 - 1
        } else {
            u16::MAX
        };
        let seq = if self.mission_run == Run::Complete {
            self.mission.len() as u16
        } else {
            self.current
        };
        MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA {
            seq,
            total,
            mission_state,
            mission_mode: if auto { 1 } else { 2 },
            ..Default::default()
        })
    }
}
