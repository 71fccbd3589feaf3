//! Where the vehicles are launched (the points their autopilots boot at and return to, the
//! rally points), and the fence they must keep clear of. ArduPilot refuses to arm a vehicle
//! within `FENCE_MARGIN` of its fence (`libraries/AC_Fence/AC_Fence.cpp`, `pre_arm_check`; the
//! refusal "Arm: Vehicle breaching Polygon fence" from `libraries/AP_Arming/AP_Arming.cpp`),
//! and a boat turning from rest sweeps its turning radius: so the points sit inside the fence
//! by the margin plus the turn, and a fence with no such room is refused when the mission is
//! read, not found out at the shore.

use crate::config::{ConfigError, MissionConfig};
use crate::fence::{clearance, inside};
use fleet_math::grid::Grid;

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
/// spread along the fence's south shore, each the place nearest its share of the shore that
/// is inside the fence by [`required_clearance`] and half a metre more (so rounding never puts
/// one on the line), on a 200 x 200 lattice over the fence's extent; no two within a metre.
/// Refused, naming the vehicle, when the fence has no such room left for it.
pub fn launch_points(mission: &MissionConfig, grid: &Grid) -> Result<Vec<[f64; 2]>, ConfigError> {
    let fence = fence_polygon_m(mission, grid);
    let need = required_clearance(mission);
    let (lo, hi) = fence
        .iter()
        .fold(([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]), |(lo, hi), p| {
            ([lo[0].min(p[0]), lo[1].min(p[1])], [hi[0].max(p[0]), hi[1].max(p[1])])
        });
    const LATTICE: usize = 200;
    let at = |i: usize, j: usize| {
        let f = |k: usize, a: f64, b: f64| a + (k as f64 + 0.5) / LATTICE as f64 * (b - a);
        [f(i, lo[0], hi[0]), f(j, lo[1], hi[1])]
    };
    let mut room: Vec<[f64; 2]> = (0..LATTICE)
        .flat_map(|i| (0..LATTICE).map(move |j| (i, j)))
        .map(|(i, j)| at(i, j))
        .filter(|p| inside(&fence, *p) && clearance(&fence, *p) >= need + 0.5)
        .collect();
    let vehicles = mission.vehicles();
    let n = vehicles.len() as f64;
    let mut points = Vec::with_capacity(vehicles.len());
    for (i, v) in vehicles.iter().enumerate() {
        let shore = [lo[0] + (i as f64 + 0.5) / n * (hi[0] - lo[0]), lo[1]];
        let d = |p: &[f64; 2]| (p[0] - shore[0]).hypot(p[1] - shore[1]);
        let Some(p) = room.iter().copied().min_by(|a, b| d(a).total_cmp(&d(b))) else {
            let key = format!(
                "fence_margin_m = {}, turn_radius_m = {}",
                mission.mavlink.fence_margin_m, mission.mavlink.turn_radius_m
            );
            let rule = format!(
                "the fence leaves no room for {}'s launch point: no place {need:.1} m inside it (the autopilot's \
                 FENCE_MARGIN plus the turn) is left for it",
                v.id
            );
            return Err(ConfigError::Field {
                table: "mavlink",
                key: Some(key),
                rule,
            });
        };
        room.retain(|q| (q[0] - p[0]).hypot(q[1] - p[1]) >= 1.0);
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
