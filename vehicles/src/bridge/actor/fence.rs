//! The fence as the bridge sees it: the fence and rally points uploaded and read back, the
//! fence enabled with the mission's action (asked again each second until the autopilot shows
//! it), a vehicle not driven until its fence is confirmed, and the autopilot's breaches.

use super::Actor;
use crate::upload::{self, Upload};
use mavlink::dialects::ardupilotmega::*;
use tracing::{error, info, warn};

impl Actor {
    /// FENCE_STATUS: a breach takes the vehicle out of the allocation (as [`guided`] reads it)
    /// until the autopilot reports it inside again.
    pub(super) fn on_fence_status(&mut self, f: &FENCE_STATUS_DATA) {
        let breach = (f.breach_status != 0).then(|| {
            let kind = match f.breach_type {
                FenceBreach::FENCE_BREACH_MINALT => "below its minimum altitude",
                FenceBreach::FENCE_BREACH_MAXALT => "above its maximum altitude",
                _ => "outside its boundary",
            };
            format!("fence breach: {kind} (breach {} since boot)", f.breach_count)
        });
        match (&self.state.breach, &breach) {
            (None, Some(b)) => warn!(
                sysid = self.state.sysid,
                "{b}: left out of the allocation until it is inside"
            ),
            (Some(_), None) => info!(sysid = self.state.sysid, "back inside the fence"),
            _ => {}
        }
        self.state.breach = breach;
    }

    /// What the uploads answer to one of the autopilot's mission-protocol messages, sent.
    pub(super) fn answer_uploads(&mut self, mut answer: impl FnMut(&mut Upload) -> Vec<MavMessage>) {
        let out: Vec<MavMessage> = self.uploads.iter_mut().flat_map(&mut answer).collect();
        for m in &out {
            self.send(m);
        }
    }

    /// The fence and rally points uploaded and read back, then the fence enabled with the
    /// mission's action, each step sent at once and again each second while unanswered; whether
    /// that is done. A vehicle whose fence is not confirmed (read back as sent and enabled) is
    /// not driven, the reason in `waiting`, unless the mission sets `drive_without_fence`.
    pub(super) fn prepared(&mut self, target: u8, second: bool) -> bool {
        if self.prepared {
            return true;
        }
        let out = match self.uploads.iter_mut().find(|u| !u.finished()) {
            Some(u) if second => u.tick(target),
            Some(u) => u.start(target),
            None => self.enable_fence(target, second),
        };
        for m in &out {
            self.send(m);
        }
        self.prepared
    }

    /// The uploads done: FENCE_ACTION and FENCE_ENABLE set (again each second until the
    /// autopilot shows the fence enabled), then prepared, or refused with the reason.
    pub(super) fn enable_fence(&mut self, target: u8, second: bool) -> Vec<MavMessage> {
        let confirmed = self.fence_confirmed();
        let fenced = self.uploads.is_empty() || (confirmed && self.state.fence_enabled);
        if !fenced && confirmed && self.enable_tries < upload::TRIES {
            if !(second || self.enable_tries == 0) {
                return vec![];
            }
            self.enable_tries += 1;
            let set = |name: &str, v: f32| {
                MavMessage::PARAM_SET(PARAM_SET_DATA {
                    param_value: v,
                    target_system: target,
                    target_component: 1,
                    param_id: name.into(),
                    param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
                })
            };
            // RTL to the nearest of the fleet's rally (launch) points, never to wherever the
            // autopilot booted: ArduPilot's RALLY_INCL_HOME = 1 (its default) counts home too.
            let rally = self
                .uploads
                .iter()
                .any(|u| u.kind == MavMissionType::MAV_MISSION_TYPE_RALLY);
            let home = rally.then(|| set("RALLY_INCL_HOME", 0.0));
            let fence = [set("FENCE_ACTION", self.spec.fence_action), set("FENCE_ENABLE", 1.0)];
            return home.into_iter().chain(fence).collect();
        }
        if fenced || self.spec.drive_without_fence {
            self.prepared = true;
            self.say_prepared(target);
        } else {
            let why = self.unfenced_reason();
            if self.state.waiting.as_ref() != Some(&why) {
                error!(sysid = target, "not driven: {why}");
                self.state.waiting = Some(why);
            }
        }
        vec![]
    }

    /// Why the fence is not confirmed, for the operator.
    pub(super) fn unfenced_reason(&self) -> String {
        let fence = self
            .uploads
            .iter()
            .find(|u| u.kind == MavMissionType::MAV_MISSION_TYPE_FENCE);
        let why = match fence.map(|u| &u.state) {
            Some(upload::State::Failed(why)) => format!("the autopilot did not take the fence ({why})"),
            _ => "the autopilot did not enable the fence (FENCE_ENABLE)".into(),
        };
        format!("a confirmed fence: {why}; [mavlink] drive_without_fence = true drives it anyway")
    }

    pub(super) fn fence_confirmed(&self) -> bool {
        self.uploads
            .iter()
            .any(|u| u.kind == MavMissionType::MAV_MISSION_TYPE_FENCE && u.confirmed())
    }

    pub(super) fn say_prepared(&self, target: u8) {
        let states: Vec<String> = self
            .uploads
            .iter()
            .map(|u| format!("{:?}: {:?} ({} starts)", u.kind, u.state, u.starts()))
            .collect();
        if self.uploads.is_empty() {
            // No fence to upload (none given): nothing to say.
        } else if self.state.fence_enabled && self.fence_confirmed() {
            info!(sysid = target, uploads = ?states, "fence and rally points uploaded and read back, fence enabled");
        } else {
            warn!(
                sysid = target,
                uploads = ?states,
                "the autopilot did not take the fence (or enable it): driven anyway (drive_without_fence), \
                 the planner alone keeps it inside"
            );
        }
    }
}
