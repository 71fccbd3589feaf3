//! What a simulated autopilot is: its airframe, system id, site, speeds and speed-up, and its
//! safety settings (the parameters a ground station reads and sets, [`super::params`]).

use super::modes::Frame;
use super::safety::{Action, Safety};
use fleet_mission::site::Site;

/// A boat pivots (stops and turns in place) when its goal is more than this far off its bow
/// (ArduRover's `WP_PIVOT_ANGLE`, 60 degrees by default); under it, it turns on its radius.
pub const PIVOT_ANGLE_DEG: f64 = 60.0;

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
    /// A boat's turning radius under way (m; ArduRover's `TURN_RADIUS`): it pivots only when the
    /// goal is more than [`PIVOT_ANGLE_DEG`] off its bow.
    pub turn_radius: f64,
    /// A mission item counts as reached within this distance (m; `WP_RADIUS`, a copter's
    /// `WPNAV_RADIUS` in cm).
    pub wp_radius: f64,
    /// Simulated seconds from boot to the GPS fix (no position, no EKF origin before).
    pub gps_delay_s: f64,
    /// A copter armed on the ground and not told to take off disarms itself after this long
    /// (simulated seconds; ArduCopter's `DISARM_DELAY`, 10 s by default).
    pub disarm_delay_s: f64,
    /// Simulated seconds per wall second.
    pub speedup: f64,
    pub safety: Safety,
    /// None unless a test sets SITL's `SIM_WIND_SPD`.
    pub wind: Wind,
}

/// A steady push on an armed vehicle, as SITL's wind (`SIM_WIND_SPD` m/s, `SIM_WIND_DIR` the
/// degrees it comes from, 0 from the north): a fault a test injects, never a mission setting.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Wind {
    pub speed: f64,
    pub from_deg: f64,
}

impl Wind {
    /// The push (m/s, local NED): toward where the wind goes.
    pub fn push(&self) -> nalgebra::Vector3<f64> {
        let to = (self.from_deg + 180.0).to_radians();
        nalgebra::Vector3::new(self.speed * to.cos(), self.speed * to.sin(), 0.0)
    }
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
            fence_margin: m.fence_margin_m,
            ..Safety::default()
        };
        Self {
            frame,
            sysid,
            site,
            max_speed,
            turn_rate: m.boat_turn_rate_dps.to_radians(),
            cruise_alt: m.cruise_alt_m,
            turn_radius: m.turn_radius_m,
            wp_radius: m.wp_radius_m,
            gps_delay_s: m.sim_gps_delay_s,
            disarm_delay_s: 10.0,
            speedup: m.sim_speedup,
            safety,
            wind: Wind::default(),
        }
    }
}
