//! The site's boundary: a polygon the planner keeps every disk and every aerial place inside
//! (`[mavlink] boundary`, a QGroundControl `.plan` with an inclusion geofence, or a GeoJSON
//! polygon). Read once from latitude and longitude into metres east and north of the site's
//! origin, so the team carries it without the file; each cell is in or out by its centre.

use crate::grid::Grid;
use crate::site::Site;
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
        let (sx, sy) = self.size_m.map_or((1.0, 1.0), |[e, n]| (e / grid.width_m(), n / grid.height_m()));
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

/// Read a boundary file: a QGroundControl `.plan` (its first inclusion polygon of `geoFence`)
/// or GeoJSON (a Polygon, or the first Polygon of a Feature or FeatureCollection; its outer
/// ring), as `[lat, lon]` vertices.
pub fn read_latlon(path: &Path) -> Result<Vec<[f64; 2]>, FenceError> {
    let bad = |why: String| FenceError::Bad { path: path.display().to_string(), why };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let doc: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(format!("not JSON ({e})")))?;
    let vertices: Vec<[f64; 2]> = if doc.get("fileType").and_then(|t| t.as_str()) == Some("Plan") {
        let polygons = doc.pointer("/geoFence/polygons").and_then(|p| p.as_array()).ok_or_else(|| bad("a QGroundControl plan without a geofence (no geoFence.polygons)".into()))?;
        let fence =
            polygons.iter().find(|p| p.get("inclusion").and_then(|i| i.as_bool()).unwrap_or(true)).ok_or_else(|| bad("a QGroundControl plan whose geofence has no inclusion polygon".into()))?;
        let points = fence.get("polygon").and_then(|p| p.as_array()).ok_or_else(|| bad("its geofence polygon has no `polygon` list".into()))?;
        points.iter().map(|v| pair(v).ok_or_else(|| bad(format!("geofence vertex {v} is not [lat, lon]")))).collect::<Result<_, _>>()?
    } else {
        let geometry = match doc.get("type").and_then(|t| t.as_str()) {
            Some("Polygon") => Some(&doc),
            Some("Feature") => doc.get("geometry"),
            Some("FeatureCollection") => {
                doc.get("features").and_then(|f| f.as_array()).and_then(|f| f.iter().filter_map(|x| x.get("geometry")).find(|g| g.get("type").and_then(|t| t.as_str()) == Some("Polygon")))
            }
            _ => return Err(bad("neither a QGroundControl plan (fileType \"Plan\") nor GeoJSON (type Polygon, Feature or FeatureCollection)".into())),
        };
        let ring = geometry
            .filter(|g| g.get("type").and_then(|t| t.as_str()) == Some("Polygon"))
            .and_then(|g| g.pointer("/coordinates/0"))
            .and_then(|r| r.as_array())
            .ok_or_else(|| bad("no GeoJSON Polygon with an outer ring in it".into()))?;
        // GeoJSON is [lon, lat].
        ring.iter().map(|v| pair(v).map(|[lon, lat]| [lat, lon]).ok_or_else(|| bad(format!("GeoJSON position {v} is not [lon, lat]")))).collect::<Result<_, _>>()?
    };
    let mut v = vertices;
    if v.len() > 1 && v.first() == v.last() {
        v.pop();
    }
    if v.len() < 3 {
        return Err(bad(format!("a boundary needs at least 3 distinct vertices, found {}", v.len())));
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
    let site = Site { origin, scale: nalgebra::Vector2::new(1.0, 1.0) };
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
        return Err(FenceError::Bad { path: path.display().to_string(), why: "the boundary encloses no area".into() });
    }
    Ok(SiteFence { polygon_m, size_m })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An L: the square [0, 10]^2 without its north-east quarter.
    fn ell() -> Vec<[f64; 2]> {
        vec![[0.0, 0.0], [10.0, 0.0], [10.0, 5.0], [5.0, 5.0], [5.0, 10.0], [0.0, 10.0]]
    }

    #[test]
    fn a_concave_polygon_keeps_out_its_notch() {
        let l = ell();
        assert!(inside(&l, [2.0, 2.0]) && inside(&l, [8.0, 2.0]) && inside(&l, [2.0, 8.0]));
        assert!(!inside(&l, [8.0, 8.0]) && !inside(&l, [11.0, 2.0]) && !inside(&l, [-1.0, 5.0]));
        let grid = Grid::new(10, 10, 1.0).unwrap();
        let ex = SiteFence { polygon_m: l, size_m: None }.excluded(&grid);
        assert_eq!(ex.iter().filter(|&&x| x).count(), 25, "the notch is 5 x 5 cells");
        assert!(ex[grid.index(crate::grid::Cell::new(9, 9))] && !ex[grid.index(crate::grid::Cell::new(9, 0))]);
        // On a site scaled to 18 m x 18 m, cell centres are 1.8 m apart from 0.9 m: six per
        // axis inside the square, three of them in the notch, so 36 - 9 cells are in.
        let ex = SiteFence { polygon_m: ell(), size_m: Some([18.0, 18.0]) }.excluded(&grid);
        assert_eq!(ex.iter().filter(|&&x| !x).count(), 27, "{ex:?}");
    }

    #[test]
    fn plans_and_geojson_are_read_and_a_plan_without_a_fence_is_refused() {
        let dir = std::env::temp_dir().join(format!("hetfleet-fence-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let plan = dir.join("f.plan");
        std::fs::write(&plan, r#"{"fileType": "Plan", "geoFence": {"polygons": [{"inclusion": true, "polygon": [[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]}], "version": 2}}"#).unwrap();
        assert_eq!(read_latlon(&plan).unwrap(), vec![[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]);
        let gj = dir.join("f.geojson");
        std::fs::write(&gj, r#"{"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [[[12.0, 55.0], [12.1, 55.0], [12.1, 55.1], [12.0, 55.0]]]}}"#).unwrap();
        assert_eq!(read_latlon(&gj).unwrap(), vec![[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]);
        for (name, text, says) in [
            ("none.plan", r#"{"fileType": "Plan", "mission": {}}"#, "without a geofence"),
            ("excl.plan", r#"{"fileType": "Plan", "geoFence": {"polygons": [{"inclusion": false, "polygon": [[55.0, 12.0], [55.0, 12.1], [55.1, 12.1]]}]}}"#, "no inclusion polygon"),
            ("two.geojson", r#"{"type": "Polygon", "coordinates": [[[12.0, 55.0], [12.1, 55.0]]]}"#, "at least 3"),
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
