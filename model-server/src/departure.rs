//! When a server told to exit once the mission is done (`--exit-when-done`) leaves.
//!
//! An ack is the only thing that lets a vehicle end: it keeps its last batch until the ack
//! comes and re-sends it when its wait runs out (at most [`fleet_net::rto::MAX_WAIT`]). A
//! server that closes its session drops whatever it has not yet delivered, so an ack still on
//! its way over a slow, lossy radio (a 9.6 kbit/s link with 5% loss stalls for tens of seconds
//! while TCP backs off) dies with it, and the boat waits out its final minute and fails with
//! its batch kept. So the server stays while a vehicle is still here, until it has heard no
//! batch for `linger`: each copy a vehicle re-sends is acknowledged again and keeps the server
//! one more `linger`. It leaves at once when every vehicle has left (each leaves once its
//! outbox is acknowledged); a vehicle out of range stops counting as here when its link's lease
//! runs out.

use std::time::{Duration, Instant};

/// The default `--linger-ms`: longer than a vehicle's longest wait before it re-sends, so a
/// vehicle whose last ack was lost re-sends once more while the server is there to answer.
pub const DEFAULT_LINGER_MS: u64 = fleet_net::rto::MAX_WAIT.as_millis() as u64 + 15_000;

/// The server's way out once the mission is done.
#[derive(Debug, Clone)]
pub struct Departure {
    linger: Duration,
    /// From the mission's end, or from the last batch heard after it.
    quiet_since: Option<Instant>,
}

impl Departure {
    pub fn new(linger: Duration) -> Self {
        Self {
            linger,
            quiet_since: None,
        }
    }

    /// The mission is done (the first call counts; later ones change nothing).
    pub fn mission_done(&mut self, now: Instant) {
        self.quiet_since.get_or_insert(now);
    }

    /// A batch came (new or a copy): a vehicle still waits for an ack.
    pub fn heard_batch(&mut self, now: Instant) {
        if let Some(t) = &mut self.quiet_since {
            *t = now;
        }
    }

    /// Whether to leave now, with `anyone_here` whether a vehicle's link is still up.
    pub fn leave(&self, now: Instant, anyone_here: bool) -> bool {
        self.quiet_since
            .is_some_and(|t| !anyone_here || now.saturating_duration_since(t) > self.linger)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Duration = Duration::from_secs(1);

    #[test]
    fn the_server_stays_while_a_vehicle_here_still_sends_and_leaves_when_all_have_gone() {
        let t0 = Instant::now();
        let mut d = Departure::new(10 * S);
        assert!(!d.leave(t0 + 100 * S, false), "not before the mission is done");
        d.mission_done(t0);
        assert!(d.leave(t0, false), "nobody here: at once");
        assert!(!d.leave(t0 + 10 * S, true));
        // A re-sent batch 9 s after the end (its ack was lost): another 10 s from then.
        d.heard_batch(t0 + 9 * S);
        d.mission_done(t0 + 9 * S + S / 2);
        assert!(!d.leave(t0 + 15 * S, true), "a re-send keeps the server");
        assert!(d.leave(t0 + 20 * S, true), "silent for the whole linger: gone");
        assert!(d.leave(t0 + 12 * S, false), "everyone left: gone");
    }

    #[test]
    fn the_default_linger_outlasts_a_vehicles_longest_wait_before_it_re_sends() {
        // The failure it prevents (CI, 9.6 kbit/s, 5% loss): the last ack stalled, the server
        // left 10 s after the end, the boat re-sent into nothing and failed a minute later.
        assert!(Duration::from_millis(DEFAULT_LINGER_MS) > fleet_net::rto::MAX_WAIT);
        let t0 = Instant::now();
        let mut d = Departure::new(Duration::from_millis(DEFAULT_LINGER_MS));
        d.mission_done(t0);
        let resend = t0 + fleet_net::rto::MAX_WAIT;
        assert!(!d.leave(resend, true), "there for the latest re-send");
    }
}
