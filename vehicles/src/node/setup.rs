//! What this vehicle is in its mission, resolved once at start-up from the command line and
//! the mission file: which vehicle of the roster (its index and kind), on which grid, behind
//! which autopilot, reading which sensor. The start-up then builds the brain, the bridge and
//! the instrument from this one value, so the roster is looked up and `--autopilot` and
//! `--sensor` are weighed against the mission in one place.

use crate::Args;
use fleet_math::grid::Grid;
use fleet_math::process::frames::Frames;
use fleet_mission::config::MissionConfig;
use fleet_mission::instrument::SensorSource;
use fleet_mission::protocol::VehicleKind;
use fleet_mission::roster::VehicleId;

/// This vehicle's place in the mission.
#[derive(Debug, Clone)]
pub struct Setup {
    pub id: VehicleId,
    /// Its index in the roster (its random stream, its launch point).
    pub index: usize,
    pub kind: VehicleKind,
    pub grid: Grid,
    /// Steps in the mission.
    pub frames: usize,
    /// The autopilot's address: `--autopilot`, else the mission's `[mavlink] autopilot`
    /// (`none`, `sim`, or a MAVLink address).
    pub autopilot: String,
    /// The sensor source: `--sensor`, else the mission's `[sensors]` for this vehicle.
    pub sensor: SensorSource,
}

impl Setup {
    /// This vehicle in `mission` (with its truth, if it has one): refused as bad input when the
    /// id is not in the roster or `--sensor` does not parse.
    pub fn resolve(args: &Args, mission: &MissionConfig, truth: Option<&Frames>) -> anyhow::Result<Self> {
        let (grid, frames) = mission.workspace(truth.map(Frames::shape))?;
        let (index, kind) = mission.vehicle(&args.id)?;
        let sensor = match &args.sensor {
            Some(s) => s
                .parse()
                .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("--sensor {e}")))?,
            None => mission.sensor_of(&args.id),
        };
        Ok(Self {
            id: args.id.clone(),
            index,
            kind,
            grid,
            frames,
            autopilot: args
                .autopilot
                .clone()
                .unwrap_or_else(|| mission.mavlink.autopilot.clone()),
            sensor,
        })
    }

    /// Whether the vehicle drives an autopilot (real or simulated) rather than none.
    pub fn has_autopilot(&self) -> bool {
        self.autopilot != "none"
    }
}
