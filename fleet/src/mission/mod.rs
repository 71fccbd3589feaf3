//! The mission report `fleet up` writes. The fleet's loop itself (the protocol, the
//! configuration, the schedule, the server's core and the vehicle's brain) is `fleet-mission`'s,
//! imported from there.

pub mod report;
