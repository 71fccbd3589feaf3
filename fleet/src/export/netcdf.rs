//! `estimate.nc`: the run's fused estimate and its variance at every step (and the truth in a
//! mixed-reality run) as NetCDF-4 with CF-1.8 and ACDD-1.3 metadata, so `xarray.open_dataset`
//! gives `(time, y, x)` arrays with latitude and longitude beside them, compressed per step.
//!
//! Precision is what each variable needs. The estimate and its variance are single precision:
//! rounding moves a value by at most 2^-24 of itself (6e-8), far below what the estimate says
//! of its own error (at most 7e-6 of its reported standard deviation on the default mission),
//! and it halves their share of the file.
//! The truth stays double, as the file it came from may hold it, so a score recomputed from
//! this file is the server's; so do the coordinates, which place the cells to a millimetre.

use super::nc4::{schema_error, Error, Nc4};
use super::{ExportError, Run};
use netcdf_writer::{DimensionId, NcAttrValue};
use std::path::Path;

/// Write `run` to `path`.
pub fn write(run: &Run, path: &Path) -> Result<(), ExportError> {
    let mut nc = Nc4::new();
    define(&mut nc, run).map_err(schema_error(path))?;
    nc.write(path)
}

/// NetCDF's default fill for doubles (`NC_FILL_DOUBLE`), written where there is no value.
pub(super) const FILL: f64 = netcdf_writer::NC_FILL_DOUBLE;

/// NaN (no value) as the fill value.
fn filled(v: &[f64]) -> Vec<f64> {
    v.iter().map(|&x| if x.is_nan() { FILL } else { x }).collect()
}

/// NaN as the single-precision fill value, every other value rounded to the nearest float.
fn filled_f32(v: &[f64]) -> Vec<f32> {
    v.iter()
        .map(|&x| {
            if x.is_nan() {
                netcdf_writer::NC_FILL_FLOAT
            } else {
                x as f32
            }
        })
        .collect()
}

/// The file: its axes, its fields and what a catalogue reads.
fn define(nc: &mut Nc4, run: &Run) -> Result<(), Error> {
    let time = (nc.dim("time", run.estimate.steps)?, run.estimate.steps);
    let y = (nc.dim("y", run.grid.rows)?, run.grid.rows);
    let x = (nc.dim("x", run.grid.cols)?, run.grid.cols);
    axes(nc, run, [time, y, x])?;
    fields(nc, run, &[time, y, x])?;
    let summary = format!(
        "The fused estimate of a field and its reported variance at each of the {} steps of hetfleet mission {}: \
         aerial frames and boat samples assimilated by a DMD model in a Kalman filter{}.{}",
        run.estimate.steps,
        run.mission.mission,
        if run.truth.is_some() {
            ", beside the truth the vehicles sensed"
        } else {
            ""
        },
        if run.finished {
            ""
        } else {
            " The model server stopped before the mission's end: these are the steps it made."
        }
    );
    let title = format!("hetfleet fused field of mission {}", run.mission.mission);
    discovery(nc, run, &title, &summary)
}

/// The coordinates: time and step, metres from the site's corner, latitude and longitude.
fn axes(nc: &mut Nc4, run: &Run, [time, y, x]: [(DimensionId, usize); 3]) -> Result<(), Error> {
    let t = run.time();
    let v = nc.var("time", &[time], &t.values)?;
    nc.text(v, &t.attrs())?;
    let step: Vec<i32> = (0..run.estimate.steps).map(|k| k as i32).collect();
    let v = nc.var("step", &[time], &step)?;
    nc.text(
        v,
        &[
            ("long_name", "mission step (index of the truth frame)"),
            ("units", "1"),
            ("coverage_content_type", "coordinate"),
        ],
    )?;
    let (xs, ys) = run.axes_m();
    let (lon, lat) = run.axes_deg();
    for (name, dim, values, axis, long) in [
        (
            "x",
            x,
            &xs,
            "X",
            "distance east of the site's south-west corner (cell centre)",
        ),
        (
            "y",
            y,
            &ys,
            "Y",
            "distance north of the site's south-west corner (cell centre)",
        ),
    ] {
        let v = nc.var(name, &[dim], values)?;
        let standard_name = format!("projection_{name}_coordinate");
        nc.text(
            v,
            &[
                ("standard_name", &standard_name),
                ("long_name", long),
                ("units", "m"),
                ("axis", axis),
            ],
        )?;
    }
    for (name, dim, values, standard_name, units) in [
        ("lon", x, &lon, "longitude", "degrees_east"),
        ("lat", y, &lat, "latitude", "degrees_north"),
    ] {
        let v = nc.var(name, &[dim], values)?;
        let long = format!("{standard_name} of the cell centre (WGS 84)");
        nc.text(
            v,
            &[("standard_name", standard_name), ("long_name", &long), ("units", units)],
        )?;
    }
    Ok(())
}

/// The estimate, its variance and the truth, `(time, y, x)`.
fn fields(nc: &mut Nc4, run: &Run, dims: &[(DimensionId, usize); 3]) -> Result<(), Error> {
    let (unit, standard_name) = field_words(run);
    let (value_units, variance_units) = match &unit {
        Some(u) => (u.clone(), format!("({u})2")),
        None => ("1".to_string(), "1".to_string()),
    };
    // ACDD's coverage_content_type (ISO 19115-1): the estimate is a model's result, its
    // variance says how good it is, the truth is what it is checked against.
    let estimate = nc.var("estimate", dims, &filled_f32(&run.estimate.data))?;
    nc.fill_f32(estimate)?;
    let long = "fused estimate of the field (posterior mean of the model server)";
    field_attrs(nc, estimate, long, &value_units, "modelResult")?;
    let variance = nc.var("variance", dims, &filled_f32(&run.variance.data))?;
    nc.fill_f32(variance)?;
    let long = "reported variance of the fused estimate per cell";
    field_attrs(nc, variance, long, &variance_units, "qualityInformation")?;
    let mut quantities = vec![estimate];
    if let Some(t) = &run.truth {
        let truth = nc.var("truth", dims, &filled(&t.data))?;
        nc.fill_f64(truth)?;
        let long = "the true field the vehicles sensed (mixed reality)";
        field_attrs(nc, truth, long, &value_units, "referenceInformation")?;
        quantities.push(truth);
    }
    // The estimate and the truth are the field's quantity (the variance is not, and CF has no
    // modifier for a variance).
    if let Some(sn) = &standard_name {
        for v in quantities {
            nc.text(v, &[("standard_name", sn)])?;
        }
    }
    Ok(())
}

/// What a field variable is, in CF's and ACDD's words.
fn field_attrs(
    nc: &mut Nc4,
    var: netcdf_writer::VariableId,
    long: &str,
    units: &str,
    content: &str,
) -> Result<(), Error> {
    nc.text(
        var,
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
    )
}

/// What the field is, where the truth's file says it: its `units` and CF `standard_name`.
pub(super) fn field_words(run: &Run) -> (Option<String>, Option<String>) {
    let source = run.mission.truth.as_ref().map(|t| &t.source);
    (source.and_then(|s| s.units()), source.and_then(|s| s.standard_name()))
}

/// The global attributes a data centre's catalogue reads (CF-1.8 and ACDD-1.3): what the file
/// is, where and when its data are, and what made it.
pub(super) fn discovery(nc: &mut Nc4, run: &Run, title: &str, summary: &str) -> Result<(), Error> {
    nc.global_text("Conventions", "CF-1.8, ACDD-1.3")?;
    nc.global_text("summary", summary)?;
    nc.global_text(
        "keywords",
        "data assimilation, dynamic mode decomposition, Kalman filter, heterogeneous robot team, \
         uncrewed surface vehicle, uncrewed aerial vehicle",
    )?;
    nc.global_text("title", title)?;
    nc.global_text(
        "history",
        format!("written by hetfleet from the run in {}", run.dir.display()),
    )?;
    nc.global_text(
        "references",
        "Salam, T. and Hsieh, M. A.: Heterogeneous robot teams for modeling and prediction of multiscale \
            environmental processes (the method hetfleet implements)",
    )?;
    for (k, v) in run.provenance() {
        nc.global_text(k, v)?;
    }
    let [w, s, e, n] = run.bounds_deg();
    for (k, v) in [
        ("geospatial_lon_min", w),
        ("geospatial_lat_min", s),
        ("geospatial_lon_max", e),
        ("geospatial_lat_max", n),
    ] {
        nc.global(k, NcAttrValue::Doubles(vec![v]))?;
    }
    nc.global_text("geospatial_lat_units", "degrees_north")?;
    nc.global_text("geospatial_lon_units", "degrees_east")?;
    if let Some(c) = run.mission.clock() {
        let end = c.start + run.estimate.steps as f64 * c.step_s;
        let iso = fleet_mission::instrument::MissionClock::rfc3339;
        nc.global_text("time_coverage_start", iso(c.start))?;
        nc.global_text("time_coverage_end", iso(end))?;
    } else if let (Some(first), Some(last)) = (run.time().date_of(0), run.time().date_of(run.estimate.steps - 1)) {
        // ACDD's coverage in the truth file's calendar, which ISO 8601 has no word for.
        nc.global_text("time_coverage_start", first.replacen(' ', "T", 1))?;
        nc.global_text("time_coverage_end", last.replacen(' ', "T", 1))?;
    }
    Ok(())
}
