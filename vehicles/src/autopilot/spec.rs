//! What a simulated autopilot is: its airframe, system id, site, speeds and speed-up, and its
//! safety settings (the parameters a ground station reads and sets, [`super::params`]).

use super::modes::Frame;
use super::safety::{Action, Safety};
use fleet_mission::site::Site;

#[derive(Debug, Clone)]
pub struct SimSpec {
    pub frame: Frame,
    pub sysid: u8,
    pub site: Site,
    /// m/s
    pub max_speed: f64,
    /// rad/s (boats only)
    pub turn_rate: f64,
    /// m above the origin (multirotors)
    pub cruise_alt: f64,
    /// Simulated seconds per wall second.
    pub speedup: f64,
    pub safety: Safety,
}

impl SimSpec {
    /// The simulated airframe the mission's `[mavlink]` section describes.
    pub fn from_config(frame: Frame, sysid: u8, site: Site, m: &fleet_mission::config::MavlinkConfig) -> Self {
        let max_speed = match frame {
            Frame::Boat => m.boat_speed_ms,
            Frame::Multirotor => m.multirotor_speed_ms,
        };
        let action = |name: &str| Action::from_name(name).unwrap_or(Action::Rtl);
        let safety = Safety {
            fence_action: action(&m.fence_action),
            battery_mah: m.battery_mah,
            battery_low_mah: m.battery_low_mah,
            low_battery_action: action(&m.low_battery_action),
            ..Safety::default()
        };
        Self {
            frame,
            sysid,
            site,
            max_speed,
            turn_rate: m.boat_turn_rate_dps.to_radians(),
            cruise_alt: m.cruise_alt_m,
            speedup: m.sim_speedup,
            safety,
        }
    }
}
