//! An aerial's camera frame as a georeferenced raster (GeoTIFF: float32 or float64, one band,
//! north up, WGS 84 geographic or UTM), read as GDAL reads it, and resampled onto the model
//! grid by area: each cell is the mean of the raster under it (sampled at 4 x 4 points per
//! cell, so a pixel counts by the share of the cell it covers), pixels that are no-data
//! (`GDAL_NODATA`) or not finite count for nothing, and a cell the frame does not cover has no
//! value. A frame is timed by its TIFF `DateTime` (UTC) or a `_YYYYMMDDTHHMMSSZ` suffix in its
//! file name.

use crate::site::Site;
use fleet_math::grid::Grid;
use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;

/// Points per cell side when resampling.
const SUPERSAMPLE: usize = 4;
/// `GDAL_NODATA`, the no-data value as ASCII (GDAL's private tag).
const GDAL_NODATA: u16 = 42113;
/// The largest frame read (pixels): 16k x 16k.
const MAX_PIXELS: usize = 1 << 28;

/// The coordinate system of a frame's model space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Crs {
    /// EPSG:4326: x longitude, y latitude (degrees).
    Geographic,
    /// EPSG:326zz (north) or 327zz (south): x easting, y northing (metres).
    Utm { zone: u8, north: bool },
}

/// A decoded frame: `values` row-major from the northern row.
#[derive(Debug, Clone, PartialEq)]
pub struct GeoFrame {
    pub width: usize,
    pub height: usize,
    pub values: Vec<f64>,
    /// Model coordinates of the north-west corner of pixel (0, 0), and the pixel size.
    pub west: f64,
    pub north: f64,
    pub pixel: (f64, f64),
    pub crs: Crs,
    /// UTC seconds since 1970 from the `DateTime` tag, if it has one.
    pub time: Option<f64>,
}

/// Decode a GeoTIFF; the error says what is missing or not supported.
pub fn decode(bytes: &[u8]) -> Result<GeoFrame, String> {
    let mut limits = Limits::default();
    limits.decoding_buffer_size = MAX_PIXELS * 8;
    let mut d = Decoder::new(std::io::Cursor::new(bytes))
        .map_err(|e| format!("not a TIFF ({e})"))?
        .with_limits(limits);
    let (w, h) = d.dimensions().map_err(|e| e.to_string())?;
    let (width, height) = (w as usize, h as usize);
    let scale = d
        .get_tag_f64_vec(Tag::ModelPixelScaleTag)
        .map_err(|_| "no ModelPixelScale: not georeferenced, or not north up".to_string())?;
    let tie = d
        .get_tag_f64_vec(Tag::ModelTiepointTag)
        .map_err(|_| "no ModelTiepoint: not georeferenced".to_string())?;
    if scale.len() < 2 || tie.len() < 6 || !(scale[0] > 0.0 && scale[1] > 0.0) {
        return Err("a ModelPixelScale of two sizes > 0 and one tie point wanted (north up)".into());
    }
    let keys = d
        .get_tag_u16_vec(Tag::GeoKeyDirectoryTag)
        .map_err(|_| "no GeoKeyDirectory: not a GeoTIFF".to_string())?;
    let (crs, point) = crs_of(&keys)?;
    let values = match d.read_image().map_err(|e| format!("reading the pixels: {e}"))? {
        DecodingResult::F32(v) => v.into_iter().map(f64::from).collect::<Vec<_>>(),
        DecodingResult::F64(v) => v,
        _ => return Err("pixels must be float32 or float64".into()),
    };
    if values.len() != width * height {
        return Err(format!(
            "{} values for {width} x {height} pixels: one band wanted",
            values.len()
        ));
    }
    let nodata = d
        .get_tag_ascii_string(Tag::Unknown(GDAL_NODATA))
        .ok()
        .and_then(|s| s.trim_matches(char::from(0)).trim().parse::<f64>().ok());
    let values = values
        .into_iter()
        .map(|v| if nodata == Some(v) { f64::NAN } else { v })
        .collect();
    // A tie point at a pixel's centre (PixelIsPoint) is half a pixel from its corner.
    let half = if point { 0.5 } else { 0.0 };
    let (px, py) = (scale[0], scale[1]);
    Ok(GeoFrame {
        width,
        height,
        values,
        west: tie[3] - (tie[0] + half) * px,
        north: tie[4] + (tie[1] + half) * py,
        pixel: (px, py),
        crs,
        time: d.get_tag_ascii_string(Tag::DateTime).ok().and_then(|s| tiff_time(&s)),
    })
}

/// The model's coordinate system and whether the raster is PixelIsPoint, from the GeoKeys.
fn crs_of(keys: &[u16]) -> Result<(Crs, bool), String> {
    let key = |id: u16| {
        keys.get(4..)?
            .chunks_exact(4)
            .find(|k| k[0] == id && k[1] == 0)
            .map(|k| k[3])
    };
    let point = key(1025) == Some(2);
    match (key(1024), key(2048), key(3072)) {
        (Some(2), Some(4326) | None, _) => Ok((Crs::Geographic, point)),
        (Some(1), _, Some(p @ 32601..=32660)) => Ok((
            Crs::Utm {
                zone: (p - 32600) as u8,
                north: true,
            },
            point,
        )),
        (Some(1), _, Some(p @ 32701..=32760)) => Ok((
            Crs::Utm {
                zone: (p - 32700) as u8,
                north: false,
            },
            point,
        )),
        (model, geographic, projected) => Err(format!(
            "coordinate system (model {model:?}, geographic {geographic:?}, projected {projected:?}) is not \
             WGS 84 geographic (EPSG:4326) or UTM (EPSG:326zz/327zz)"
        )),
    }
}

/// TIFF's `DateTime` (`YYYY:MM:DD HH:MM:SS`), read as UTC.
fn tiff_time(s: &str) -> Option<f64> {
    let s = s.trim_matches(char::from(0)).trim();
    let (date, time) = s.split_once(' ')?;
    let iso = format!("{}T{time}Z", date.replace(':', "-"));
    iso.parse::<jiff::Timestamp>()
        .ok()
        .map(|t| t.as_millisecond() as f64 / 1e3)
}

/// A frame file's bytes (named `name`) as the aerial takes it: its time (its DateTime, else the
/// `_YYYYMMDDTHHMMSSZ` in its name) and its values on `grid`, or why not.
pub fn frame_on_grid(bytes: &[u8], name: &str, site: &Site, grid: &Grid) -> Result<(f64, Vec<Option<f64>>), String> {
    let frame = decode(bytes)?;
    let Some(t) = frame.time.or_else(|| time_from_name(name)) else {
        return Err("no time: neither a TIFF DateTime nor a _YYYYMMDDTHHMMSSZ suffix".into());
    };
    Ok((t, frame.resample(site, grid)))
}

/// The time in a file name's `_YYYYMMDDTHHMMSSZ` suffix (before the extension).
pub fn time_from_name(name: &str) -> Option<f64> {
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    let (_, stamp) = stem.rsplit_once('_')?;
    let b = stamp.as_bytes();
    if b.len() != 16 || b[8] != b'T' || b[15] != b'Z' {
        return None;
    }
    let iso = format!(
        "{}-{}-{}T{}:{}:{}Z",
        &stamp[0..4],
        &stamp[4..6],
        &stamp[6..8],
        &stamp[9..11],
        &stamp[11..13],
        &stamp[13..15]
    );
    iso.parse::<jiff::Timestamp>()
        .ok()
        .map(|t| t.as_millisecond() as f64 / 1e3)
}

impl GeoFrame {
    /// The pixel value at latitude and longitude (`None` off the frame or no data).
    pub fn at(&self, lat: f64, lon: f64) -> Option<f64> {
        let (east, y) = match self.crs {
            // East of the frame's west edge the frame's way round: -179 is 11 degrees east of
            // a west edge at 170 (a frame across the dateline, or in 0..360).
            Crs::Geographic => ((lon - self.west).rem_euclid(360.0), lat),
            Crs::Utm { zone, north } => {
                // The crate adds the southern false northing by the point's own latitude; the
                // frame's zone says which one its coordinates carry.
                let (northing, easting, _) = utm::to_utm_wgs84(lat, lon, zone);
                let true_northing = northing - if lat > 0.0 { 0.0 } else { 10_000_000.0 };
                (
                    easting - self.west,
                    true_northing + if north { 0.0 } else { 10_000_000.0 },
                )
            }
        };
        let (c, r) = (east / self.pixel.0, (self.north - y) / self.pixel.1);
        if !(c >= 0.0 && r >= 0.0 && (c as usize) < self.width && (r as usize) < self.height) {
            return None;
        }
        Some(self.values[r as usize * self.width + c as usize]).filter(|v| v.is_finite())
    }

    /// The frame on the model grid, by area (see the module's doc): a value per cell, `None`
    /// where the frame has none.
    pub fn resample(&self, site: &Site, grid: &Grid) -> Vec<Option<f64>> {
        let n = SUPERSAMPLE as f64;
        (0..grid.len())
            .map(|i| {
                let cell = grid.cell(i);
                let (x0, y0) = (cell.col as f64 * grid.cell_m, cell.row as f64 * grid.cell_m);
                let (mut sum, mut count) = (0.0, 0usize);
                for a in 0..SUPERSAMPLE {
                    for b in 0..SUPERSAMPLE {
                        let p = (
                            x0 + (a as f64 + 0.5) / n * grid.cell_m,
                            y0 + (b as f64 + 0.5) / n * grid.cell_m,
                        );
                        let (lat, lon, _) = site.global_of(&site.ned_of(p, 0.0));
                        if let Some(v) = self.at(lat, lon) {
                            sum += v;
                            count += 1;
                        }
                    }
                }
                (count > 0).then(|| sum / count as f64)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tiff::encoder::{colortype::Gray32Float, TiffEncoder};

    /// A float32 GeoTIFF of `values` (`w` x `h`, northern row first) with the north-west corner
    /// at `(west, north)` and square pixels of `pixel` (`at`), GeoKeys `keys` and an optional
    /// `DateTime`.
    pub fn geotiff(w: u32, h: u32, values: &[f32], at: [f64; 3], keys: &[u16], when: Option<&str>) -> Vec<u8> {
        let [west, north, pixel] = at;
        let mut out = std::io::Cursor::new(vec![]);
        let mut enc = TiffEncoder::new(&mut out).unwrap();
        let mut image = enc.new_image::<Gray32Float>(w, h).unwrap();
        image
            .encoder()
            .write_tag(Tag::ModelPixelScaleTag, &[pixel, pixel, 0.0][..])
            .unwrap();
        image
            .encoder()
            .write_tag(Tag::ModelTiepointTag, &[0.0, 0.0, 0.0, west, north, 0.0][..])
            .unwrap();
        image.encoder().write_tag(Tag::GeoKeyDirectoryTag, keys).unwrap();
        if let Some(t) = when {
            image.encoder().write_tag(Tag::DateTime, t).unwrap();
        }
        image.encoder().write_tag(Tag::Unknown(GDAL_NODATA), "-9999").unwrap();
        image.write_data(values).unwrap();
        out.into_inner()
    }

    const GEOGRAPHIC: [u16; 12] = [1, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326];

    #[test]
    fn a_geographic_frame_lands_on_the_cells_under_it() {
        let grid = Grid::new(4, 4, 1.0).unwrap();
        let site = Site::new([55.0, 12.0, 0.0], Some([400.0, 400.0]), &grid);
        // The site spans 400 m: a frame of 2 x 2 pixels, each covering a quarter of it.
        let (lat1, lon1, _) = site.global_of(&site.ned_of((4.0, 4.0), 0.0));
        let px = (lon1 - 12.0) / 2.0;
        let py = (lat1 - 55.0) / 2.0;
        // Square pixels in degrees would not fit: use the larger size and check by position.
        let p = px.max(py);
        let bytes = geotiff(
            2,
            2,
            &[1.0, 2.0, 3.0, -9999.0],
            [12.0, 55.0 + 2.0 * p, p],
            &GEOGRAPHIC,
            Some("2026:11:25 09:00:30"),
        );
        let f = decode(&bytes).unwrap();
        assert_eq!((f.width, f.height, f.crs), (2, 2, Crs::Geographic));
        assert_eq!(f.time, Some(1_795_597_230.0));
        assert!(f.values[3].is_nan(), "no-data is no value");
        let cells = f.resample(&site, &grid);
        // The south-west corner cell is under pixel (row 1, col 0) = 3.0; the south-east under
        // the no-data pixel or off the frame: no value.
        assert_eq!(cells[0], Some(3.0));
        assert!(cells
            .iter()
            .all(|v| v.is_none_or(|v| [1.0, 2.0, 3.0].contains(&v) || (1.0..=3.0).contains(&v))));
        assert!(cells.iter().any(Option::is_none));
    }

    #[test]
    fn a_geographic_frame_across_the_dateline_is_read_on_both_sides() {
        // A site whose eastern half is past 180 (its autopilot longitudes there are -179.9...)
        // and a frame of 2 x 2 pixels with its west edge at the site's: each half under a column
        // (square pixels of half the site's width in degrees cover its height at 17 S).
        let grid = Grid::new(4, 4, 1.0).unwrap();
        let site = Site::new([-17.0, 179.999, 0.0], Some([400.0, 400.0]), &grid);
        let (north, east) = site.map_of(&site.ned_of((4.0, 4.0), 0.0));
        let p = (east - 179.999) / 2.0;
        assert!(east > 180.0 && 2.0 * p > north + 17.0);
        let f = decode(&geotiff(
            2,
            2,
            &[1.0, 2.0, 1.0, 2.0],
            [179.999, north, p],
            &GEOGRAPHIC,
            None,
        ))
        .unwrap();
        let cells = f.resample(&site, &grid);
        assert_eq!((cells[0], cells[3]), (Some(1.0), Some(2.0)), "{cells:?}");
        // A frame stored in 0..360 reads a site in -180..180 the same way.
        let west = Site::new([-17.0, -10.0, 0.0], Some([400.0, 400.0]), &grid);
        let (_, e) = west.map_of(&west.ned_of((4.0, 4.0), 0.0));
        let f = decode(&geotiff(1, 1, &[5.0], [350.0, north, e - -10.0], &GEOGRAPHIC, None)).unwrap();
        assert_eq!(f.resample(&west, &grid)[0], Some(5.0));
    }

    #[test]
    fn a_utm_frame_is_placed_by_its_zone() {
        // A linear field in easting, in UTM zone 33 north (the default mission's origin).
        let grid = Grid::new(10, 20, 1.0).unwrap();
        let site = Site::new([55.6761, 12.5683, 0.0], Some([200.0, 100.0]), &grid);
        let (n0, e0, _) = utm::to_utm_wgs84(55.6761, 12.5683, 33);
        let (west, north) = ((e0 - 50.0).floor(), (n0 + 150.0).floor());
        let (w, h) = (300u32, 200u32);
        let values: Vec<f32> = (0..h).flat_map(|_| (0..w).map(|c| c as f32)).collect();
        let keys = [1, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633];
        let f = decode(&geotiff(w, h, &values, [west, north, 1.0], &keys, None)).unwrap();
        assert_eq!(f.crs, Crs::Utm { zone: 33, north: true });
        let cells = f.resample(&site, &grid);
        for (i, v) in cells.iter().enumerate() {
            let (x, y) = grid.centre_m(grid.cell(i));
            let (lat, lon, _) = site.global_of(&site.ned_of((x, y), 0.0));
            let (_, e, _) = utm::to_utm_wgs84(lat, lon, 33);
            // Pixel c covers eastings [west + c, west + c + 1): its value is the floor; the
            // 4 x 4 points of a 10 m cell span whole pixels, so the mean is within a pixel.
            let want = e - west - 0.5;
            assert!((v.unwrap() - want).abs() < 1.0, "cell {i}: {v:?} vs {want}");
        }
    }

    #[test]
    fn what_is_not_a_north_up_wgs84_float_geotiff_is_refused_with_why() {
        assert!(decode(b"not a tiff").unwrap_err().contains("not a TIFF"));
        let mercator = [1, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 3857];
        let e = decode(&geotiff(2, 2, &[0.0; 4], [0.0, 0.0, 1.0], &mercator, None)).unwrap_err();
        assert!(e.contains("EPSG:4326"), "{e}");
        assert_eq!(time_from_name("frame_20261125T090030Z.tif"), Some(1_795_597_230.0));
        assert_eq!(time_from_name("frame.tif"), None);
        assert_eq!(time_from_name("frame_20261325T090030Z.tif"), None);
    }
}
