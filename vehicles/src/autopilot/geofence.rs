//! The simulated autopilot's geofence, from the items of a fence upload
//! (MAV_MISSION_TYPE_FENCE) as ArduPilot and PX4 take them: inclusion and exclusion polygons
//! (consecutive `MAV_CMD_NAV_FENCE_POLYGON_VERTEX_*` items, param1 the vertex count) and
//! circles (`MAV_CMD_NAV_FENCE_CIRCLE_*`, param1 the radius), and an optional return point.
//! Inside means inside every inclusion zone (any, when there are none) and outside every
//! exclusion zone.

use fleet_mission::fence::{clearance, inside};
use fleet_mission::site::Site;
use mavlink::dialects::ardupilotmega::{MavCmd, MavMissionResult, MISSION_ITEM_INT_DATA};
use nalgebra::Vector3;

/// Longest fence we take (ArduPilot's default FENCE_TOTAL allows about 80 points).
pub const MAX_FENCE_ITEMS: u16 = 200;

#[derive(Debug, Clone, Default, PartialEq)]
pub struct Geofence {
    /// Polygons, vertices `[east, north]` in local metres.
    inclusion: Vec<Vec<[f64; 2]>>,
    exclusion: Vec<Vec<[f64; 2]>>,
    /// Circles: centre `[east, north]` and radius (m).
    inclusion_circles: Vec<([f64; 2], f64)>,
    exclusion_circles: Vec<([f64; 2], f64)>,
}

impl Geofence {
    /// The fence the items describe (on `site`), or why they are refused.
    pub fn from_items(items: &[MISSION_ITEM_INT_DATA], site: &Site) -> Result<Self, MavMissionResult> {
        use MavCmd::*;
        let en = |i: &MISSION_ITEM_INT_DATA| {
            let ned = site.ned_of_global(i.x as f64 * 1e-7, i.y as f64 * 1e-7, site.origin[2]);
            [ned.y, ned.x]
        };
        let mut f = Self::default();
        let mut k = 0;
        while k < items.len() {
            let it = &items[k];
            if it.x.unsigned_abs() > 900_000_000 || it.y.unsigned_abs() > 1_800_000_000 {
                return Err(MavMissionResult::MAV_MISSION_INVALID);
            }
            match it.command {
                MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION | MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION => {
                    let n = it.param1;
                    if !(n >= 3.0 && n.fract() == 0.0) || k + n as usize > items.len() {
                        return Err(MavMissionResult::MAV_MISSION_INVALID_PARAM1);
                    }
                    let poly = &items[k..k + n as usize];
                    if poly.iter().any(|v| v.command != it.command || v.param1 != n) {
                        return Err(MavMissionResult::MAV_MISSION_INVALID_PARAM1);
                    }
                    let vertices: Vec<[f64; 2]> = poly.iter().map(en).collect();
                    if it.command == MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION {
                        &mut f.inclusion
                    } else {
                        &mut f.exclusion
                    }
                    .push(vertices);
                    k += n as usize;
                }
                MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION | MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION => {
                    if !(it.param1.is_finite() && it.param1 > 0.0) {
                        return Err(MavMissionResult::MAV_MISSION_INVALID_PARAM1);
                    }
                    let c = (en(it), it.param1 as f64);
                    if it.command == MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION {
                        &mut f.inclusion_circles
                    } else {
                        &mut f.exclusion_circles
                    }
                    .push(c);
                    k += 1;
                }
                MAV_CMD_NAV_FENCE_RETURN_POINT => k += 1,
                _ => return Err(MavMissionResult::MAV_MISSION_UNSUPPORTED),
            }
        }
        Ok(f)
    }

    pub fn is_empty(&self) -> bool {
        self.inclusion.is_empty()
            && self.exclusion.is_empty()
            && self.inclusion_circles.is_empty()
            && self.exclusion_circles.is_empty()
    }

    /// How far inside the fence a point is (m; negative outside) and the kind of zone nearest
    /// its edge (`Polygon` or `Circle`, as ArduPilot names them); `None` without a fence.
    pub fn clearance(&self, ned: &Vector3<f64>) -> Option<(f64, &'static str)> {
        let p = [ned.y, ned.x];
        let from_centre = |c: &[f64; 2]| (p[0] - c[0]).hypot(p[1] - c[1]);
        let polygons = (self.inclusion.iter().map(|poly| clearance(poly, p)))
            .chain(self.exclusion.iter().map(|poly| -clearance(poly, p)))
            .map(|d| (d, "Polygon"));
        let circles = (self.inclusion_circles.iter().map(|(c, r)| r - from_centre(c)))
            .chain(self.exclusion_circles.iter().map(|(c, r)| from_centre(c) - r))
            .map(|d| (d, "Circle"));
        polygons.chain(circles).min_by(|a, b| a.0.total_cmp(&b.0))
    }

    /// Whether a local NED point is inside the fence.
    pub fn contains(&self, ned: &Vector3<f64>) -> bool {
        let p = [ned.y, ned.x];
        let in_circle = |(c, r): &([f64; 2], f64)| (p[0] - c[0]).hypot(p[1] - c[1]) <= *r;
        let included = (self.inclusion.is_empty() && self.inclusion_circles.is_empty())
            || (self.inclusion.iter().all(|poly| inside(poly, p)) && self.inclusion_circles.iter().all(in_circle));
        included && !self.exclusion.iter().any(|poly| inside(poly, p)) && !self.exclusion_circles.iter().any(in_circle)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_math::grid::Grid;
    use fleet_mission::config::MavlinkConfig;

    fn item(site: &Site, command: MavCmd, param1: f32, north: f64, east: f64) -> MISSION_ITEM_INT_DATA {
        let (lat, lon, _) = site.global_of(&Vector3::new(north, east, 0.0));
        MISSION_ITEM_INT_DATA {
            command,
            param1,
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            ..Default::default()
        }
    }

    #[test]
    fn a_concave_inclusion_with_an_exclusion_circle_keeps_out_the_notch_and_the_hole() {
        let site = MavlinkConfig::default().site(&Grid::new(100, 100, 1.0).unwrap());
        let v = MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION;
        // An L (east, north): [0,100]^2 without its north-east quarter; a 5 m hole at (20, 20).
        let ell = [
            (0.0, 0.0),
            (100.0, 0.0),
            (100.0, 50.0),
            (50.0, 50.0),
            (50.0, 100.0),
            (0.0, 100.0),
        ];
        let mut items: Vec<_> = ell.iter().map(|&(e, n)| item(&site, v, 6.0, n, e)).collect();
        items.push(item(&site, MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, 5.0, 20.0, 20.0));
        let f = Geofence::from_items(&items, &site).unwrap();
        let at = |e: f64, n: f64| f.contains(&Vector3::new(n, e, 0.0));
        assert!(at(80.0, 10.0) && at(10.0, 80.0) && at(30.0, 30.0));
        assert!(!at(80.0, 80.0), "the notch");
        assert!(!at(21.0, 21.0), "the hole");
        assert!(!at(-1.0, 10.0) && !at(10.0, 101.0));
        // A polygon whose count does not match its items, or a mission item, is refused.
        assert_eq!(
            Geofence::from_items(&items[..4], &site),
            Err(MavMissionResult::MAV_MISSION_INVALID_PARAM1)
        );
        let mut bad = items.clone();
        bad[0].param1 = 2.0;
        assert_eq!(
            Geofence::from_items(&bad, &site),
            Err(MavMissionResult::MAV_MISSION_INVALID_PARAM1)
        );
        bad[0] = item(&site, MavCmd::MAV_CMD_NAV_WAYPOINT, 0.0, 0.0, 0.0);
        assert_eq!(
            Geofence::from_items(&bad, &site),
            Err(MavMissionResult::MAV_MISSION_UNSUPPORTED)
        );
        assert!(
            Geofence::from_items(&[], &site)
                .unwrap()
                .contains(&Vector3::new(1e6, 1e6, 0.0)),
            "no fence: everywhere"
        );
    }
}
