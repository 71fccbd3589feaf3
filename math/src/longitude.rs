//! Longitudes in the range autopilots and receivers use: one wrap for the site's positions and
//! a file's bounds.

/// A longitude (or a difference of two) in [-180, 180); one already there is returned as it
/// is, to the bit (adding and taking away 180 would move its last bit).
pub fn wrap_longitude(lon: f64) -> f64 {
    match (-180.0..180.0).contains(&lon) {
        true => lon,
        false => (lon + 180.0).rem_euclid(360.0) - 180.0,
    }
}
