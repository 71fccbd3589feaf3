//! `fleet assimilate MISSION --readings r.ndjson [--frames DIR] --out run/`: a day's readings
//! assimilated after the fact (`fleet_mission::offline`), written as a live run writes its
//! results (`summary.json`, `model.cbor`, `estimate.npy`, `variance.npy`, `plans.json`,
//! `estimate.nc`). The readings of a live run (its `readings.ndjson`) give its model again, byte
//! for byte.

use anyhow::{Context as _, Result};
use fleet_math::process::FieldSeries;
use fleet_mission::config::MissionConfig;
use fleet_mission::events::{Percentiles, ServerSummary};
use fleet_mission::instrument::{raster, Entry, Logged, SensorSource};
use fleet_mission::offline::{self, VehicleLog};
use fleet_mission::protocol::VehicleKind;
use std::collections::{BTreeMap, BTreeSet};
use std::io::BufRead;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The mission the readings were taken in (every vehicle on an instrument).
    pub mission: PathBuf,
    /// The readings: NDJSON, one reading a line as the interface has it with the vehicle's id
    /// added (`{"vehicle": "boat-1", "t": ..., "lat": ..., "lon": ..., "value": ...}`), as a run
    /// directory's `readings.ndjson` has them.
    #[arg(long)]
    pub readings: PathBuf,
    /// The aerials' frames under `DIR/<vehicle id>/` (default: each aerial's `geotiff:DIR`).
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// Where to write the results.
    #[arg(long, default_value = "fleet-assimilate")]
    pub out: PathBuf,
}

pub fn run(args: Args) -> Result<()> {
    let t0 = std::time::Instant::now();
    let mut mission = MissionConfig::load(Some(&args.mission)).map_err(fleet_exit::bad_input)?;
    let pb = super::progress_bar(mission.frames_hint() as u64, "truth");
    let truth = mission.truth(|k| pb.set_position(k as u64))?;
    mission.adopt_land(truth.as_ref().map_or_else(Vec::new, FieldSeries::land));
    pb.finish_and_clear();
    let (grid, frames) = mission
        .workspace(truth.as_ref().map(FieldSeries::shape))
        .map_err(fleet_exit::bad_input)?;
    if let Some(v) = mission
        .vehicles()
        .iter()
        .find(|v| mission.sensor_of(&v.id) == SensorSource::Sim)
    {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "{}: {} reads the simulated sensor, whose values are in no log: fleet assimilate takes missions whose \
             vehicles all read instruments",
            args.mission.display(),
            v.id
        )));
    }
    let (mut logs, skipped) = read_log(&args.readings, &mission)?;
    read_frames(&mission, args.frames.as_deref(), &mut logs, (&grid, &args.mission))?;
    let pb = super::progress_bar(mission.schedule(frames).epochs(), "assimilate");
    let done = offline::run(&mission, (grid, frames), &logs, |e, _| pb.set_position(e))?;
    pb.finish_and_clear();
    let core = &done.core;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    fleet_records::outputs::write(&args.out, core, mission.pace.horizon)?;
    std::fs::copy(&args.mission, args.out.join("mission.toml")).context("copying the mission into the run")?;
    let mse: Vec<f64> = match truth.as_ref() {
        Some(t) => (0..core.history().len())
            .map(|k| {
                let truth: Vec<f64> = t.snapshots.col(k).iter().copied().collect();
                Ok(fleet_math::fusion::mse(&core.history().estimate(k)?, &truth))
            })
            .collect::<std::io::Result<_>>()
            .context("reading the estimate back")?,
        None => vec![],
    };
    let summary = ServerSummary {
        mission: mission.mission.clone(),
        vehicles: core.vehicles().iter().map(|v| v.id.clone()).collect(),
        epochs: core.counters.epochs,
        model_version: core.version,
        rank: core.assimilator().rank(),
        counters: core.counters.clone(),
        latency_ms: Percentiles::of(&[]),
        mean_mse: fleet_mission::events::mean_mse(&mse),
        mse,
        eigenvalues: core.model_update().map(|m| m.eigenvalues).unwrap_or_default(),
        link_ups: BTreeMap::new(),
        wall_s: t0.elapsed().as_secs_f64(),
        peak_resident_mib: fleet_mission::memory::peak_resident_mib(),
        dt: truth
            .as_ref()
            .map_or_else(|| mission.clock().map_or(1.0, |c| c.step_s), |t| t.dt),
        holdout: core.holdout(),
        innovations: core.innovations(),
        traffic: BTreeMap::new(),
        readings: BTreeMap::new(),
        land_cells: core.assimilator().land().len(),
        skill: core.skills(),
        sensor_verdicts: core.verdicts_at(0..usize::MAX),
        screened: core.health().1,
    };
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)?)
        .with_context(|| format!("writing {}", path.display()))?;
    let run = fleet::export::Run::load(&args.out)?;
    fleet::export::netcdf::write(&run, &args.out.join("estimate.nc")).context("writing estimate.nc")?;
    say(&done, skipped, &summary, &args.out);
    Ok(())
}

/// What was taken and refused, and where the results are.
fn say(done: &offline::Offline, skipped: BTreeMap<String, u64>, summary: &ServerSummary, out: &Path) {
    for (id, tally) in &done.tallies {
        let refused = tally.refusals();
        let refused = if refused.is_empty() {
            String::new()
        } else {
            format!(", refused {refused:?}")
        };
        println!("{id}: {} readings taken{refused}", tally.accepted);
    }
    if !skipped.is_empty() {
        println!("lines of the log not taken: {skipped:?}");
    }
    let holdout = summary.holdout.as_ref().map_or(String::new(), |h| {
        format!("; held out {} readings, MSE {:.3e}", h.readings, h.mse)
    });
    println!(
        "assimilated {} epochs (model v{}, rank {}){holdout}; wrote {}/summary.json, model.cbor, estimate.npy, \
         variance.npy, plans.json, estimate.nc",
        summary.epochs,
        summary.model_version,
        summary.rank,
        out.display()
    );
}

/// The log's lines by vehicle, and the lines not taken by why (not a line of the log, not a
/// vehicle of the mission). A log that cannot be read is bad input.
fn read_log(path: &Path, mission: &MissionConfig) -> Result<(BTreeMap<String, VehicleLog>, BTreeMap<String, u64>)> {
    let file = std::fs::File::open(path)
        .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("--readings {}: {e}", path.display())))?;
    let ids: BTreeSet<String> = mission.vehicles().iter().map(|v| v.id.to_string()).collect();
    let (mut logs, mut skipped) = (BTreeMap::<String, VehicleLog>::new(), BTreeMap::<String, u64>::new());
    for line in std::io::BufReader::new(file).lines() {
        let line = line.map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("--readings {}: {e}", path.display())))?;
        if line.trim().is_empty() {
            continue;
        }
        let Ok(logged) = Logged::parse(&line) else {
            *skipped.entry("malformed".into()).or_default() += 1;
            continue;
        };
        if !ids.contains(&logged.vehicle) {
            *skipped.entry("unknown_vehicle".into()).or_default() += 1;
            continue;
        }
        let log = logs.entry(logged.vehicle).or_default();
        match logged.entry {
            Entry::Reading(r) => log.readings.push(r),
            Entry::Frame { frame, t } => log.frames.push((frame, t, vec![])),
            Entry::Fix { step, fix } => {
                log.fixes.insert(step, (fix[0], fix[1]));
            }
        }
    }
    Ok((logs, skipped))
}

/// Each aerial camera's frames on the model grid: those its log names (a live run's), or, when
/// it names none, every frame in its directory. A frame that cannot be read is left out and
/// said (the live vehicle refused it too).
fn read_frames(
    mission: &MissionConfig,
    base: Option<&Path>,
    logs: &mut BTreeMap<String, VehicleLog>,
    (grid, mission_path): (&fleet_math::grid::Grid, &Path),
) -> Result<()> {
    let site = mission.mavlink.site(grid);
    for v in mission.vehicles().iter().filter(|v| v.kind == VehicleKind::Aerial) {
        let SensorSource::Geotiff(dir) = mission.sensor_of(&v.id) else {
            continue;
        };
        let dir = match base {
            Some(b) => b.join(v.id.as_str()),
            None if dir.is_relative() => mission_path.parent().unwrap_or(Path::new(".")).join(dir),
            None => dir,
        };
        let log = logs.entry(v.id.to_string()).or_default();
        let mut names: Vec<String> = log.frames.iter().map(|(n, _, _)| n.clone()).collect();
        if names.is_empty() {
            names = tiffs_in(&dir)?;
        }
        names.sort();
        names.dedup();
        log.frames.clear();
        for name in names {
            match read_frame(&dir.join(&name), &site, grid) {
                Ok((t, values)) => log.frames.push((name, t, values)),
                Err(why) => eprintln!("{}: frame {name} left out: {why}", v.id),
            }
        }
    }
    Ok(())
}

/// The `.tif`/`.tiff` files in `dir`.
fn tiffs_in(dir: &Path) -> Result<Vec<String>> {
    let entries = std::fs::read_dir(dir)
        .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("the frames directory {}: {e}", dir.display())))?;
    Ok(entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| {
            let n = n.to_ascii_lowercase();
            n.ends_with(".tif") || n.ends_with(".tiff")
        })
        .collect())
}

/// A frame's time and its values on the model grid, or why not.
fn read_frame(
    path: &Path,
    site: &fleet_mission::site::Site,
    grid: &fleet_math::grid::Grid,
) -> Result<(f64, Vec<Option<f64>>), String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    raster::frame_on_grid(&bytes, &name, site, grid)
}
