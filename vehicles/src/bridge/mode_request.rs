//! A mode the vehicle itself asks its autopilot for (its failsafe's RTL or HOLD, GUIDED again
//! on rejoining), asked again until the autopilot's HEARTBEAT shows it.
//!
//! A DO_SET_MODE is one datagram. Over a radio, or a loopback socket whose reader is behind,
//! it can be lost, and ArduPilot does not say that it never heard one. So a request is
//! confirmed by what the autopilot says it is in, not by having been sent: asked again every
//! [`RESEND_AFTER`] (two of ArduPilot's 1 Hz heartbeats) until the heartbeat shows the mode, at
//! most [`MODE_TRIES`] times. It ends early when the autopilot refuses the command (a
//! COMMAND_ACK other than accepted: retrying changes nothing) or when an operator's own mode
//! change passes through the bridge (the operator's word wins over the vehicle's request).

use tokio::time::{Duration, Instant};

/// A request is sent at most this many times.
pub(super) const MODE_TRIES: u32 = 5;
/// How long a request waits for the heartbeat to show it before asking again.
pub(super) const RESEND_AFTER: Duration = Duration::from_secs(2);

/// A mode asked for and not yet shown by the autopilot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct ModeRequest {
    pub mode: u32,
    tries: u32,
    asked_at: Instant,
}

/// What to do about a pending request, a second on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Due {
    /// Wait: asked too recently to expect the heartbeat to show it.
    Wait,
    /// Ask again (this is the n-th time).
    Resend(u32),
    /// Asked [`MODE_TRIES`] times and never shown: left to the operator.
    GiveUp,
}

impl ModeRequest {
    /// A request just sent for the first time.
    pub fn sent(mode: u32, now: Instant) -> Self {
        Self {
            mode,
            tries: 1,
            asked_at: now,
        }
    }

    /// Whether the autopilot's heartbeat mode fulfils it.
    pub fn shown_by(&self, mode: u32) -> bool {
        self.mode == mode
    }

    /// What is due now; a resend counts as asked now.
    pub fn due(&mut self, now: Instant) -> Due {
        if now.duration_since(self.asked_at) < RESEND_AFTER {
            return Due::Wait;
        }
        if self.tries >= MODE_TRIES {
            return Due::GiveUp;
        }
        self.tries += 1;
        self.asked_at = now;
        Due::Resend(self.tries)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_is_asked_again_every_resend_interval_then_given_up() {
        let t0 = Instant::now();
        let mut r = ModeRequest::sent(11, t0);
        assert!(r.shown_by(11) && !r.shown_by(15));
        assert_eq!(r.due(t0 + RESEND_AFTER / 2), Due::Wait);
        let mut t = t0;
        for n in 2..=MODE_TRIES {
            t += RESEND_AFTER;
            assert_eq!(r.due(t), Due::Resend(n));
            assert_eq!(r.due(t), Due::Wait, "asked again just now");
        }
        assert_eq!(r.due(t + RESEND_AFTER), Due::GiveUp);
    }
}
