//! What the simulated autopilot does when something goes wrong, set as ArduPilot's parameters
//! are (`FENCE_ENABLE`, `FENCE_ACTION`, `BATT_CAPACITY`, `BATT_LOW_MAH`, `BATT_FS_LOW_ACT`): a
//! fence breach triggers the fence action, a battery drained below its low mark the battery
//! failsafe's action. The battery drains with use: a draw at rest when armed, up to
//! `MAX_DRAW_A` at full speed.

/// A failsafe's action, numbered as ArduRover's `FENCE_ACTION` / `FS_ACTION`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, strum::EnumString)]
#[strum(serialize_all = "lowercase")]
pub enum Action {
    /// Report only, and go on (`report` in a mission file, as ArduPilot calls it).
    #[strum(serialize = "continue", serialize = "report")]
    Continue = 0,
    /// Return to the nearest rally point (home without one).
    Rtl = 1,
    /// Stop where it is.
    Hold = 2,
}

impl Action {
    /// From a parameter's value.
    pub fn from_param(v: f32) -> Option<Self> {
        match v {
            0.0 => Some(Self::Continue),
            1.0 => Some(Self::Rtl),
            2.0 => Some(Self::Hold),
            _ => None,
        }
    }

    /// From a mission file's name for it.
    pub fn from_name(s: &str) -> Option<Self> {
        s.parse().ok()
    }
}

/// Battery draw (A): disarmed, armed at rest, and at full speed.
pub const IDLE_DRAW_A: f64 = 0.05;
pub const ARMED_DRAW_A: f64 = 1.0;
pub const MAX_DRAW_A: f64 = 10.0;

/// The autopilot's safety settings.
#[derive(Debug, Clone, PartialEq)]
pub struct Safety {
    /// Whether the uploaded fence is enforced (a guided target outside is refused, a breach
    /// triggers `fence_action`).
    pub fence_enable: bool,
    pub fence_action: Action,
    /// Arming is refused within this distance inside the fence (m; `FENCE_MARGIN`).
    pub fence_margin: f64,
    /// Battery capacity, and the charge left (mAh) at which `low_battery_action` is taken.
    pub battery_mah: f64,
    pub battery_low_mah: f64,
    pub low_battery_action: Action,
    /// The charge at boot (mAh; `None`: full), for a pack that was not charged.
    pub battery_start_mah: Option<f64>,
    /// RTL goes to the nearest of the rally points and home, not of the rally points alone
    /// (`RALLY_INCL_HOME`, 1 by default: `AP_Rally::calc_best_rally_or_home_location`).
    pub rally_include_home: bool,
}

impl Default for Safety {
    /// ArduPilot's defaults where it has them (no fence enforced, RTL on a breach once it is,
    /// RTL on a low battery), and a battery of 20 Ah with a low mark at 20 %: two hours at
    /// full speed.
    fn default() -> Self {
        Self {
            fence_enable: false,
            fence_action: Action::Rtl,
            fence_margin: 2.0,
            battery_mah: 20_000.0,
            battery_low_mah: 4_000.0,
            low_battery_action: Action::Rtl,
            battery_start_mah: None,
            rally_include_home: true,
        }
    }
}
