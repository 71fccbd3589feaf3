//! What the simulated autopilot does when something goes wrong, set as ArduPilot's parameters
//! are (`FENCE_ENABLE`, `FENCE_ACTION`): a fence breach triggers the fence action.

/// A failsafe's action, numbered as ArduRover's `FENCE_ACTION` / `FS_ACTION`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// Report only, and go on.
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
        match s {
            "continue" | "report" => Some(Self::Continue),
            "rtl" => Some(Self::Rtl),
            "hold" => Some(Self::Hold),
            _ => None,
        }
    }
}

/// The autopilot's safety settings.
#[derive(Debug, Clone, PartialEq)]
pub struct Safety {
    /// Whether the uploaded fence is enforced (a guided target outside is refused, a breach
    /// triggers `fence_action`).
    pub fence_enable: bool,
    pub fence_action: Action,
}

impl Default for Safety {
    /// ArduPilot's defaults: no fence enforced; RTL on a breach once it is.
    fn default() -> Self {
        Self { fence_enable: false, fence_action: Action::Rtl }
    }
}
