//! hetfleet's records of a mission: the MCAP recording the model server writes and `fleet
//! replay` reads back ([`recording`]), the Foxglove channels it carries and the live view
//! serves ([`foxglove`]), and the server's output files at the end of a run ([`outputs`]).
//!
//! Apart from `fleet-mission` so that the mission itself (protocol, schedule, server core,
//! vehicle brain) carries no log format: the server, the watcher and the CLI use this crate.

pub mod foxglove;
pub mod outputs;
pub mod recording;
