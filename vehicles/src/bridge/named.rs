//! The instrument on the autopilot's link (`mavlink:NAME`): the bridge's actor hands this every
//! frame from the autopilot's system; NAMED_VALUE_FLOAT of the name (from any component: an
//! ArduPilot Lua script sends as the autopilot, a companion computer as itself) become readings,
//! positioned by the autopilot's GLOBAL_POSITION_INT and timed through its SYSTEM_TIME
//! ([`fleet_mission::instrument::named`]). Readings go to the node's loop on the instrument's
//! bounded queue; one that finds it full is counted and the count goes with the next one that
//! fits (the `overflow` refusal), so a flood is seen, and never held.

use crate::sensor::Input;
use fleet_mission::instrument::NamedValues;
use mavlink::dialects::ardupilotmega::MavMessage;
use tokio::sync::mpsc;
use tokio::sync::mpsc::error::TrySendError;

#[derive(Debug)]
pub(crate) struct NamedSource {
    name: String,
    values: NamedValues,
    tx: mpsc::Sender<Input>,
    /// Readings that found the queue full since the last count went through.
    lost: u64,
}

impl NamedSource {
    pub fn new(name: String, tx: mpsc::Sender<Input>) -> Self {
        Self {
            name,
            values: NamedValues::default(),
            tx,
            lost: 0,
        }
    }

    /// A frame from the autopilot's system; `autopilot`: from the autopilot itself (its
    /// position and clock count only from it).
    pub fn on_frame(&mut self, m: &MavMessage, autopilot: bool) {
        let outcomes = match m {
            MavMessage::NAMED_VALUE_FLOAT(d) if d.name.to_str().is_ok_and(|n| n == self.name) => {
                self.values.on_value(d.time_boot_ms, d.value)
            }
            MavMessage::GLOBAL_POSITION_INT(g) if autopilot => self.values.on_fix(g.time_boot_ms, g.lat, g.lon),
            MavMessage::SYSTEM_TIME(t) if autopilot => self.values.on_time(t.time_unix_usec, t.time_boot_ms),
            _ => return,
        };
        for o in outcomes {
            self.deliver(Input::Reading(o));
        }
    }

    fn deliver(&mut self, input: Input) {
        if self.lost > 0 {
            match self.tx.try_send(Input::Lost(self.lost)) {
                Ok(()) => self.lost = 0,
                Err(TrySendError::Full(_)) => {
                    self.lost += 1;
                    return;
                }
                Err(TrySendError::Closed(_)) => return,
            }
        }
        if let Err(TrySendError::Full(_)) = self.tx.try_send(input) {
            self.lost += 1;
        }
    }
}
