//! Where the workspace is on the Earth: grid metres (x east, y north from the grid's (0, 0)
//! corner) to the autopilot's local NED frame (origin at that corner) and to latitude and
//! longitude. The grid may be scaled onto a physical extent (the paper's 4.5 m x 3.0 m tank, or
//! a field site); the flat-Earth approximation is well under a centimetre over a few kilometres.

use fleet_math::grid::Grid;
use fleet_math::longitude::wrap_longitude;
use nalgebra::{Vector2, Vector3};

/// WGS-84 equatorial radius (m).
pub const EARTH_RADIUS_M: f64 = 6_378_137.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Site {
    /// Latitude, longitude (degrees) and altitude AMSL (m) of the NED origin.
    pub origin: [f64; 3],
    /// Physical metres per grid metre, east and north.
    pub scale: Vector2<f64>,
}

impl Site {
    pub fn new(origin: [f64; 3], size_m: Option<[f64; 2]>, grid: &Grid) -> Self {
        let (w, h) = (grid.width_m(), grid.height_m());
        let scale = size_m.map_or(Vector2::new(1.0, 1.0), |[e, n]| Vector2::new(e / w, n / h));
        Self { origin, scale }
    }

    /// A grid point at height `up` (m above the origin) in local NED.
    pub fn ned_of(&self, grid_xy: (f64, f64), up: f64) -> Vector3<f64> {
        Vector3::new(grid_xy.1 * self.scale.y, grid_xy.0 * self.scale.x, -up)
    }

    /// The grid point under a local NED position.
    pub fn grid_of(&self, ned: &Vector3<f64>) -> (f64, f64) {
        (ned.y / self.scale.x, ned.x / self.scale.y)
    }

    /// Latitude, longitude (degrees) and altitude AMSL of a local NED position, the longitude in
    /// [-180, 180) as autopilots and receivers give and take it: ArduPilot refuses a waypoint
    /// past 180 (`check_latlng`), and a site across the dateline has its east in -180...
    pub fn global_of(&self, ned: &Vector3<f64>) -> (f64, f64, f64) {
        let (lat, lon) = self.map_of(ned);
        (lat, wrap_longitude(lon), self.origin[2] - ned.z)
    }

    /// Latitude and longitude of a local NED position on the site's map: the longitude
    /// continuous from the origin's (past 180 east of a dateline), as a map's axes and a
    /// GeoTIFF's transform need it.
    pub fn map_of(&self, ned: &Vector3<f64>) -> (f64, f64) {
        let [lat0, lon0, _] = self.origin;
        let lat = lat0 + (ned.x / EARTH_RADIUS_M).to_degrees();
        let lon = lon0 + (ned.y / (EARTH_RADIUS_M * lat0.to_radians().cos())).to_degrees();
        (lat, lon)
    }

    /// The local NED position of a latitude, longitude and altitude AMSL; the longitude taken
    /// the short way round from the origin's (-179.9 is 0.2 degrees east of 179.9).
    pub fn ned_of_global(&self, lat: f64, lon: f64, alt: f64) -> Vector3<f64> {
        let [lat0, lon0, alt0] = self.origin;
        let north = (lat - lat0).to_radians() * EARTH_RADIUS_M;
        let east = wrap_longitude(lon - lon0).to_radians() * EARTH_RADIUS_M * lat0.to_radians().cos();
        Vector3::new(north, east, alt0 - alt)
    }

    /// A physical distance (m) in grid metres (the smaller scale: a bound that holds both ways).
    pub fn grid_distance(&self, metres: f64) -> f64 {
        metres / self.scale.x.max(self.scale.y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tank_maps_its_corners_and_round_trips() {
        let grid = Grid::new(48, 96, 1.0).unwrap();
        let cfg = crate::config::MavlinkConfig::default();
        let site = Site::new(cfg.origin, Some([4.5, 3.0]), &grid);
        let far = site.ned_of((96.0, 48.0), 0.0);
        assert!((far.x - 3.0).abs() < 1e-12 && (far.y - 4.5).abs() < 1e-12, "{far}");
        let p = (12.5, 30.25);
        let back = site.grid_of(&site.ned_of(p, 2.0));
        assert!((back.0 - p.0).abs() < 1e-12 && (back.1 - p.1).abs() < 1e-12);
        let ned = Vector3::new(120.0, -45.0, -10.0);
        let (lat, lon, alt) = site.global_of(&ned);
        assert!(lat > cfg.origin[0] && lon < cfg.origin[1] && (alt - 10.0).abs() < 1e-9);
        // One degree of latitude is about 111.3 km.
        assert!(((lat - cfg.origin[0]) * 111_319.5 - 120.0).abs() < 0.1);
        assert!((site.ned_of_global(lat, lon, alt) - ned).norm() < 1e-6);
    }

    #[test]
    fn a_site_across_the_dateline_gives_autopilots_longitudes_within_180_and_maps_one_box() {
        let grid = Grid::new(10, 10, 100.0).unwrap();
        let site = Site::new([-17.0, 179.99, 0.0], None, &grid);
        // 2 km east of the origin is past the dateline.
        let east = Vector3::new(0.0, 2_000.0, 0.0);
        let (lat, lon, _) = site.global_of(&east);
        let (_, map_lon) = site.map_of(&east);
        assert!(map_lon > 180.0 && (-180.0..-179.9).contains(&lon), "{lon} {map_lon}");
        assert!((map_lon - lon - 360.0).abs() < 1e-9);
        // Back from the autopilot's longitude, or the map's: the same point, not 40,000 km west.
        assert!((site.ned_of_global(lat, lon, 0.0) - east).norm() < 1e-6);
        assert!((site.ned_of_global(lat, map_lon, 0.0) - east).norm() < 1e-6);
        assert_eq!(wrap_longitude(180.0), -180.0);
        assert_eq!(wrap_longitude(-180.0), -180.0);
        assert_eq!(wrap_longitude(190.0), -170.0);
    }
}
