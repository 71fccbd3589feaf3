//! The site's boundary: a polygon the planner keeps every disk and every aerial place inside
//! (`[mavlink] boundary`, a QGroundControl `.plan` with an inclusion geofence, or a GeoJSON
//! polygon). Read once from latitude and longitude into metres east and north of the site's
//! origin, so the team carries it without the file; each cell is in or out by its centre.

use crate::site::Site;
use fleet_math::grid::Grid;
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum FenceError {
    #[error("{path}: {why}")]
    Bad { path: String, why: String },
}

/// The boundary as the planner uses it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SiteFence {
    /// Vertices, metres `[east, north]` of the site's origin (the grid's (0, 0) corner), in order.
    pub polygon_m: Vec<[f64; 2]>,
    /// The site's physical extent (`[mavlink] size_m`), which scales grid metres to physical
    /// ones; `None`: one grid metre is one metre.
    pub size_m: Option<[f64; 2]>,
}

impl SiteFence {
    /// Which cells of `grid` lie outside (by their centres).
    pub fn excluded(&self, grid: &Grid) -> Vec<bool> {
        let (sx, sy) = self
            .size_m
            .map_or((1.0, 1.0), |[e, n]| (e / grid.width_m(), n / grid.height_m()));
        (0..grid.len())
            .map(|i| {
                let (x, y) = grid.centre_m(grid.cell(i));
                !inside(&self.polygon_m, [x * sx, y * sy])
            })
            .collect()
    }
}

/// Point in polygon by the even-odd rule (a ray to the east crosses the boundary an odd number
/// of times); concave polygons included.
pub fn inside(polygon: &[[f64; 2]], p: [f64; 2]) -> bool {
    let mut odd = false;
    let n = polygon.len();
    for i in 0..n {
        let (a, b) = (polygon[i], polygon[(i + n - 1) % n]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if p[0] < x {
                odd = !odd;
            }
        }
    }
    odd
}

/// How far `p` is inside the polygon: the distance to its nearest edge, negative outside.
/// What an autopilot's `FENCE_MARGIN` is measured against.
pub fn clearance(polygon: &[[f64; 2]], p: [f64; 2]) -> f64 {
    let n = polygon.len();
    let to_edge = |a: [f64; 2], b: [f64; 2]| {
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len2 = (dx * dx + dy * dy).max(1e-24);
        let t = (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0);
        (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
    };
    let d = (0..n)
        .map(|i| to_edge(polygon[i], polygon[(i + 1) % n]))
        .fold(f64::INFINITY, f64::min);
    if inside(polygon, p) {
        d
    } else {
        -d
    }
}

/// Whether segments `a`-`b` and `c`-`d` cross (touching counts).
fn crosses(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> bool {
    let orient = |p: [f64; 2], q: [f64; 2], r: [f64; 2]| (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]);
    let (d1, d2, d3, d4) = (orient(c, d, a), orient(c, d, b), orient(a, b, c), orient(a, b, d));
    (d1 * d2 <= 0.0) && (d3 * d4 <= 0.0) && !(d1 == 0.0 && d2 == 0.0 && d3 == 0.0 && d4 == 0.0)
}

/// Whether the straight leg `a`-`b` stays inside the polygon (both ends inside, no edge
/// crossed).
pub fn leg_inside(polygon: &[[f64; 2]], a: [f64; 2], b: [f64; 2]) -> bool {
    let n = polygon.len();
    inside(polygon, a) && inside(polygon, b) && (0..n).all(|i| !crosses(a, b, polygon[i], polygon[(i + 1) % n]))
}

/// The shortest way from `from` to `to` that stays inside the polygon: the corners to pass
/// (each set `inset` inside the polygon's corner) and then `to`. A straight leg when it stays
/// inside (always, for a convex fence); straight too when either end is outside (nothing to
/// route around) or no way is found. Dijkstra over the visibility graph of the inset corners:
/// a fence has tens of corners, so this is microseconds.
pub fn route(polygon: &[[f64; 2]], from: [f64; 2], to: [f64; 2], inset: f64) -> Vec<[f64; 2]> {
    if polygon.len() < 3 || leg_inside(polygon, from, to) || !inside(polygon, from) || !inside(polygon, to) {
        return vec![to];
    }
    let n = polygon.len();
    let unit = |v: [f64; 2]| {
        let l = v[0].hypot(v[1]).max(1e-12);
        [v[0] / l, v[1] / l]
    };
    // Corners moved `inset` along their bisector, to the inside.
    let mut nodes = vec![from, to];
    for i in 0..n {
        let (p, v, q) = (polygon[(i + n - 1) % n], polygon[i], polygon[(i + 1) % n]);
        let (u, w) = (unit([p[0] - v[0], p[1] - v[1]]), unit([q[0] - v[0], q[1] - v[1]]));
        let dir = unit([u[0] + w[0], u[1] + w[1]]);
        let c = [v[0] + inset * dir[0], v[1] + inset * dir[1]];
        let c = if inside(polygon, c) {
            c
        } else {
            [v[0] - inset * dir[0], v[1] - inset * dir[1]]
        };
        if inside(polygon, c) {
            nodes.push(c);
        }
    }
    let m = nodes.len();
    let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    let mut best = vec![f64::INFINITY; m];
    let mut prev = vec![usize::MAX; m];
    let mut done = vec![false; m];
    best[0] = 0.0;
    while let Some(u) = (0..m)
        .filter(|&i| !done[i] && best[i].is_finite())
        .min_by(|&a, &b| best[a].total_cmp(&best[b]))
    {
        done[u] = true;
        if u == 1 {
            break;
        }
        for v in 0..m {
            let d = best[u] + dist(nodes[u], nodes[v]);
            if !done[v] && d < best[v] && leg_inside(polygon, nodes[u], nodes[v]) {
                best[v] = d;
                prev[v] = u;
            }
        }
    }
    if !best[1].is_finite() {
        return vec![to];
    }
    let mut path = vec![];
    let mut at = 1;
    while at != 0 {
        path.push(nodes[at]);
        at = prev[at];
    }
    path.reverse();
    path
}

/// Read a boundary file: a QGroundControl `.plan` (its first inclusion polygon of `geoFence`)
/// or GeoJSON (a Polygon, or the first Polygon of a Feature or FeatureCollection; its outer
/// ring), as `[lat, lon]` vertices.
pub fn read_latlon(path: &Path) -> Result<Vec<[f64; 2]>, FenceError> {
    let bad = |why: String| FenceError::Bad {
        path: path.display().to_string(),
        why,
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let doc: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(format!("not JSON ({e})")))?;
    let vertices: Vec<[f64; 2]> = if doc.get("fileType").and_then(|t| t.as_str()) == Some("Plan") {
        let polygons = doc
            .pointer("/geoFence/polygons")
            .and_then(|p| p.as_array())
            .ok_or_else(|| bad("a QGroundControl plan without a geofence (no geoFence.polygons)".into()))?;
        let fence = polygons
            .iter()
            .find(|p| p.get("inclusion").and_then(|i| i.as_bool()).unwrap_or(true))
            .ok_or_else(|| bad("a QGroundControl plan whose geofence has no inclusion polygon".into()))?;
        let points = fence
            .get("polygon")
            .and_then(|p| p.as_array())
            .ok_or_else(|| bad("its geofence polygon has no `polygon` list".into()))?;
        points
            .iter()
            .map(|v| pair(v).ok_or_else(|| bad(format!("geofence vertex {v} is not [lat, lon]"))))
            .collect::<Result<_, _>>()?
    } else {
        let geometry = match doc.get("type").and_then(|t| t.as_str()) {
            Some("Polygon") => Some(&doc),
            Some("Feature") => doc.get("geometry"),
            Some("FeatureCollection") => doc.get("features").and_then(|f| f.as_array()).and_then(|f| {
                f.iter()
                    .filter_map(|x| x.get("geometry"))
                    .find(|g| g.get("type").and_then(|t| t.as_str()) == Some("Polygon"))
            }),
            _ => {
                return Err(bad(
                    "neither a QGroundControl plan (fileType \"Plan\") nor GeoJSON (type Polygon, Feature \
                or FeatureCollection)"
                        .into(),
                ))
            }
        };
        let ring = geometry
            .filter(|g| g.get("type").and_then(|t| t.as_str()) == Some("Polygon"))
            .and_then(|g| g.pointer("/coordinates/0"))
            .and_then(|r| r.as_array())
            .ok_or_else(|| bad("no GeoJSON Polygon with an outer ring in it".into()))?;
        // GeoJSON is [lon, lat].
        ring.iter()
            .map(|v| {
                pair(v)
                    .map(|[lon, lat]| [lat, lon])
                    .ok_or_else(|| bad(format!("GeoJSON position {v} is not [lon, lat]")))
            })
            .collect::<Result<_, _>>()?
    };
    let mut v = vertices;
    if v.len() > 1 && v.first() == v.last() {
        v.pop();
    }
    if v.len() < 3 {
        return Err(bad(format!(
            "a boundary needs at least 3 distinct vertices, found {}",
            v.len()
        )));
    }
    if let Some(p) = v.iter().find(|[lat, lon]| !(lat.abs() <= 90.0 && lon.abs() <= 180.0)) {
        return Err(bad(format!("vertex {p:?} is not a latitude and longitude")));
    }
    Ok(v)
}

fn pair(v: &serde_json::Value) -> Option<[f64; 2]> {
    let a = v.as_array()?;
    Some([a.first()?.as_f64()?, a.get(1)?.as_f64()?])
}

/// A boundary file as the planner's fence for a site at `origin` of extent `size_m`.
pub fn load(path: &Path, origin: [f64; 3], size_m: Option<[f64; 2]>) -> Result<SiteFence, FenceError> {
    let site = Site {
        origin,
        scale: nalgebra::Vector2::new(1.0, 1.0),
    };
    let polygon_m: Vec<[f64; 2]> = read_latlon(path)?
        .into_iter()
        .map(|[lat, lon]| {
            let ned = site.ned_of_global(lat, lon, origin[2]);
            [ned.y, ned.x]
        })
        .collect();
    let area2: f64 = (0..polygon_m.len())
        .map(|i| {
            let (a, b) = (polygon_m[i], polygon_m[(i + 1) % polygon_m.len()]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    if area2.abs() < 1e-6 {
        return Err(FenceError::Bad {
            path: path.display().to_string(),
            why: "the boundary encloses no area".into(),
        });
    }
    Ok(SiteFence { polygon_m, size_m })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An L: the square [0, 10]^2 without its north-east quarter.
    fn ell() -> Vec<[f64; 2]> {
        vec![
            [0.0, 0.0],
            [10.0, 0.0],
            [10.0, 5.0],
            [5.0, 5.0],
            [5.0, 10.0],
            [0.0, 10.0],
        ]
    }

    #[test]
    fn a_concave_polygon_keeps_out_its_notch() {
        let l = ell();
        assert!(inside(&l, [2.0, 2.0]) && inside(&l, [8.0, 2.0]) && inside(&l, [2.0, 8.0]));
        assert!(!inside(&l, [8.0, 8.0]) && !inside(&l, [11.0, 2.0]) && !inside(&l, [-1.0, 5.0]));
        let grid = Grid::new(10, 10, 1.0).unwrap();
        let ex = SiteFence {
            polygon_m: l,
            size_m: None,
        }
        .excluded(&grid);
        assert_eq!(ex.iter().filter(|&&x| x).count(), 25, "the notch is 5 x 5 cells");
        assert!(
            ex[grid.index(fleet_math::grid::Cell::new(9, 9))] && !ex[grid.index(fleet_math::grid::Cell::new(9, 0))]
        );
        // On a site scaled to 18 m x 18 m, cell centres are 1.8 m apart from 0.9 m: six per
        // axis inside the square, three of them in the notch, so 36 - 9 cells are in.
        let ex = SiteFence {
            polygon_m: ell(),
            size_m: Some([18.0, 18.0]),
        }
        .excluded(&grid);
        assert_eq!(ex.iter().filter(|&&x| !x).count(), 27, "{ex:?}");
    }

    #[test]
    fn a_route_round_the_notch_passes_its_corner_and_stays_inside() {
        let l = ell();
        // Across the notch: from the east arm's tip to the north arm's tip.
        let (a, b) = ([9.0, 2.0], [2.0, 9.0]);
        assert!(!leg_inside(&l, a, b), "the straight leg cuts the notch");
        let r = route(&l, a, b, 0.5);
        assert_eq!(r.len(), 2, "one corner: {r:?}");
        assert!(
            (r[0][0] - (5.0 - 0.5 / 2f64.sqrt())).abs() < 1e-9 && (r[0][1] - (5.0 - 0.5 / 2f64.sqrt())).abs() < 1e-9,
            "the re-entrant corner, inset: {r:?}"
        );
        assert_eq!(r[1], b);
        let mut at = a;
        for p in &r {
            assert!(leg_inside(&l, at, *p), "{at:?} -> {p:?}");
            at = *p;
        }
        // No routing needed, or nothing to route around.
        assert_eq!(route(&l, [1.0, 1.0], [9.0, 1.0], 0.5), vec![[9.0, 1.0]]);
        assert_eq!(
            route(&l, [8.0, 8.0], [1.0, 1.0], 0.5),
            vec![[1.0, 1.0]],
            "from outside: straight"
        );
        let square = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]];
        assert_eq!(route(&square, [1.0, 1.0], [9.0, 9.0], 0.5), vec![[9.0, 9.0]]);
    }

    #[test]
    fn plans_and_geojson_are_read_and_a_plan_without_a_fence_is_refused() {
        let dir = std::env::temp_dir().join(format!("hetfleet-fence-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let plan = dir.join("f.plan");
        let polygon = r#"[[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]"#;
        let text = format!(
            r#"{{"fileType": "Plan", "geoFence": {{"polygons": [{{"inclusion": true, "polygon": {polygon}}}], "version": 2}}}}"#
        );
        std::fs::write(&plan, text).unwrap();
        assert_eq!(
            read_latlon(&plan).unwrap(),
            vec![[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]
        );
        let gj = dir.join("f.geojson");
        std::fs::write(&gj, r#"{"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [[[12.0, 55.0], [12.1, 55.0], [12.1, 55.1], [12.0, 55.0]]]}}"#).unwrap();
        assert_eq!(
            read_latlon(&gj).unwrap(),
            vec![[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]
        );
        for (name, text, says) in [
            (
                "none.plan",
                r#"{"fileType": "Plan", "mission": {}}"#,
                "without a geofence",
            ),
            (
                "excl.plan",
                r#"{"fileType": "Plan", "geoFence": {"polygons": [{"inclusion": false, "polygon": [[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]}]}}"#,
                "no inclusion polygon",
            ),
            (
                "two.geojson",
                r#"{"type": "Polygon", "coordinates": [[[12.0, 55.0], [12.1, 55.0]]]}"#,
                "at least 3",
            ),
            ("cut.plan", r#"{"fileType": "Plan", "geoF"#, "not JSON"),
            ("other.json", r#"{"type": "Point", "coordinates": [1, 2]}"#, "neither"),
        ] {
            let p = dir.join(name);
            std::fs::write(&p, text).unwrap();
            let e = read_latlon(&p).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains(says), "{name}: {e}");
        }
    }
}
