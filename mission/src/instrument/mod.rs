//! Readings from instruments that are not the vehicle: a sonde on a boat, a camera on a drone,
//! any driver that can write a line of JSON. This module is the interface (what a reading is,
//! [`reading`]), the mission's clock that puts a reading in a step ([`clock`]), where a reading
//! lands on the model grid and why one is refused ([`placer`]), which source each vehicle reads
//! ([`source`]), and how a vehicle turns an epoch's readings into the batch it sends
//! ([`collect`]). Pure: the vehicle node owns the sockets and the clock's `now`.
//!
//! A reading is one line of newline-delimited JSON:
//!
//! ```text
//! {"t": 1795000000.25, "lat": -33.8601, "lon": 151.2101, "value": 0.42, "sigma": 0.01}
//! ```
//!
//! `t` is UTC seconds since 1970, `lat`/`lon` WGS 84 degrees, `value` the measured quantity in
//! the field's units and `sigma` (optional) its noise standard deviation; without it the
//! mission's noise for the vehicle's kind applies. These names are the interface and are kept.

pub mod clock;
pub mod collect;
pub mod log;
pub mod named;
pub mod placer;
pub mod raster;
pub mod reading;
pub mod source;

pub use clock::MissionClock;
pub use collect::{Collected, Tally};
pub use log::{Entry, Logged};
pub use named::NamedValues;
pub use placer::{Placed, Placer};
pub use reading::{parse_line, Reading, Refusal, MAX_LINE};
pub use source::{check_source, SensorSource};
