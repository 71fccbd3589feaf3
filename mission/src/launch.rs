//! Where the vehicles are launched (the points their autopilots boot at and return to, the
//! rally points), and the fence they must keep clear of. ArduPilot refuses to arm a vehicle
//! within `FENCE_MARGIN` of its fence (`libraries/AC_Fence/AC_Fence.cpp`, `pre_arm_check`; the
//! refusal "Arm: Vehicle breaching Polygon fence" from `libraries/AP_Arming/AP_Arming.cpp`),
//! and a boat turning from rest sweeps its turning radius: so the points sit inside the fence
//! by the margin plus the turn, and a fence with no such room is refused when the mission is
//! read, not found out at the shore.

use crate::config::{ConfigError, MissionConfig};
use crate::fence::{clearance, inside};
use crate::grid::Grid;

/// The site's fence, metres `[east, north]` of the origin: the mission's boundary, or the
/// grid's extent on the site.
pub fn fence_polygon_m(mission: &MissionConfig, grid: &Grid) -> Vec<[f64; 2]> {
    match &mission.team.fence {
        Some(f) => f.polygon_m.clone(),
        None => {
            let far = mission
                .mavlink
                .site(grid)
                .ned_of((grid.width_m(), grid.height_m()), 0.0);
            vec![[0.0, 0.0], [far.y, 0.0], [far.y, far.x], [0.0, far.x]]
        }
    }
}

/// How far inside the fence launch and rally points must be (m): the margin plus the turn.
pub fn required_clearance(mission: &MissionConfig) -> f64 {
    mission.mavlink.fence_margin_m + mission.mavlink.turn_radius_m
}

/// Each vehicle's launch point, metres `[east, north]` of the origin, in the mission's order:
/// spread along the site's south shore, half a metre further in than the clearance needs (so
/// rounding never puts one on the line). Refused, naming the vehicle, when one is not inside
/// the fence by [`required_clearance`].
pub fn launch_points(mission: &MissionConfig, grid: &Grid) -> Result<Vec<[f64; 2]>, ConfigError> {
    let fence = fence_polygon_m(mission, grid);
    let need = required_clearance(mission);
    let far = mission
        .mavlink
        .site(grid)
        .ned_of((grid.width_m(), grid.height_m()), 0.0);
    let vehicles = mission.vehicles();
    let n = vehicles.len() as f64;
    let mut points = Vec::with_capacity(vehicles.len());
    for (i, v) in vehicles.iter().enumerate() {
        let p = [(i as f64 + 0.5) * far.y / n, need + 0.5];
        let room = clearance(&fence, p);
        if !(inside(&fence, p) && room >= need) {
            let key = format!(
                "fence_margin_m = {}, turn_radius_m = {}",
                mission.mavlink.fence_margin_m, mission.mavlink.turn_radius_m
            );
            let rule = format!(
                "the fence leaves no room for {}'s launch point at ({:.1}, {:.1}) m east, north: {:.1} m inside, \
                 {need:.1} m needed (the autopilot's FENCE_MARGIN plus the turn)",
                v.id, p[0], p[1], room
            );
            return Err(ConfigError::Field {
                table: "mavlink",
                key: Some(key),
                rule,
            });
        }
        points.push(p);
    }
    Ok(points)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn launch_points_keep_the_margin_and_a_fence_too_small_is_refused() {
        let mut m = MissionConfig::from_toml(crate::config::DEFAULT_MISSION).unwrap();
        let grid = Grid::new(48, 96, 1.0).unwrap();
        let points = launch_points(&m, &grid).unwrap();
        assert_eq!(points.len(), m.vehicles().len());
        let fence = fence_polygon_m(&m, &grid);
        for p in &points {
            assert!(clearance(&fence, *p) >= required_clearance(&m), "{p:?}");
        }
        // The paper's tank (4.5 x 3 m) cannot keep a boat 2.9 m from every edge.
        m.mavlink.size_m = Some([4.5, 3.0]);
        let e = launch_points(&m, &grid).unwrap_err().to_string();
        assert!(
            e.starts_with("[mavlink] fence_margin_m = 2, turn_radius_m = 0.9: the fence leaves no room"),
            "{e}"
        );
        assert!(!e.contains('\n'));
        m.mavlink.fence_margin_m = 0.1;
        m.mavlink.turn_radius_m = 0.1;
        assert!(
            launch_points(&m, &grid).is_ok(),
            "a tank's autopilots keep a tank's margin"
        );
    }
}
