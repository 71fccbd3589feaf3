//! Flight modes as ArduPilot numbers them (HEARTBEAT `custom_mode`), so QGroundControl,
//! MAVProxy and pymavlink show our simulated autopilots' modes by name and set them with
//! their usual commands. What matters to the fleet is one thing: in GUIDED the planner
//! drives the vehicle; in any other mode the operator (or its mission) does, and the vehicle
//! is left out of the allocation.

use mavlink::dialects::ardupilotmega::MavType;

/// What a mode means to the fleet and to the simulator.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The fleet's planner sends guided targets.
    Guided,
    /// Flies the uploaded mission.
    Auto,
    /// Stays where it is (operator hold, loiter, brake, manual with sticks centred).
    Hold,
    /// Goes back to where it was armed.
    Return,
}

/// The two airframes we simulate and bridge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    Boat,
    Multirotor,
}

impl Frame {
    pub fn of(kind: fleet_mission::protocol::VehicleKind) -> Self {
        match kind {
            fleet_mission::protocol::VehicleKind::Boat => Self::Boat,
            fleet_mission::protocol::VehicleKind::Aerial => Self::Multirotor,
        }
    }

    pub fn mav_type(self) -> MavType {
        match self {
            Self::Boat => MavType::MAV_TYPE_SURFACE_BOAT,
            Self::Multirotor => MavType::MAV_TYPE_QUADROTOR,
        }
    }

    /// (number, name, role) of the modes we know.
    fn table(self) -> &'static [(u32, &'static str, Role)] {
        match self {
            // ArduRover
            Self::Boat => &[
                (0, "MANUAL", Role::Hold),
                (4, "HOLD", Role::Hold),
                (5, "LOITER", Role::Hold),
                (10, "AUTO", Role::Auto),
                (11, "RTL", Role::Return),
                (12, "SMART_RTL", Role::Return),
                (15, "GUIDED", Role::Guided),
            ],
            // ArduCopter
            Self::Multirotor => &[
                (0, "STABILIZE", Role::Hold),
                (2, "ALT_HOLD", Role::Hold),
                (3, "AUTO", Role::Auto),
                (4, "GUIDED", Role::Guided),
                (5, "LOITER", Role::Hold),
                (6, "RTL", Role::Return),
                (16, "POSHOLD", Role::Hold),
                (17, "BRAKE", Role::Hold),
            ],
        }
    }

    pub fn role(self, custom_mode: u32) -> Option<Role> {
        self.table().iter().find(|m| m.0 == custom_mode).map(|m| m.2)
    }

    pub fn name(self, custom_mode: u32) -> String {
        self.table()
            .iter()
            .find(|m| m.0 == custom_mode)
            .map_or_else(|| format!("MODE({custom_mode})"), |m| m.1.to_string())
    }

    /// The mode a role is entered by (the first of the table with it).
    pub fn mode(self, role: Role) -> u32 {
        self.table()
            .iter()
            .find(|m| m.2 == role)
            .map(|m| m.0)
            .expect("every role has a mode")
    }

    /// The mode an operator's hold (MAV_CMD_DO_PAUSE_CONTINUE 0) enters.
    pub fn hold_mode(self) -> u32 {
        match self {
            Self::Boat => 4,
            Self::Multirotor => 17,
        }
    }

    /// What an autopilot boots in.
    pub fn boot_mode(self) -> u32 {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_have_their_ardupilot_numbers() {
        assert_eq!(Frame::Boat.mode(Role::Guided), 15);
        assert_eq!(Frame::Multirotor.mode(Role::Guided), 4);
        assert_eq!(Frame::Boat.role(4), Some(Role::Hold));
        assert_eq!(Frame::Multirotor.role(Frame::Multirotor.hold_mode()), Some(Role::Hold));
        assert_eq!(Frame::Boat.name(10), "AUTO");
        assert_eq!(Frame::Boat.role(99), None);
    }
}
