//! The teams a row compares and how two of them are compared: their names (as `per_step.csv`
//! and the tables give them) and the paired difference of their MSE over seeds. The claims
//! ([`super::claims`]) and the paper's report ([`super::paper`]) both read them.

use super::stats::{Interval, Outcome};
use serde::Serialize;

/// Team names in `per_step.csv` and the tables.
pub const HETEROGENEOUS: &str = "heterogeneous";
pub const AERIAL_ONLY: &str = "aerial-only";
pub const BOAT_ONLY: &str = "boat-only";
pub const RANDOM: &str = "heterogeneous-random";
pub const ORACLE: &str = "heterogeneous-oracle";

/// A paired difference of two teams' time-averaged MSE over seeds, and what it says.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    pub first: String,
    pub second: String,
    pub difference: Interval,
    pub verdict: Outcome,
}
