//! hetfleet's vehicle side: the vehicle node's MAVLink bridge to its autopilot, a simulated
//! autopilot (boat and multirotor) that speaks MAVLink as ArduPilot does, and the ground-station
//! gateway that offers the whole fleet to QGroundControl or MAVProxy on one endpoint.

pub mod autopilot;
pub mod bridge;
pub mod gateway;
pub mod link;
pub mod sensor;
pub mod signing;
pub mod throttle;
pub mod upload;
