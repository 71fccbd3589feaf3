//! QGroundControl plans: each boat's planned sensing places as a `.plan` file (QGC holds one
//! mission per vehicle), with the site's boundary (the mission's fence, or the grid's extent)
//! as an inclusion geofence. The format is QGC's JSON plan (`fileType` "Plan", mission
//! version 2, geofence and rally points version 2).

use super::{ExportError, Run};
use fleet_mission::protocol::VehicleKind;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// MAV_CMD_NAV_WAYPOINT.
const NAV_WAYPOINT: u32 = 16;
/// MAV_FRAME_GLOBAL_RELATIVE_ALT: latitude, longitude, altitude above home.
const FRAME_RELATIVE_ALT: u32 = 3;
/// MAV_AUTOPILOT_ARDUPILOTMEGA (what `sim-autopilot` says it is).
const FIRMWARE_ARDUPILOT: u32 = 3;
/// MAV_TYPE_SURFACE_BOAT.
const TYPE_SURFACE_BOAT: u32 = 11;

/// Where `path` puts vehicle `id`'s plan: `f.plan` -> `f.boat-1.plan`.
pub fn path_for(path: &Path, id: &str) -> PathBuf {
    let stem = path.file_stem().unwrap_or_default().to_string_lossy();
    path.with_file_name(format!("{stem}.{id}.plan"))
}

/// Write each boat's plan as published at `epoch` (default: the last epoch with plans):
/// one waypoint per sampling step with a disk, in step order. Returns the files written.
pub fn write(run: &Run, path: &Path, epoch: Option<u64>) -> Result<Vec<PathBuf>, ExportError> {
    let published = run.plans()?;
    let last = published.plans.iter().map(|p| p.epoch).max();
    let Some(epoch) = epoch.or(last) else {
        return Err(ExportError::Bad {
            path: run.dir.join("plans.json"),
            why: "it holds no plans".into(),
        });
    };
    let boats: Vec<_> = published
        .plans
        .iter()
        .filter(|p| p.epoch == epoch && p.kind == VehicleKind::Boat)
        .collect();
    if boats.is_empty() {
        return Err(ExportError::Bad {
            path: run.dir.join("plans.json"),
            why: format!(
                "no boat has a plan published at epoch {epoch} (epochs with plans: up to {})",
                last.unwrap_or(0)
            ),
        });
    }
    let fence = run.boundary_deg()?;
    let mut written = vec![];
    for plan in boats {
        let places: Vec<[f64; 2]> = plan.targets.iter().filter(|t| t.3 > 0.0).map(|t| t.2).collect();
        let doc = plan_json(run, &places, &fence, &format!("{} at epoch {epoch}", plan.vehicle));
        let out = path_for(path, &plan.vehicle);
        let text = serde_json::to_string_pretty(&doc).expect("JSON values serialise");
        std::fs::write(&out, text).map_err(|e| ExportError::Write {
            path: out.clone(),
            why: e.to_string(),
        })?;
        written.push(out);
    }
    Ok(written)
}

/// A QGC plan flying through `places` (grid metres), fenced to the site.
fn plan_json(run: &Run, places: &[[f64; 2]], fence: &[[f64; 2]], what: &str) -> Value {
    let site = &run.site;
    let alt_home = run.mission.mavlink.origin[2];
    let items: Vec<Value> = places
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let (lat, lon, _) = site.global_of(&site.ned_of((p[0], p[1]), 0.0));
            json!({
                "type": "SimpleItem",
                "autoContinue": true,
                "command": NAV_WAYPOINT,
                "doJumpId": i + 1,
                "frame": FRAME_RELATIVE_ALT,
                "params": [0, 0, 0, null, lat, lon, 0],
                "Altitude": 0,
                "AltitudeMode": 1,
                "AMSLAltAboveTerrain": null,
            })
        })
        .collect();
    let [west, south, _, _] = run.bounds_deg();
    json!({
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "comment": format!("hetfleet: {what}, mission {}", run.mission.mission),
        "mission": {
            "version": 2,
            "firmwareType": FIRMWARE_ARDUPILOT,
            "vehicleType": TYPE_SURFACE_BOAT,
            "cruiseSpeed": run.mission.mavlink.boat_speed_ms,
            "hoverSpeed": run.mission.mavlink.multirotor_speed_ms,
            "plannedHomePosition": [south, west, alt_home],
            "items": items,
        },
        "geoFence": {
            "version": 2,
            "circles": [],
            "polygons": [{ "inclusion": true, "version": 1, "polygon": fence }],
        },
        "rallyPoints": { "version": 2, "points": [] },
    })
}
