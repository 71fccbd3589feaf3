//! Flight modes as ArduPilot numbers them (HEARTBEAT `custom_mode`), so QGroundControl,
//! MAVProxy and pymavlink show our simulated autopilots' modes by name and set them with
//! their usual commands. What matters to the fleet is one thing: in GUIDED the planner
//! drives the vehicle; in any other mode the operator (or its mission) does, and the vehicle
//! is left out of the allocation.

use mavlink::dialects::ardupilotmega::MavType;

/// Who drives the vehicle in a mode: what a mode means to the fleet and to the simulator.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
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
    fn table(self) -> &'static [(u32, &'static str, Control)] {
        match self {
            // ArduRover
            Self::Boat => &[
                (0, "MANUAL", Control::Hold),
                (4, "HOLD", Control::Hold),
                (5, "LOITER", Control::Hold),
                (10, "AUTO", Control::Auto),
                (11, "RTL", Control::Return),
                (12, "SMART_RTL", Control::Return),
                (15, "GUIDED", Control::Guided),
            ],
            // ArduCopter
            Self::Multirotor => &[
                (0, "STABILIZE", Control::Hold),
                (2, "ALT_HOLD", Control::Hold),
                (3, "AUTO", Control::Auto),
                (4, "GUIDED", Control::Guided),
                (5, "LOITER", Control::Hold),
                (6, "RTL", Control::Return),
                (16, "POSHOLD", Control::Hold),
                (17, "BRAKE", Control::Hold),
            ],
        }
    }

    pub fn role(self, custom_mode: u32) -> Option<Control> {
        self.table().iter().find(|m| m.0 == custom_mode).map(|m| m.2)
    }

    pub fn name(self, custom_mode: u32) -> String {
        self.table()
            .iter()
            .find(|m| m.0 == custom_mode)
            .map_or_else(|| format!("MODE({custom_mode})"), |m| m.1.to_string())
    }

    /// The mode a role is entered by (the first of the table with it).
    pub fn mode(self, role: Control) -> u32 {
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
        assert_eq!(Frame::Boat.mode(Control::Guided), 15);
        assert_eq!(Frame::Multirotor.mode(Control::Guided), 4);
        assert_eq!(Frame::Boat.role(4), Some(Control::Hold));
        assert_eq!(
            Frame::Multirotor.role(Frame::Multirotor.hold_mode()),
            Some(Control::Hold)
        );
        assert_eq!(Frame::Boat.name(10), "AUTO");
        assert_eq!(Frame::Boat.role(99), None);
    }
}
