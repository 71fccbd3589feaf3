//! `fleet export <run-dir>`: a run as NetCDF, GeoTIFF and QGroundControl plans; a run whose
//! server stopped before the mission's end, as far as it went.

use anyhow::Result;
use fleet::export::{self, ExportError, Run};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The run directory `fleet up --out` wrote.
    pub run_dir: PathBuf,
    /// The estimate, its variance and the truth at every step as CF-1.8 NetCDF (xarray, Panoply).
    #[arg(long, value_name = "FILE.nc")]
    pub netcdf: Option<PathBuf>,
    /// The boats' readings (value, its sigma, the sensor-health flag) as a CF-1.8 trajectory file,
    /// one trajectory per boat (ERDDAP, xarray with cf_xarray, Panoply).
    #[arg(long, value_name = "FILE.nc")]
    pub readings: Option<PathBuf>,
    /// The final estimate and its variance as GeoTIFFs (WGS 84) in this directory (GDAL, QGIS).
    #[arg(long, value_name = "DIR")]
    pub geotiff: Option<PathBuf>,
    /// Each boat's planned sensing places as a QGroundControl plan, one file per boat (QGC holds
    /// one mission per vehicle): `f.plan` writes `f.boat-1.plan`, `f.boat-2.plan`, ...
    #[arg(long, value_name = "FILE.plan")]
    pub qgc_plan: Option<PathBuf>,
    /// The plans published at this epoch (default: the last).
    #[arg(long, requires = "qgc_plan")]
    pub epoch: Option<u64>,
}

/// An export's error as the exit code wants it: the run directory's fault is bad input.
fn classify(e: ExportError) -> anyhow::Error {
    let bad = e.is_bad_input();
    fleet_exit::bad_input_if(e, bad)
}

pub fn run(args: Args) -> Result<()> {
    if args.netcdf.is_none() && args.readings.is_none() && args.geotiff.is_none() && args.qgc_plan.is_none() {
        return Err(fleet_exit::bad_input(anyhow::anyhow!(
            "nothing to export: give --netcdf FILE.nc, --readings FILE.nc, --geotiff DIR or --qgc-plan FILE.plan"
        )));
    }
    let run = Run::load(&args.run_dir).map_err(classify)?;
    if !run.finished {
        println!(
            "{}: the model server stopped before the mission's end (no estimate.npy): exporting the {} steps \
             it made, from estimate.npy.part and variance.npy.part",
            args.run_dir.display(),
            run.estimate.steps
        );
    }
    if let Some(path) = &args.netcdf {
        export::netcdf::write(&run, path).map_err(classify)?;
        println!(
            "wrote {} ({} steps of {} x {})",
            path.display(),
            run.estimate.steps,
            run.grid.rows,
            run.grid.cols
        );
    }
    if let Some(path) = &args.readings {
        match export::trajectory::write(&run, path).map_err(classify)? {
            Some(n) => println!("wrote {} ({n} boat readings)", path.display()),
            None => {
                return Err(fleet_exit::bad_input(anyhow::anyhow!(
                    "{}: no boat's reading in the run's journal: {} not written",
                    args.run_dir.display(),
                    path.display()
                )))
            }
        }
    }
    if let Some(dir) = &args.geotiff {
        let files = export::geotiff::write(&run, dir).map_err(classify)?;
        println!("wrote {} (step {}, WGS 84)", list(&files), run.estimate.steps - 1);
    }
    if let Some(path) = &args.qgc_plan {
        let files = export::qgc::write(&run, path, args.epoch).map_err(classify)?;
        println!("wrote {}", list(&files));
    }
    Ok(())
}

fn list(files: &[PathBuf]) -> String {
    files
        .iter()
        .map(|p| Path::display(p).to_string())
        .collect::<Vec<_>>()
        .join(", ")
}
