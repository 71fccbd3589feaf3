//! The autopilot side of a vehicle: where the workspace is on the Earth, the modes, a simulated
//! autopilot, and serving it on a MAVLink connection as an autopilot's serial or UDP port.

pub mod geofence;
pub mod modes;
pub mod params;
pub mod safety;
pub mod serve;
pub mod sim;
pub mod spec;
