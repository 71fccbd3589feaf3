//! How long a vehicle waits for the server's ack before it sends a batch again, measured on its
//! own link: RFC 6298's estimator (the smoothed round trip plus four times its variation), with
//! Karn's rule (only a batch sent once is timed: the ack of a resent one could be either's).
//! Never below the mission's `resend_ms` (loopback stays as quick as it was), never above a
//! minute. Over a 64 kbit/s radio shared by five boats a batch's ack takes seconds; a fixed 1 s
//! would send every batch several times and fill the radio with copies. And the wait doubles
//! each time it runs out (RFC 6298 5.5) until an ack is timed again: under Karn's rule a link
//! slower than the wait would otherwise never be timed at all, and every batch would go out
//! once a second for ever (a first radio run sent each batch seven times).

use std::time::Duration;

/// The most a resend waits.
pub const MAX_WAIT: Duration = Duration::from_secs(60);

#[derive(Debug, Clone)]
pub struct Retransmit {
    srtt: Option<f64>,
    rttvar: f64,
    floor: f64,
    /// How many times the wait ran out since the last timed ack (the wait is doubled as often).
    backoff: u32,
}

impl Retransmit {
    /// Before any ack is timed, `floor` (the mission's `resend_ms`).
    pub fn new(floor: Duration) -> Self {
        Self {
            srtt: None,
            rttvar: 0.0,
            floor: floor.as_secs_f64(),
            backoff: 0,
        }
    }

    /// A batch sent once was acknowledged `rtt` after it went.
    pub fn sample(&mut self, rtt: Duration) {
        let r = rtt.as_secs_f64();
        self.backoff = 0;
        match self.srtt {
            None => {
                self.srtt = Some(r);
                self.rttvar = r / 2.0;
            }
            Some(s) => {
                self.rttvar = 0.75 * self.rttvar + 0.25 * (s - r).abs();
                self.srtt = Some(0.875 * s + 0.125 * r);
            }
        }
    }

    /// The wait ran out and batches went again: the next wait is twice as long.
    pub fn back_off(&mut self) {
        self.backoff = (self.backoff + 1).min(16);
    }

    /// How long an unacknowledged batch waits before it goes again.
    pub fn timeout(&self) -> Duration {
        let rto = self.srtt.map_or(0.0, |s| s + 4.0 * self.rttvar);
        let doubled = rto.max(self.floor) * f64::from(1u32 << self.backoff);
        Duration::from_secs_f64(doubled.min(MAX_WAIT.as_secs_f64()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wait_follows_the_link_and_stays_within_its_bounds() {
        let floor = Duration::from_millis(1000);
        let mut r = Retransmit::new(floor);
        assert_eq!(r.timeout(), floor, "nothing timed yet");
        // Loopback: acks in milliseconds; the mission's floor holds.
        for _ in 0..20 {
            r.sample(Duration::from_millis(5));
        }
        assert_eq!(r.timeout(), floor);
        // A radio: acks in about 3 s, give or take 0.5 s; RFC 6298's first sample is 3 s + 4 x 1.5 s.
        let mut radio = Retransmit::new(floor);
        radio.sample(Duration::from_secs(3));
        assert!((radio.timeout().as_secs_f64() - 9.0).abs() < 1e-9);
        for i in 0..50 {
            radio.sample(Duration::from_millis(if i % 2 == 0 { 2500 } else { 3500 }));
        }
        let t = radio.timeout().as_secs_f64();
        assert!((4.0..6.0).contains(&t), "{t}");
        // A link gone bad: never more than a minute.
        radio.sample(Duration::from_secs(1000));
        assert_eq!(radio.timeout(), MAX_WAIT);
    }

    #[test]
    fn a_wait_that_runs_out_doubles_until_an_ack_is_timed() {
        let floor = Duration::from_millis(1000);
        let mut r = Retransmit::new(floor);
        let waits: Vec<f64> = (0..8)
            .map(|_| {
                let w = r.timeout().as_secs_f64();
                r.back_off();
                w
            })
            .collect();
        assert_eq!(waits, [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 60.0, 60.0]);
        for _ in 0..100 {
            r.back_off();
        }
        assert_eq!(r.timeout(), MAX_WAIT, "no overflow however long the link is gone");
        // An ack timed (a batch that went once): the estimate again, without the doubling.
        r.sample(Duration::from_secs(3));
        assert!((r.timeout().as_secs_f64() - 9.0).abs() < 1e-9);
    }
}
