//! hetfleet's mission without the network: what the nodes say to each other ([`protocol`]),
//! what a mission and a team are ([`config`], [`team`], the [`roster`] of its vehicles), the
//! epoch [`schedule`] every node agrees on, the model server's core ([`server`], with the
//! [`assimilator`] that fuses and allocates), the vehicle's brain ([`vehicle`]), the server's
//! events ([`events`]), the fused map at every step ([`history`]), and the secured configs
//! ([`security`]). Pure and testable without a socket; the nodes wrap it.
//!
//! The mathematics it stands on (`grid`, `dmd`, `sensing`, `fusion`, `process`, `npy`) is
//! `fleet-math`'s, imported from there (one path for every item: nothing is re-exported).

pub mod assimilator;
pub mod config;
pub mod events;
pub mod fence;
pub mod health;
pub mod history;
pub mod holdout;
pub mod instrument;
pub mod launch;
pub mod memory;
pub mod offline;
pub mod protocol;
pub mod published;
pub mod roster;
pub mod schedule;
pub mod security;
pub mod server;
pub mod side_by_side;
pub mod signing_key;
pub mod site;
pub mod step_file;
pub mod step_writer;
pub mod team;
pub mod vehicle;
