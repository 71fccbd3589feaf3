//! What telemetry shows of the autopilot that matters to the allocation (link, GUIDED, mode),
//! and the log line of each change.
//!
//! Two paths read the autopilot's status: the status watch (a change sends telemetry at once)
//! and the periodic telemetry. Whichever reads a change first logs it, so a tick that falls
//! between the change and the watch's wake-up does not swallow the log line (an RTL taken on a
//! link-loss failsafe went unlogged that way, and the operator's log showed no RTL at all).

use fleet_mission::protocol::{AutopilotLink, AutopilotStatus};
use tracing::info;

/// The last status shown, as the allocation reads it.
#[derive(Debug, Default)]
pub(super) struct Shown(Option<(AutopilotLink, bool, String)>);

impl Shown {
    /// Notes `status` as shown; logs it and returns true when the allocation's view changed.
    pub fn note(&mut self, status: &AutopilotStatus) -> bool {
        let now = (status.link, status.guided, status.mode.clone());
        if self.0.as_ref() == Some(&now) {
            return false;
        }
        info!(link = ?status.link, mode = status.mode, armed = status.armed, "autopilot");
        self.0 = Some(now);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(mode: &str, guided: bool) -> AutopilotStatus {
        AutopilotStatus {
            link: AutopilotLink::Up,
            mode: mode.into(),
            guided,
            ..AutopilotStatus::default()
        }
    }

    #[test]
    fn each_change_is_noted_once_whichever_path_reads_it_first() {
        let mut shown = Shown::default();
        assert!(shown.note(&status("GUIDED", true)), "the first status is a change");
        assert!(!shown.note(&status("GUIDED", true)), "the same status again is not");
        // The periodic telemetry reads the RTL first; the watch's wake-up then has nothing new.
        assert!(shown.note(&status("RTL", false)));
        assert!(!shown.note(&status("RTL", false)));
        assert!(shown.note(&status("GUIDED", true)), "back in GUIDED is a change");
    }
}
