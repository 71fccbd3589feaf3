//! A finished run in the formats field teams open: NetCDF-4 for xarray and Panoply
//! ([`netcdf`]), the boats' readings as a CF trajectory file ([`trajectory`]), GeoTIFF for GDAL
//! and QGIS ([`geotiff`]), QGroundControl plans ([`qgc`]).
//! Everything is read from the run directory `fleet up` leaves (the server's `estimate.npy`,
//! `variance.npy`, `plans.json` and `summary.json`, the mission and the truth), so a run can
//! be exported again later, and by the same code `fleet up` uses at its end.

pub mod geotiff;
mod nc4;
pub mod netcdf;
pub mod qgc;
pub mod trajectory;

use fleet_math::grid::Grid;
use fleet_math::npy;
use fleet_mission::config::MissionConfig;
use fleet_mission::events::{PublishedPlans, ServerSummary};
use fleet_mission::site::Site;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(
        "{}: not a finished run directory: it has no {what} (run `fleet up --out {}` first)",
        dir.display(),
        dir.display()
    )]
    Missing { dir: PathBuf, what: &'static str },
    #[error("{}: {why}", path.display())]
    Bad { path: PathBuf, why: String },
    #[error("writing {}: {why}", path.display())]
    Write { path: PathBuf, why: String },
}

impl ExportError {
    /// Whether the run directory is at fault (exit 2), rather than the machine (exit 1).
    pub fn is_bad_input(&self) -> bool {
        !matches!(self, Self::Write { .. })
    }
}

type Result<T> = std::result::Result<T, ExportError>;

/// One `(steps, rows, cols)` field of a run, flat in that order.
pub struct Steps {
    pub steps: usize,
    pub data: Vec<f64>,
}

impl Steps {
    /// Step `k` as `rows * cols` values, row 0 the southern edge.
    pub fn step(&self, k: usize, grid: &Grid) -> &[f64] {
        &self.data[k * grid.len()..(k + 1) * grid.len()]
    }
}

/// A run's time axis as CF writes it: a value per step in `units` of `calendar`.
pub struct RunTime {
    pub long_name: &'static str,
    pub units: String,
    pub calendar: String,
    pub values: Vec<f64>,
}

impl RunTime {
    /// The time axis of `steps` steps of `mission`: its UTC clock where it has one, else the
    /// truth file's own dates in its own calendar (a climate model's 360-day years stay
    /// theirs), else `step_s` seconds a step since the first, which name no date.
    pub fn of(mission: &MissionConfig, steps: usize, step_s: f64) -> Self {
        if let Some(c) = mission.clock() {
            let epoch = fleet_mission::instrument::MissionClock::rfc3339(c.start);
            return Self {
                long_name: "the start of the step in UTC",
                units: format!("seconds since {}", epoch.trim_end_matches('Z').replacen('T', " ", 1)),
                calendar: "standard".into(),
                values: (0..steps).map(|k| k as f64 * c.step_s).collect(),
            };
        }
        let file = mission.truth.as_ref().and_then(|t| t.source.time_axis());
        match file.filter(|a| a.values.len() >= steps && a.date_of(a.values[0]).is_some()) {
            Some(a) => Self {
                long_name: "the time of the truth's frame, as its file gives it",
                calendar: a.calendar_name(),
                values: a.values[..steps].to_vec(),
                units: a.units,
            },
            None => Self {
                long_name: "the field's own time since the mission's first step",
                units: "s".into(),
                calendar: "standard".into(),
                values: (0..steps).map(|k| k as f64 * step_s).collect(),
            },
        }
    }

    /// The date of step `k` in the axis's calendar (`YYYY-MM-DD hh:mm:ss`), where the axis
    /// names dates.
    pub fn date_of(&self, k: usize) -> Option<String> {
        let axis = fleet_math::process::netcdf::TimeAxis {
            units: self.units.clone(),
            calendar: self.calendar.clone(),
            values: vec![],
        };
        axis.date_of(*self.values.get(k)?)
    }

    /// The value of step `k`, also past the axis's last (one step on from it per step).
    pub fn at(&self, k: usize) -> f64 {
        match (self.values.get(k), self.values.as_slice()) {
            (Some(&v), _) => v,
            (None, [.., a, b]) => b + (b - a) * (k + 1 - self.values.len()) as f64,
            (None, [b]) => b + (k as f64),
            (None, []) => k as f64,
        }
    }

    /// CF's attributes of the time variable.
    pub fn attrs(&self) -> [(&str, &str); 5] {
        [
            ("standard_name", "time"),
            ("long_name", self.long_name),
            ("units", &self.units),
            ("calendar", &self.calendar),
            ("axis", "T"),
        ]
    }
}

/// What a run directory holds, read and checked against itself.
pub struct Run {
    pub dir: PathBuf,
    pub mission: MissionConfig,
    /// The server's account of the run (`None`: it stopped before the mission's end).
    pub summary: Option<ServerSummary>,
    /// Whether the server wrote the run's outputs (else the steps are those it made before it
    /// stopped).
    pub finished: bool,
    pub grid: Grid,
    pub site: Site,
    pub estimate: Steps,
    pub variance: Steps,
    /// The truth's first `steps` frames, in a mixed-reality run.
    pub truth: Option<Steps>,
}

impl Run {
    /// Seconds a step spans: the mission's clock (`[time] step_s`), else the field's own.
    pub fn step_s(&self) -> f64 {
        match self.mission.clock() {
            Some(c) => c.step_s,
            None => match self.summary.as_ref().map_or(0.0, |s| s.dt) {
                dt if dt > 0.0 => dt,
                _ => 1.0,
            },
        }
    }

    /// The time axis the run's files carry ([`RunTime::of`]).
    pub fn time(&self) -> RunTime {
        RunTime::of(&self.mission, self.estimate.steps, self.step_s())
    }

    /// UTC of the start of step `k`, with mission time (RFC 3339).
    pub fn utc_of(&self, k: usize) -> Option<String> {
        let c = self.mission.clock()?;
        Some(fleet_mission::instrument::MissionClock::rfc3339(c.time_of(k as u64)))
    }

    /// A run directory read and checked: a finished run's, or one whose server stopped before
    /// the mission's end, which leaves its steps in the `.part` files (written as they were
    /// made) and no summary: its steps are exported all the same.
    pub fn load(dir: &Path) -> Result<Self> {
        let files = RunFiles(dir);
        let mission_path = files.need("mission.toml")?;
        let text = std::fs::read_to_string(&mission_path).map_err(|e| bad(&mission_path, e.to_string()))?;
        let mission = MissionConfig::from_toml(&text).map_err(|e| bad(&mission_path, e.to_string()))?;
        let names = Self::step_files(dir);
        let finished = names[0] == "estimate.npy";
        let summary = match finished || dir.join("summary.json").is_file() {
            true => Some(files.summary()?),
            false => None,
        };
        let (grid, [estimate, variance]) = files.fields(names, finished)?;
        let truth = files.truth(&grid, estimate.steps)?;
        let site = mission.mavlink.site(&grid);
        Ok(Self {
            dir: dir.into(),
            mission,
            summary,
            finished,
            grid,
            site,
            estimate,
            variance,
            truth,
        })
    }

    /// The estimate's and variance's files: a finished run's, else those a server still
    /// running, or stopped before the mission's end, is writing.
    fn step_files(dir: &Path) -> [&'static str; 2] {
        let finished = ["estimate.npy", "variance.npy"];
        let part = ["estimate.npy.part", "variance.npy.part"];
        match !dir.join(finished[0]).is_file() && dir.join(part[0]).is_file() {
            true => part,
            false => finished,
        }
    }

    /// The plans the server published (`plans.json`).
    pub fn plans(&self) -> Result<PublishedPlans> {
        let p = self.dir.join("plans.json");
        if !p.is_file() {
            return Err(ExportError::Missing {
                dir: self.dir.clone(),
                what: "plans.json",
            });
        }
        std::fs::read(&p)
            .map_err(|e| e.to_string())
            .and_then(|b| serde_json::from_slice(&b).map_err(|e| e.to_string()))
            .map_err(|why| ExportError::Bad { path: p, why })
    }

    /// Physical metres east of the site's corner of each column's centre, and north of each
    /// row's.
    pub fn axes_m(&self) -> (Vec<f64>, Vec<f64>) {
        let x = (0..self.grid.cols)
            .map(|c| (c as f64 + 0.5) * self.grid.cell_m * self.site.scale.x)
            .collect();
        let y = (0..self.grid.rows)
            .map(|r| (r as f64 + 0.5) * self.grid.cell_m * self.site.scale.y)
            .collect();
        (x, y)
    }

    /// Longitude of each column's centre and latitude of each row's (the flat-Earth site: a
    /// column has one longitude, a row one latitude), on the site's map: increasing across a
    /// dateline, as CF coordinates may.
    pub fn axes_deg(&self) -> (Vec<f64>, Vec<f64>) {
        let g = &self.grid;
        let lon = (0..g.cols)
            .map(|c| {
                self.site
                    .map_of(&self.site.ned_of(((c as f64 + 0.5) * g.cell_m, 0.0), 0.0))
                    .1
            })
            .collect();
        let lat = (0..g.rows)
            .map(|r| {
                self.site
                    .map_of(&self.site.ned_of((0.0, (r as f64 + 0.5) * g.cell_m), 0.0))
                    .0
            })
            .collect();
        (lon, lat)
    }

    /// `[west, south, east, north]` of the grid's outer edges, degrees.
    pub fn bounds_deg(&self) -> [f64; 4] {
        let (lat0, lon0) = self.site.map_of(&self.site.ned_of((0.0, 0.0), 0.0));
        let (lat1, lon1) = self
            .site
            .map_of(&self.site.ned_of((self.grid.width_m(), self.grid.height_m()), 0.0));
        [lon0, lat0, lon1, lat1]
    }

    /// The site's boundary the run was planned within, if it had one: as the server read it,
    /// from the recording's header (the file the mission names need not be beside the run's
    /// copy of the mission). Read only when asked: a damaged recording does not stop the
    /// other exports.
    pub fn fence(&self) -> Result<Option<fleet_mission::fence::SiteFence>> {
        let recording = self.dir.join("recording.mcap");
        if !recording.is_file() {
            return Ok(None);
        }
        let rec = fleet_records::recording::Recording::read(&recording).map_err(|e| ExportError::Bad {
            path: recording.clone(),
            why: format!("the site's boundary is read from it: {e}"),
        })?;
        Ok(rec.mission.team.fence)
    }

    /// The site's boundary as `[lat, lon]` vertices: the mission's fence, or the grid's extent.
    pub fn boundary_deg(&self) -> Result<Vec<[f64; 2]>> {
        Ok(match self.fence()? {
            Some(f) => {
                let origin = Site {
                    origin: self.site.origin,
                    scale: nalgebra::Vector2::new(1.0, 1.0),
                };
                f.polygon_m
                    .iter()
                    .map(|[e, n]| {
                        let (lat, lon, _) = origin.global_of(&nalgebra::Vector3::new(*n, *e, 0.0));
                        [lat, lon]
                    })
                    .collect()
            }
            None => {
                let [w, s, e, n] = self.bounds_deg();
                vec![[s, w], [s, e], [n, e], [n, w]]
            }
        })
    }

    /// What produced the run, for files' metadata: `(name, value)`.
    pub fn provenance(&self) -> Vec<(&'static str, String)> {
        let name = |v: serde_json::Value| v.as_str().map_or_else(|| v.to_string(), String::from);
        let t = &self.mission.team;
        vec![
            ("mission", self.mission.mission.clone()),
            ("seed", t.seed.to_string()),
            ("fusion", name(serde_json::to_value(t.fusion).unwrap_or_default())),
            ("placement", name(serde_json::to_value(t.placement).unwrap_or_default())),
            (
                "model_version",
                self.summary
                    .as_ref()
                    .map_or("unknown".into(), |s| s.model_version.to_string()),
            ),
            ("source", format!("hetfleet {} (fleet up)", env!("CARGO_PKG_VERSION"))),
        ]
    }
}

/// A file of a run directory at fault, and why.
fn bad(path: &Path, why: String) -> ExportError {
    ExportError::Bad { path: path.into(), why }
}

/// The files of a run directory, each read and checked as [`Run::load`] needs it.
struct RunFiles<'a>(&'a Path);

impl RunFiles<'_> {
    fn need(&self, name: &'static str) -> Result<PathBuf> {
        let p = self.0.join(name);
        match p.is_file() {
            true => Ok(p),
            false => Err(ExportError::Missing {
                dir: self.0.into(),
                what: name,
            }),
        }
    }

    fn summary(&self) -> Result<ServerSummary> {
        let path = self.need("summary.json")?;
        std::fs::read(&path)
            .map_err(|e| e.to_string())
            .and_then(|b| serde_json::from_slice(&b).map_err(|e| e.to_string()))
            .map_err(|why| bad(&path, why))
    }

    /// A `(steps, rows, cols)` array: its shape and values.
    fn array(&self, name: &'static str) -> Result<(Vec<usize>, Vec<f64>)> {
        let p = self.need(name)?;
        let a = npy::read(&p).map_err(|e| bad(&p, e.to_string()))?;
        // NaN is a cell without a value (land, no data); an infinity is a broken file.
        if let Some(i) = a.data.iter().position(|v| v.is_infinite()) {
            return Err(bad(&p, format!("value {i} is {}", a.data[i])));
        }
        Ok((a.shape, a.data))
    }

    /// The estimate and its variance, and the grid they are on.
    fn fields(&self, [estimate_name, variance_name]: [&'static str; 2], finished: bool) -> Result<(Grid, [Steps; 2])> {
        let (shape, mut estimate) = self.array(estimate_name)?;
        let &[made, rows, cols] = shape.as_slice() else {
            return Err(bad(
                &self.0.join(estimate_name),
                format!("expected shape (steps, rows, cols), found {shape:?}"),
            ));
        };
        let grid = Grid::new(rows, cols, 1.0).map_err(|e| bad(&self.0.join(estimate_name), e.to_string()))?;
        let (vshape, mut variance) = self.array(variance_name)?;
        if vshape.get(1..) != shape.get(1..) || (finished && vshape != shape) {
            return Err(bad(
                &self.0.join(variance_name),
                format!("shape {vshape:?} differs from {estimate_name}'s {shape:?}"),
            ));
        }
        // A server stopped between its two files' writes of a step has one more in the first.
        let steps = made.min(vshape[0]);
        if steps == 0 {
            return Err(bad(
                &self.0.join(estimate_name),
                "no steps: the run assimilated nothing".into(),
            ));
        }
        estimate.truncate(steps * grid.len());
        variance.truncate(steps * grid.len());
        let steps_of = |data| Steps { steps, data };
        Ok((grid, [steps_of(estimate), steps_of(variance)]))
    }

    /// The truth's first `steps` frames, in a mixed-reality run.
    fn truth(&self, grid: &Grid, steps: usize) -> Result<Option<Steps>> {
        if !self.0.join("truth.npy").is_file() {
            return Ok(None);
        }
        let (shape, data) = self.array("truth.npy")?;
        if shape.len() != 3 || shape[1..] != [grid.rows, grid.cols] || shape[0] < steps {
            return Err(bad(
                &self.0.join("truth.npy"),
                format!(
                    "shape {shape:?} does not cover the estimate's ({steps}, {}, {})",
                    grid.rows, grid.cols
                ),
            ));
        }
        Ok(Some(Steps {
            steps,
            data: data[..steps * grid.len()].to_vec(),
        }))
    }
}
