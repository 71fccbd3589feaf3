//! hetfleet's application layer: the paper's studies ([`experiment`]), figures ([`plot`]), the
//! mission report, and the `fleet` command line. It stands on `fleet-math` (the mathematics)
//! and `fleet-mission` (the protocol, configuration, schedule, server core and vehicle brain),
//! each item imported from the crate that defines it (`fleet_math::dmd`,
//! `fleet_mission::server`): nothing is re-exported, so every item has one path.
//!
//! Layers (the compiler enforces them: each crate depends only on those below it):
//! `fleet-math` <- `fleet-mission` <- `fleet-net` <- `model-server`, `vehicles`;
//! `fleet-math`, `fleet-mission` <- `fleet` (this crate: CLI, experiments, plots, reports).

pub mod experiment;
pub mod export;
pub mod mission;
pub mod plot;
pub mod reference;
