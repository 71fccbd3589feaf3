//! The simulated autopilot's parameters, under ArduPilot's names, so a ground station's
//! parameter download finishes and shows (and may change) the settings the simulation really
//! uses. Only what the simulation does is here: a parameter for a feature it lacks would be a
//! promise it does not keep.

use super::modes::Frame;
use super::safety::Action;
use super::spec::SimSpec;

/// One parameter: its name and how it reads from and writes to the simulation.
struct Param {
    name: &'static str,
    get: fn(&SimSpec) -> f32,
    /// `None`: read-only (a set is answered with the unchanged value, as ArduPilot does).
    set: Option<fn(&mut SimSpec, f32) -> bool>,
}

fn positive(v: f32) -> bool {
    v.is_finite() && v > 0.0
}

/// The system id, under ArduPilot 4.7's name (`MAV_SYSID`; `SYSID_THISMAV` until 4.6, migrated
/// by `gcs_conversion_info` in each vehicle's `Parameters.cpp`): 4.7 answers no read of the old
/// name, and neither does the simulation.
const SYSID: Param = Param {
    name: "MAV_SYSID",
    get: |s| s.sysid as f32,
    set: None,
};
/// A failsafe action's parameter (0 continue, 1 RTL, 2 HOLD) over a field of [`super::safety::Safety`].
macro_rules! action_param {
    ($name:literal, $field:ident) => {
        Param {
            name: $name,
            get: |s| s.safety.$field as u8 as f32,
            set: Some(|s, v| match Action::from_param(v) {
                Some(a) => {
                    s.safety.$field = a;
                    true
                }
                None => false,
            }),
        }
    };
}

/// A 0/1 parameter over a flag of [`super::safety::Safety`] (other values refused).
macro_rules! flag_param {
    ($name:literal, $field:ident) => {
        Param {
            name: $name,
            get: |s| f32::from(u8::from(s.safety.$field)),
            set: Some(|s, v| {
                (v == 0.0 || v == 1.0) && {
                    s.safety.$field = v == 1.0;
                    true
                }
            }),
        }
    };
}

/// Whether the uploaded fence is enforced (0/1), and what a breach does (0 report, 1 RTL,
/// 2 HOLD: ArduRover's numbers).
const FENCE_ENABLE: Param = flag_param!("FENCE_ENABLE", fence_enable);
const FENCE_ACTION: Param = action_param!("FENCE_ACTION", fence_action);

/// The battery: capacity and low mark (mAh), and the low-battery action (0 none, 1 RTL, 2 HOLD).
const BATT_CAPACITY: Param = Param {
    name: "BATT_CAPACITY",
    get: |s| s.safety.battery_mah as f32,
    set: Some(|s, v| {
        positive(v) && {
            s.safety.battery_mah = v as f64;
            true
        }
    }),
};
const BATT_LOW_MAH: Param = Param {
    name: "BATT_LOW_MAH",
    get: |s| s.safety.battery_low_mah as f32,
    set: Some(|s, v| {
        (v.is_finite() && v >= 0.0) && {
            s.safety.battery_low_mah = v as f64;
            true
        }
    }),
};
const BATT_FS_LOW_ACT: Param = action_param!("BATT_FS_LOW_ACT", low_battery_action);

/// A non-negative length (m) over a field of [`SimSpec`], scaled by `$per_m` units a metre.
macro_rules! length_param {
    ($name:literal, $($field:ident).+, $per_m:expr) => {
        Param {
            name: $name,
            get: |s| (s.$($field).+ * $per_m) as f32,
            set: Some(|s, v| {
                (v.is_finite() && v >= 0.0) && {
                    s.$($field).+ = v as f64 / $per_m;
                    true
                }
            }),
        }
    };
}

/// Arming is refused within this distance inside the fence (m; `AC_Fence`'s `FENCE_MARGIN`).
const FENCE_MARGIN: Param = length_param!("FENCE_MARGIN", safety.fence_margin, 1.0);

/// Whether RTL may go home as well as to the rally points (0/1).
const RALLY_INCL_HOME: Param = flag_param!("RALLY_INCL_HOME", rally_include_home);

/// SITL's steady wind (m/s, and the degrees it comes from): a push a test sets to drive a
/// vehicle where it was not told to go (out of its fence), as one does to SITL.
const SIM_WIND_DIR: Param = Param {
    name: "SIM_WIND_DIR",
    get: |s| s.wind.from_deg as f32,
    set: Some(|s, v| {
        v.is_finite() && {
            s.wind.from_deg = v as f64;
            true
        }
    }),
};
const SIM_WIND_SPD: Param = length_param!("SIM_WIND_SPD", wind.speed, 1.0);

/// A Rover's: cruise speed (m/s), steering rate limit (deg/s), turning radius and waypoint
/// radius (m).
const BOAT: [Param; 14] = [
    Param {
        name: "ATC_STR_RAT_MAX",
        get: |s| s.turn_rate.to_degrees() as f32,
        set: Some(|s, v| {
            positive(v) && {
                s.turn_rate = (v as f64).to_radians();
                true
            }
        }),
    },
    BATT_CAPACITY,
    BATT_FS_LOW_ACT,
    BATT_LOW_MAH,
    Param {
        name: "CRUISE_SPEED",
        get: |s| s.max_speed as f32,
        set: Some(|s, v| {
            positive(v) && {
                s.max_speed = v as f64;
                true
            }
        }),
    },
    FENCE_ACTION,
    FENCE_ENABLE,
    FENCE_MARGIN,
    SYSID,
    RALLY_INCL_HOME,
    SIM_WIND_DIR,
    SIM_WIND_SPD,
    length_param!("TURN_RADIUS", turn_radius, 1.0),
    length_param!("WP_RADIUS", wp_radius, 1.0),
];

/// A Copter's: the delay before it disarms itself on the ground (s), waypoint radius (cm) and
/// speed (cm/s).
const MULTIROTOR: [Param; 13] = [
    BATT_CAPACITY,
    BATT_FS_LOW_ACT,
    BATT_LOW_MAH,
    length_param!("DISARM_DELAY", disarm_delay_s, 1.0),
    FENCE_ACTION,
    FENCE_ENABLE,
    FENCE_MARGIN,
    SYSID,
    RALLY_INCL_HOME,
    SIM_WIND_DIR,
    SIM_WIND_SPD,
    length_param!("WPNAV_RADIUS", wp_radius, 100.0),
    Param {
        name: "WPNAV_SPEED",
        get: |s| (s.max_speed * 100.0) as f32,
        set: Some(|s, v| {
            positive(v) && {
                s.max_speed = v as f64 / 100.0;
                true
            }
        }),
    },
];

fn table(frame: Frame) -> &'static [Param] {
    match frame {
        Frame::Boat => &BOAT,
        Frame::Multirotor => &MULTIROTOR,
    }
}

/// How many parameters the frame has.
pub fn count(frame: Frame) -> usize {
    table(frame).len()
}

/// Parameter `index`: its name and value.
pub fn by_index(spec: &SimSpec, index: usize) -> Option<(&'static str, f32)> {
    table(spec.frame).get(index).map(|p| (p.name, (p.get)(spec)))
}

/// A parameter's index by name.
pub fn index_of(frame: Frame, name: &str) -> Option<usize> {
    table(frame).iter().position(|p| p.name == name)
}

/// Set a parameter; returns whether the value was taken (out of range and read-only ones are
/// not). Either way the caller answers with the value now in force.
pub fn set(spec: &mut SimSpec, index: usize, value: f32) -> bool {
    match table(spec.frame).get(index).and_then(|p| p.set) {
        Some(f) => f(spec, value),
        None => false,
    }
}
