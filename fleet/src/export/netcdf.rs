//! `estimate.nc`: the run's fused estimate and its variance at every step (and the truth in a
//! mixed-reality run) as NetCDF-3 classic with CF-1.8 metadata, so `xarray.open_dataset`
//! gives `(time, y, x)` arrays with latitude and longitude beside them. Written by `netcdf3`
//! (pure Rust: nothing native to install).

use super::{ExportError, Run};
use netcdf3::error::WriteError;
use netcdf3::{DataSet, FileWriter, Version};
use std::path::Path;

/// Write `run` to `path`.
pub fn write(run: &Run, path: &Path) -> Result<(), ExportError> {
    let ds = define(run).map_err(|e| ExportError::Write {
        path: path.into(),
        why: format!("{e:?}"),
    })?;
    write_whole(path, &ds, |w| {
        let (x, y) = run.axes_m();
        let (lon, lat) = run.axes_deg();
        let time: Vec<f64> = (0..run.estimate.steps).map(|k| k as f64 * run.step_s()).collect();
        let step: Vec<i32> = (0..run.estimate.steps).map(|k| k as i32).collect();
        w.write_var_f64("time", &time)?;
        w.write_var_i32("step", &step)?;
        w.write_var_f64("x", &x)?;
        w.write_var_f64("y", &y)?;
        w.write_var_f64("lon", &lon)?;
        w.write_var_f64("lat", &lat)?;
        w.write_var_f64("estimate", &filled(&run.estimate.data))?;
        w.write_var_f64("variance", &filled(&run.variance.data))?;
        if let Some(t) = &run.truth {
            w.write_var_f64("truth", &filled(&t.data))?;
        }
        Ok(())
    })
}

/// Write the NetCDF-3 classic file of schema `ds` with `values` through a temporary beside
/// `path`, so a failed export leaves no half file under the name.
pub(super) fn write_whole(
    path: &Path,
    ds: &DataSet,
    values: impl FnOnce(&mut FileWriter) -> Result<(), WriteError>,
) -> Result<(), ExportError> {
    let failed = |why: String| ExportError::Write { path: path.into(), why };
    let tmp = path.with_extension("nc.partial");
    let written = (|| -> Result<(), WriteError> {
        let mut w = FileWriter::open(&tmp)?;
        w.set_def(ds, Version::Classic, 0)?;
        values(&mut w)?;
        w.close()
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(failed(format!("{e:?}")));
    }
    std::fs::rename(&tmp, path).map_err(|e| failed(e.to_string()))
}

/// NetCDF's default fill for doubles (`NC_FILL_DOUBLE`), the `_FillValue` of every field:
/// where there is no value (land, no data), which xarray decodes to NaN and GDAL to nodata.
pub(super) const FILL: f64 = 9.969_209_968_386_869e36;

/// NaN (no value) as the fill value.
fn filled(v: &[f64]) -> Vec<f64> {
    v.iter().map(|&x| if x.is_nan() { FILL } else { x }).collect()
}

/// A CF `since` date: UTC, `YYYY-MM-DD hh:mm:ss` (CF's own form, which every reader takes).
fn cf_epoch(t: f64) -> String {
    let iso = fleet_mission::instrument::MissionClock::rfc3339(t);
    iso.trim_end_matches('Z').replacen('T', " ", 1)
}

/// Long because it is the file's schema: every dimension, variable and attribute in the order
/// `ncdump -h` lists them (the global ones in [`discovery`]).
fn define(run: &Run) -> Result<DataSet, netcdf3::InvalidDataSet> {
    let mut ds = DataSet::new();
    ds.add_fixed_dim("time", run.estimate.steps)?;
    ds.add_fixed_dim("y", run.grid.rows)?;
    ds.add_fixed_dim("x", run.grid.cols)?;
    ds.add_var_f64("time", &["time"])?;
    let (long_name, units) = time_words(run);
    text(&mut ds, "time", &time_attrs(long_name, &units))?;
    ds.add_var_i32("step", &["time"])?;
    text(
        &mut ds,
        "step",
        &[
            ("long_name", "mission step (index of the truth frame)"),
            ("units", "1"),
            ("coverage_content_type", "coordinate"),
        ],
    )?;
    ds.add_var_f64("x", &["x"])?;
    text(
        &mut ds,
        "x",
        &[
            ("standard_name", "projection_x_coordinate"),
            (
                "long_name",
                "distance east of the site's south-west corner (cell centre)",
            ),
            ("units", "m"),
            ("axis", "X"),
        ],
    )?;
    ds.add_var_f64("y", &["y"])?;
    text(
        &mut ds,
        "y",
        &[
            ("standard_name", "projection_y_coordinate"),
            (
                "long_name",
                "distance north of the site's south-west corner (cell centre)",
            ),
            ("units", "m"),
            ("axis", "Y"),
        ],
    )?;
    ds.add_var_f64("lon", &["x"])?;
    text(
        &mut ds,
        "lon",
        &[
            ("standard_name", "longitude"),
            ("long_name", "longitude of the cell centre (WGS 84)"),
            ("units", "degrees_east"),
        ],
    )?;
    ds.add_var_f64("lat", &["y"])?;
    text(
        &mut ds,
        "lat",
        &[
            ("standard_name", "latitude"),
            ("long_name", "latitude of the cell centre (WGS 84)"),
            ("units", "degrees_north"),
        ],
    )?;
    let (unit, standard_name) = field_words(run);
    let (value_units, variance_units) = match &unit {
        Some(u) => (u.clone(), format!("({u})2")),
        None => ("1".to_string(), "1".to_string()),
    };
    // ACDD's coverage_content_type (ISO 19115-1): the estimate is a model's result, its
    // variance says how good it is, the truth is what it is checked against.
    let fields: &[(&str, &str, &str, &str)] = &[
        (
            "estimate",
            "fused estimate of the field (posterior mean of the model server)",
            &value_units,
            "modelResult",
        ),
        (
            "variance",
            "reported variance of the fused estimate per cell",
            &variance_units,
            "qualityInformation",
        ),
        (
            "truth",
            "the true field the vehicles sensed (mixed reality)",
            &value_units,
            "referenceInformation",
        ),
    ];
    // The estimate and the truth are the field's quantity (the variance is not, and CF has no
    // modifier for a variance).
    for (name, long, units, content) in fields {
        if *name == "truth" && run.truth.is_none() {
            continue;
        }
        ds.add_var_f64(name, &["time", "y", "x"])?;
        text(
            &mut ds,
            name,
            &[
                ("long_name", long),
                ("units", units),
                ("coordinates", "step lat lon"),
                ("coverage_content_type", content),
                (
                    "comment",
                    "units are the truth's (dimensionless for the simulated fields); variance in their square",
                ),
            ],
        )?;
        if let (Some(sn), false) = (&standard_name, *name == "variance") {
            ds.add_var_attr_string(name, "standard_name", sn)?;
        }
        ds.add_var_attr_f64(name, "_FillValue", vec![FILL])?;
    }
    let summary = format!(
        "The fused estimate of a field and its reported variance at each of the {} steps of hetfleet mission {}: \
         aerial frames and boat samples assimilated by a DMD model in a Kalman filter{}.",
        run.estimate.steps,
        run.mission.mission,
        if run.truth.is_some() {
            ", beside the truth the vehicles sensed"
        } else {
            ""
        }
    );
    let title = format!("hetfleet fused field of mission {}", run.mission.mission);
    discovery(&mut ds, run, &title, &summary)?;
    Ok(ds)
}

/// Text attributes of variable `var`.
pub(super) fn text(ds: &mut DataSet, var: &str, attrs: &[(&str, &str)]) -> Result<(), netcdf3::InvalidDataSet> {
    for (k, v) in attrs {
        ds.add_var_attr_string(var, k, v)?;
    }
    Ok(())
}

/// The time axis's `long_name` and `units`: with mission time a step is a span of UTC, and the
/// axis is CF time (xarray decodes it to datetime64); without it, the field's own seconds
/// since the mission's first step.
pub(super) fn time_words(run: &Run) -> (&'static str, String) {
    match run.mission.clock() {
        Some(c) => (
            "the start of the step in UTC",
            format!("seconds since {}", cf_epoch(c.start)),
        ),
        None => ("the field's own time since the mission's first step", "s".to_string()),
    }
}

/// A CF time variable's attributes.
pub(super) fn time_attrs<'a>(long_name: &'a str, units: &'a str) -> [(&'a str, &'a str); 5] {
    [
        ("standard_name", "time"),
        ("long_name", long_name),
        ("units", units),
        ("calendar", "standard"),
        ("axis", "T"),
    ]
}

/// What the field is, where the truth's file says it: its `units` and CF `standard_name`.
pub(super) fn field_words(run: &Run) -> (Option<String>, Option<String>) {
    let source = run.mission.truth.as_ref().map(|t| &t.source);
    (source.and_then(|s| s.units()), source.and_then(|s| s.standard_name()))
}

/// The global attributes a data centre's catalogue reads (CF-1.8 and ACDD-1.3): what the file
/// is, where and when its data are, and what made it.
pub(super) fn discovery(
    ds: &mut DataSet,
    run: &Run,
    title: &str,
    summary: &str,
) -> Result<(), netcdf3::InvalidDataSet> {
    ds.add_global_attr_string("Conventions", "CF-1.8, ACDD-1.3")?;
    ds.add_global_attr_string("summary", summary)?;
    ds.add_global_attr_string(
        "keywords",
        "data assimilation, dynamic mode decomposition, Kalman filter, heterogeneous robot team, \
         uncrewed surface vehicle, uncrewed aerial vehicle",
    )?;
    ds.add_global_attr_string("title", title)?;
    ds.add_global_attr_string(
        "history",
        format!("written by hetfleet from the run in {}", run.dir.display()),
    )?;
    ds.add_global_attr_string(
        "references",
        "Salam, T. and Hsieh, M. A.: Heterogeneous robot teams for modeling and prediction of multiscale \
            environmental processes (the method hetfleet implements)",
    )?;
    for (k, v) in run.provenance() {
        ds.add_global_attr_string(k, v)?;
    }
    let [w, s, e, n] = run.bounds_deg();
    ds.add_global_attr_f64("geospatial_lon_min", vec![w])?;
    ds.add_global_attr_f64("geospatial_lat_min", vec![s])?;
    ds.add_global_attr_f64("geospatial_lon_max", vec![e])?;
    ds.add_global_attr_f64("geospatial_lat_max", vec![n])?;
    ds.add_global_attr_string("geospatial_lat_units", "degrees_north")?;
    ds.add_global_attr_string("geospatial_lon_units", "degrees_east")?;
    if let Some(c) = run.mission.clock() {
        let end = c.start + run.estimate.steps as f64 * c.step_s;
        let iso = fleet_mission::instrument::MissionClock::rfc3339;
        ds.add_global_attr_string("time_coverage_start", iso(c.start))?;
        ds.add_global_attr_string("time_coverage_end", iso(end))?;
    }
    Ok(())
}
