//! The run's final estimate and its variance as georeferenced GeoTIFFs (WGS 84, one float64
//! band, north up), so GDAL and QGIS place them on the site. The GeoTIFF keys are plain TIFF
//! tags: a tie point at the north-west corner, the pixel size in degrees, and
//! EPSG:4326 as the model; NaN (land, no value) is GDAL's no-data value.

use super::{ExportError, Run};
use std::path::{Path, PathBuf};
use tiff::encoder::{colortype::Gray64Float, TiffEncoder};
use tiff::tags::Tag;

/// GeoKeyDirectory: version 1.1.0, then (key, location, count, value) per key.
const GEO_KEYS: [u16; 16] = [
    1, 1, 0, 3, //
    1024, 0, 1, 2, // GTModelTypeGeoKey: geographic latitude-longitude
    1025, 0, 1, 1, // GTRasterTypeGeoKey: a pixel is an area (its corner is the tie point)
    2048, 0, 1, 4326, // GeographicTypeGeoKey: WGS 84
];

/// Write `estimate.tif` and `variance.tif` of the run's last step into `dir` (created if
/// needed); returns their paths.
pub fn write(run: &Run, dir: &Path) -> Result<Vec<PathBuf>, ExportError> {
    std::fs::create_dir_all(dir).map_err(|e| ExportError::Write {
        path: dir.into(),
        why: e.to_string(),
    })?;
    let last = run.estimate.steps - 1;
    let mut out = vec![];
    for (name, steps) in [("estimate.tif", &run.estimate), ("variance.tif", &run.variance)] {
        let path = dir.join(name);
        write_one(run, steps.step(last, &run.grid), &path)?;
        out.push(path);
    }
    Ok(out)
}

fn write_one(run: &Run, field: &[f64], path: &Path) -> Result<(), ExportError> {
    let failed = |why: String| ExportError::Write { path: path.into(), why };
    let (rows, cols) = (run.grid.rows, run.grid.cols);
    // Row 0 of the grid is its southern edge; a TIFF's first row is the northern one.
    let north_up: Vec<f64> = (0..rows)
        .rev()
        .flat_map(|r| field[r * cols..(r + 1) * cols].iter().copied())
        .collect();
    let [west, south, east, north] = run.bounds_deg();
    let scale = [(east - west) / cols as f64, (north - south) / rows as f64, 0.0];
    let tie = [0.0, 0.0, 0.0, west, north, 0.0];
    let tmp = path.with_extension("tif.partial");
    let written = (|| -> tiff::TiffResult<()> {
        let file = std::io::BufWriter::new(std::fs::File::create(&tmp)?);
        let mut enc = TiffEncoder::new(file)?;
        let mut image = enc.new_image::<Gray64Float>(cols as u32, rows as u32)?;
        image.encoder().write_tag(Tag::ModelPixelScaleTag, &scale[..])?;
        image.encoder().write_tag(Tag::ModelTiepointTag, &tie[..])?;
        image.encoder().write_tag(Tag::GeoKeyDirectoryTag, &GEO_KEYS[..])?;
        // GDAL's no-data tag, as GDAL writes it for a NaN (ASCII "nan"): land and cells with no
        // value are NaN, which without it GDAL and QGIS take for data.
        image.encoder().write_tag(Tag::GdalNodata, "nan")?;
        let last = run.estimate.steps - 1;
        let utc = run.utc_of(last);
        let at = utc.as_ref().map_or(String::new(), |t| format!(" at {t}"));
        let what = path.file_stem().unwrap_or_default().to_string_lossy();
        let description = format!("hetfleet {what} of mission {}, step {last}{at}", run.mission.mission);
        image.encoder().write_tag(Tag::ImageDescription, description.as_str())?;
        // TIFF's DateTime ("YYYY:MM:DD HH:MM:SS", here UTC): when the step began, with mission time.
        if let Some(t) = utc.filter(|t| t.len() >= 19 && t.as_bytes()[10] == b'T') {
            let datetime = format!("{} {}", t[..10].replace('-', ":"), &t[11..19]);
            image.encoder().write_tag(Tag::DateTime, datetime.as_str())?;
        }
        image.write_data(&north_up)
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(failed(e.to_string()));
    }
    std::fs::rename(&tmp, path).map_err(|e| failed(e.to_string()))
}
