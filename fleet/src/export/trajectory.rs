//! `readings.nc`: the boats' readings of a run as a CF discrete-sampling-geometry trajectory
//! file (CF-1.8 chapter 9, a contiguous ragged array), the form ERDDAP, xarray with cf_xarray
//! and Panoply open: one trajectory per boat, each value at the centre of the cell it measured
//! with its noise standard deviation, and the sensor-health verdict the server held for the
//! boat at that step as a CF flag. The boats' readings are a survey's most precious data; inside
//! the journal only hetfleet can read them.
//!
//! Read from the model server's journal (`state/<mission>.redb`), which holds every batch it
//! accepted exactly once; the recording can hold a batch twice (a resend after a lost ack).

use super::nc4::{schema_error, Error, Nc4};
use super::netcdf::{discovery, field_words};
use super::{ExportError, Run};
use fleet_mission::protocol::{self, Body, Context, Health, MeasurementBatch, SensorVerdict, VehicleId, VehicleKind};
use netcdf_writer::{DimensionId, NcAttrValue};
use std::path::{Path, PathBuf};

/// One value a boat read.
#[derive(Debug, Clone, PartialEq)]
pub struct Reading {
    pub step: u64,
    /// The flat index of the cell measured.
    pub cell: u32,
    pub value: f64,
    /// The value's noise standard deviation: the instrument's own where it said one, else the
    /// boat's sensor model at the cell's distance from the boat.
    pub sigma: f64,
    pub flag: Health,
}

/// A boat's readings in the order of their steps.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    pub boat: String,
    pub readings: Vec<Reading>,
}

/// The CF flag of each verdict: `flag_values` 0, 1, 2 mean `flag_meanings`.
const FLAG_MEANINGS: &str = "ok suspect excluded";

fn flag_value(h: Health) -> i8 {
    match h {
        Health::Ok => 0,
        Health::Suspect => 1,
        Health::Excluded => 2,
    }
}

/// Where the server's journal of a run lives.
pub fn journal_path(run: &Run) -> PathBuf {
    run.dir.join("state").join(format!("{}.redb", run.mission.mission))
}

/// Every boat of the mission with what its journalled batches hold, in the mission's order.
pub fn tracks(run: &Run) -> Result<Vec<Track>, ExportError> {
    // The flags are the server's verdicts, which only its summary holds: a run whose server
    // stopped before the end has none, and a flag is never guessed.
    let Some(summary) = &run.summary else {
        return Err(ExportError::Bad {
            path: run.dir.join("summary.json"),
            why: "missing: the server stopped before the mission's end, so the readings' quality flags \
                  (its sensor verdicts) are not known; the readings are in state/<id>.readings.ndjson and the journal"
                .into(),
        });
    };
    let path = journal_path(run);
    if !path.is_file() {
        return Err(ExportError::Missing {
            dir: run.dir.clone(),
            what: "server journal (state/<mission>.redb)",
        });
    }
    let bad = |why: String| ExportError::Bad {
        path: path.clone(),
        why,
    };
    let journal = fleet_net::store::Store::open(&path).map_err(|e| bad(e.to_string()))?;
    let vehicles = run.mission.vehicles();
    let mut out: Vec<Track> = vehicles
        .iter()
        .filter(|v| v.kind == VehicleKind::Boat)
        .map(|v| Track {
            boat: v.id.as_str().to_string(),
            readings: vec![],
        })
        .collect();
    let mut ctx = Context::new(run.grid);
    ctx.vehicles = vehicles.into_iter().map(|v| v.id).collect();
    for ((vehicle, seq), bytes) in journal.messages().map_err(|e| bad(e.to_string()))? {
        // The journal's key names the vehicle: the aerials' batches, most of it, are not decoded.
        let Some(t) = out.iter_mut().find(|t| t.boat == vehicle) else {
            continue;
        };
        match protocol::decode(&bytes, &ctx) {
            Ok(Body::Batch(b)) => t.readings.extend(readings_of(run, &summary.sensor_verdicts, &b)),
            Ok(_) => {}
            Err(e) => return Err(bad(format!("message {seq} of {vehicle}: {e}"))),
        }
    }
    for t in &mut out {
        t.readings.sort_by_key(|r| r.step);
    }
    Ok(out)
}

/// The values of one batch, each with its sigma and the boat's verdict at its step.
fn readings_of<'a>(
    run: &'a Run,
    verdicts: &'a [SensorVerdict],
    batch: &'a MeasurementBatch,
) -> impl Iterator<Item = Reading> + 'a {
    batch.samples.iter().flat_map(move |s| {
        let flag = verdict_at(verdicts, &batch.vehicle, s.step);
        s.cells
            .iter()
            .zip(&s.values)
            .enumerate()
            .map(move |(i, (&cell, &value))| {
                let (x, y) = run.grid.centre_m(run.grid.cell(cell as usize));
                let sigma = match &s.sigma {
                    Some(own) => own[i],
                    None => batch.noise.std_at((s.position[0] - x).hypot(s.position[1] - y)),
                };
                Reading {
                    step: s.step,
                    cell,
                    value,
                    sigma,
                    flag,
                }
            })
    })
}

/// The verdict on `vehicle`'s sensor at `step`: what its latest change at or before the step
/// made it (ok before any).
fn verdict_at(changes: &[SensorVerdict], vehicle: &VehicleId, step: u64) -> Health {
    changes
        .iter()
        .filter(|v| v.vehicle == *vehicle && v.step <= step)
        .max_by_key(|v| v.step)
        .map_or(Health::Ok, |v| v.to)
}

/// Write the boats' readings of `run` to `path`; how many values. Nothing is written for a run
/// whose boats read nothing (`None`): a trajectory file of no observation is not one a checker
/// takes.
pub fn write(run: &Run, path: &Path) -> Result<Option<usize>, ExportError> {
    let tracks = tracks(run)?;
    let n: usize = tracks.iter().map(|t| t.readings.len()).sum();
    if n == 0 {
        return Ok(None);
    }
    let mut nc = Nc4::new();
    define(&mut nc, run, &tracks, n).map_err(schema_error(path))?;
    nc.write(path)?;
    Ok(Some(n))
}

/// Characters of the longest boat id (CF's string as a fixed-length character array).
fn name_width(tracks: &[Track]) -> usize {
    tracks.iter().map(|t| t.boat.len()).max().unwrap_or(1).max(1)
}

/// The file: the trajectories, their observations and what a catalogue reads.
fn define(nc: &mut Nc4, run: &Run, tracks: &[Track], n: usize) -> Result<(), Error> {
    let trajectory = (nc.dim("trajectory", tracks.len())?, tracks.len());
    let obs = (nc.dim("obs", n)?, n);
    let width = name_width(tracks);
    let strlen = (nc.dim("name_strlen", width)?, width);
    let names: Vec<String> = tracks.iter().map(|t| t.boat.clone()).collect();
    let v = nc.strings("vehicle", [trajectory, strlen], &names)?;
    nc.text(
        v,
        &[
            ("cf_role", "trajectory_id"),
            ("long_name", "the boat's id in the mission"),
        ],
    )?;
    let sizes: Vec<i32> = tracks.iter().map(|t| t.readings.len() as i32).collect();
    let v = nc.var("rowSize", &[trajectory], &sizes)?;
    nc.text(
        v,
        &[
            ("sample_dimension", "obs"),
            (
                "long_name",
                "number of values the boat read (its observations are contiguous)",
            ),
        ],
    )?;
    positions(nc, run, tracks, obs)?;
    values(nc, run, tracks, obs)?;
    nc.global_text("featureType", "trajectory")?;
    let summary = format!(
        "Every value the boats of hetfleet mission {} read and the model server accepted: {n} values from {} \
         boats, each at the centre of the cell it measured, with its noise standard deviation and the server's \
         sensor-health verdict on the boat at that step.",
        run.mission.mission,
        tracks.len()
    );
    let title = format!("hetfleet boats' readings of mission {}", run.mission.mission);
    discovery(nc, run, &title, &summary)
}

/// Where and when each reading was: time, step, and the centre of the cell read.
fn positions(nc: &mut Nc4, run: &Run, tracks: &[Track], obs: (DimensionId, usize)) -> Result<(), Error> {
    let all = || tracks.iter().flat_map(|t| &t.readings);
    let t = run.time();
    let time: Vec<f64> = all().map(|r| t.at(r.step as usize)).collect();
    let v = nc.var("time", &[obs], &time)?;
    nc.text(v, &t.attrs())?;
    let v = nc.var("step", &[obs], &all().map(|r| r.step as i32).collect::<Vec<_>>())?;
    nc.text(v, &[("long_name", "mission step of the reading"), ("units", "1")])?;
    let (lon, lat) = run.axes_deg();
    let cols = run.grid.cols;
    let lats: Vec<f64> = all().map(|r| lat[r.cell as usize / cols]).collect();
    let lons: Vec<f64> = all().map(|r| lon[r.cell as usize % cols]).collect();
    for (name, values, standard_name, units, axis) in [
        ("lat", lats, "latitude", "degrees_north", "Y"),
        ("lon", lons, "longitude", "degrees_east", "X"),
    ] {
        let v = nc.var(name, &[obs], &values)?;
        let long = format!("{standard_name} of the centre of the cell read (WGS 84)");
        nc.text(
            v,
            &[
                ("standard_name", standard_name),
                ("long_name", &long),
                ("units", units),
                ("axis", axis),
            ],
        )?;
    }
    Ok(())
}

/// What each reading said: its value, its noise and the verdict on the boat's sensor.
fn values(nc: &mut Nc4, run: &Run, tracks: &[Track], obs: (DimensionId, usize)) -> Result<(), Error> {
    let all = || tracks.iter().flat_map(|t| &t.readings);
    let (unit, standard_name) = field_words(run);
    let unit = unit.unwrap_or_else(|| "1".into());
    let v = nc.var("value", &[obs], &all().map(|r| r.value).collect::<Vec<_>>())?;
    nc.text(
        v,
        &[
            (
                "long_name",
                "the boat's reading of the field, as the server accepted it",
            ),
            ("units", &unit),
            ("coordinates", "time lat lon"),
            ("ancillary_variables", "sigma flag"),
            ("coverage_content_type", "physicalMeasurement"),
        ],
    )?;
    if let Some(sn) = &standard_name {
        nc.text(v, &[("standard_name", sn)])?;
    }
    let v = nc.var("sigma", &[obs], &all().map(|r| r.sigma).collect::<Vec<_>>())?;
    nc.text(
        v,
        &[
            ("long_name", "noise standard deviation of the reading"),
            ("units", &unit),
            ("coordinates", "time lat lon"),
            ("coverage_content_type", "qualityInformation"),
        ],
    )?;
    let v = nc.var("flag", &[obs], &all().map(|r| flag_value(r.flag)).collect::<Vec<_>>())?;
    nc.text(
        v,
        &[
            ("standard_name", "status_flag"),
            (
                "long_name",
                "the server's sensor-health verdict on the boat at the reading's step",
            ),
            ("flag_meanings", FLAG_MEANINGS),
            ("coordinates", "time lat lon"),
            ("coverage_content_type", "qualityInformation"),
        ],
    )?;
    nc.attr(v, "flag_values", NcAttrValue::Bytes(vec![0, 1, 2]))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn change(vehicle: &str, step: u64, to: Health) -> SensorVerdict {
        SensorVerdict {
            vehicle: VehicleId::new(vehicle).unwrap(),
            step,
            from: Health::Ok,
            to,
            reason: String::new(),
        }
    }

    /// A verdict holds from its step until the boat's next; another boat's changes nothing.
    #[test]
    fn a_reading_carries_the_verdict_its_boat_had_at_its_step() {
        let changes = [
            change("boat-1", 10, Health::Suspect),
            change("boat-2", 5, Health::Excluded),
            change("boat-1", 20, Health::Excluded),
            change("boat-1", 30, Health::Ok),
        ];
        let b1 = VehicleId::new("boat-1").unwrap();
        let at = |step| verdict_at(&changes, &b1, step);
        assert_eq!(
            [at(0), at(9), at(10), at(19), at(20), at(29), at(30), at(99)],
            [
                Health::Ok,
                Health::Ok,
                Health::Suspect,
                Health::Suspect,
                Health::Excluded,
                Health::Excluded,
                Health::Ok,
                Health::Ok
            ]
        );
        let b3 = VehicleId::new("boat-3").unwrap();
        assert_eq!(verdict_at(&changes, &b3, 50), Health::Ok);
        assert_eq!(FLAG_MEANINGS.split(' ').count(), 3);
        assert_eq!(
            [Health::Ok, Health::Suspect, Health::Excluded].map(flag_value),
            [0, 1, 2]
        );
    }
}
