//! hetfleet's application layer: the paper's studies ([`experiment`]), figures ([`plot`]), the
//! mission report, and the `fleet` command line. It stands on `fleet-math` (the mathematics)
//! and `fleet-mission` (the protocol, configuration, schedule, server core and vehicle brain),
//! re-exported here under their module names so `fleet::dmd`, `fleet::mission::server` and
//! the rest read as one library.
//!
//! Layers (the compiler enforces them: each crate depends only on those below it):
//! `fleet-math` <- `fleet-mission` <- `fleet-net` <- `model-server`, `vehicles`;
//! `fleet-math`, `fleet-mission` <- `fleet` (this crate: CLI, experiments, plots, reports).

pub use fleet_exit as exit;
pub use fleet_math::{configure_linalg_threads, dmd, fusion, grid, kalman, npy, process, sensing, Allocator};
pub use fleet_mission::protocol;

pub mod experiment;
pub mod export;
pub mod mission;
pub mod plot;
pub mod reference;
