//! The fleet's loop as the nodes run it, re-exported from `fleet-mission` (the protocol, the
//! configuration, the schedule, the server's core and the vehicle's brain), plus the mission
//! report `fleet up` writes.

pub use fleet_mission::assimilator::*;
pub use fleet_mission::vehicle::{aerial_region, sense_aerial, sense_boat, sense_cells, vehicle_rng};
pub use fleet_mission::{
    config, events, health, launch, memory, schedule, security, server, signing_key, site, team, vehicle,
};

pub mod report;
