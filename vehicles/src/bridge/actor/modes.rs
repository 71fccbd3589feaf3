//! The vehicle's own mode requests to its autopilot ([`super::super::mode_request`]: asked
//! again until the heartbeat shows the mode, given up on after a few tries or a refusal).

use super::super::mode_request::{Due, ModeRequest, MODE_TRIES};
use super::Actor;
use mavlink::dialects::ardupilotmega::*;
use tokio::time::Instant;
use tracing::warn;

impl Actor {
    /// The vehicle's own mode change, asked for until the heartbeat shows it ([`ModeRequest`]).
    pub(super) fn request_mode(&mut self, target: u8, mode: u32) {
        self.set_mode(target, mode);
        self.mode_request = Some(ModeRequest::sent(mode, Instant::now()));
    }

    /// A pending mode request, a second on: asked again, or given up on with a warning.
    pub(super) fn follow_mode_request(&mut self, target: u8) {
        let Some(r) = self.mode_request.as_mut() else { return };
        let (mode, shown) = (self.spec.vehicle.frame.name(r.mode), self.state.mode);
        match r.due(Instant::now()) {
            Due::Wait => {}
            Due::Resend(n) => {
                let r = r.mode;
                warn!(
                    sysid = target,
                    mode,
                    try_ = n,
                    "the autopilot does not show the mode asked for: asking again"
                );
                self.set_mode(target, r);
            }
            Due::GiveUp => {
                let now = shown.map_or_else(|| "unknown".into(), |m| self.spec.vehicle.frame.name(m));
                warn!(
                    sysid = target,
                    mode, now, "the autopilot never showed the mode asked for {MODE_TRIES} times"
                );
                self.mode_request = None;
            }
        }
    }

    /// The autopilot refused a mode change while the vehicle's own request was pending: asking
    /// again changes nothing, and the operator must know.
    pub(super) fn on_mode_refused(&mut self, result: MavResult) {
        let Some(r) = self.mode_request.take() else { return };
        let mode = self.spec.vehicle.frame.name(r.mode);
        warn!(
            sysid = self.state.sysid,
            mode,
            ?result,
            "the autopilot refused the mode asked for"
        );
        self.state.failsafe = Some(format!("the autopilot refused {mode} ({result:?})"));
    }
}
