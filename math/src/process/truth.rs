//! A truth field for an experiment or a mixed-reality mission: the plasma-cloud simulator on a
//! given grid, or a `.npy` dataset, then area-averaged onto the model grid.

use super::plasma::{PlasmaCloud, Preset};
use super::FieldSeries;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Debug, thiserror::Error, strum::VariantNames)]
pub enum TruthError {
    #[error(
        "give exactly one of `preset` or `dataset` (in [truth] of a mission file, in each [[row]] of an \
        experiment file)"
    )]
    Source,
    #[error(
        "`variable` goes with a NetCDF dataset (`dataset = \"f.nc\"`, `variable = \"density\"`), and a NetCDF \
        dataset needs it"
    )]
    Variable,
    #[error("`select` fixes dimensions of a NetCDF dataset (`select = {{ pressure = 500 }}`); it goes with one")]
    Select,
    #[error("simulating {preset:?}: {source}")]
    Simulation {
        preset: Preset,
        source: super::plasma::PlasmaError,
    },
    #[error("loading the dataset {}: {source}", path.display())]
    Dataset {
        path: PathBuf,
        source: super::error::DatasetError,
    },
    #[error("{rows} x {cols} averaged by {factor} leaves less than 4 x 4 cells")]
    TooCoarse { rows: usize, cols: usize, factor: usize },
    #[error(transparent)]
    Grid(#[from] crate::grid::GridError),
}

impl TruthError {
    /// Whether the file or settings that asked for this truth are at fault (exit 2): all but
    /// the simulator failing to converge on valid parameters and a dataset the disk would not
    /// give (`DatasetError::Io`). A grid the simulator cannot take, or one averaged below 4 x 4,
    /// is the mission file's.
    pub fn is_input(&self) -> bool {
        match self {
            Self::Simulation { source, .. } => matches!(source, super::plasma::PlasmaError::Param(_)),
            Self::Dataset { source, .. } => !matches!(source, super::error::DatasetError::Io { .. }),
            Self::Source | Self::Variable | Self::Select | Self::TooCoarse { .. } | Self::Grid(_) => true,
        }
    }
}

/// Where the truth comes from: the plasma-cloud simulator's preset, a `(frames, rows, cols)`
/// `.npy` dataset, or a `(time, y, x)` variable of a NetCDF file (classic or NetCDF-4). In files it is written as
/// one of two keys, `preset = "cloud1"` or `dataset = "path.npy"` (`dataset = "f.nc"` with
/// `variable = "density"`); giving both or neither is refused where the file is read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(try_from = "TruthKeys", into = "TruthKeys")]
pub enum TruthSource {
    Preset(Preset),
    Dataset(PathBuf),
    NetCdf {
        path: PathBuf,
        variable: String,
        /// Dimensions beyond `(time, y, x)` fixed at one value ([`super::netcdf::Select`]).
        select: super::netcdf::Select,
    },
}

/// The two keys as they stand in a file.
#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
struct TruthKeys {
    /// The plasma-cloud simulator's cloud (`cloud1`, `cloud2`, `cloud10`): one of `preset` and
    /// `dataset`.
    #[serde(default)]
    preset: Option<Preset>,
    /// A field from a file, `(frames, rows, cols)`: a NumPy `.npy` array or a NetCDF file (with
    /// `variable`); its cells with no value (NaN, `_FillValue`) are land. Relative to the file
    /// that names it.
    #[serde(default)]
    dataset: Option<PathBuf>,
    /// A NetCDF dataset's variable (its time, y and x dimensions; decoded as xarray decodes it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    variable: Option<String>,
    /// A NetCDF variable's dimensions beyond time, y and x fixed at one coordinate value
    /// (`select = { pressure = 500 }`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    select: Option<super::netcdf::Select>,
}

impl TryFrom<TruthKeys> for TruthSource {
    type Error = TruthError;
    fn try_from(k: TruthKeys) -> Result<Self, TruthError> {
        // By content where the file can be read now, else by name; a `variable` names a
        // NetCDF file's, whatever it is called, unless it is a NumPy array.
        match (k.preset, k.dataset, k.variable, k.select) {
            (Some(p), None, None, None) => Ok(Self::Preset(p)),
            (None, Some(d), None, None) if !is_netcdf(&d) => Ok(Self::Dataset(d)),
            (None, Some(d), Some(variable), select) if !is_npy(&d) => Ok(Self::NetCdf {
                path: d,
                variable,
                select: select.unwrap_or_default(),
            }),
            (Some(_), Some(_), ..) | (None, None, ..) => Err(TruthError::Source),
            (_, _, _, Some(_)) => Err(TruthError::Select),
            _ => Err(TruthError::Variable),
        }
    }
}

impl From<TruthSource> for TruthKeys {
    fn from(s: TruthSource) -> Self {
        match s {
            TruthSource::Preset(p) => Self {
                preset: Some(p),
                dataset: None,
                variable: None,
                select: None,
            },
            TruthSource::Dataset(d) => Self {
                preset: None,
                dataset: Some(d),
                variable: None,
                select: None,
            },
            TruthSource::NetCdf { path, variable, select } => Self {
                preset: None,
                dataset: Some(path),
                variable: Some(variable),
                select: (!select.is_empty()).then_some(select),
            },
        }
    }
}

impl TruthSource {
    pub fn preset(&self) -> Option<Preset> {
        match self {
            Self::Preset(p) => Some(*p),
            Self::Dataset(_) | Self::NetCdf { .. } => None,
        }
    }

    /// The truth's name in tables and figure files: the preset (`Cloud1`), the file stem, or for
    /// a NetCDF variable the stem, the variable and what `select` fixes (`hgt_djf-z-pressure500`):
    /// two rows on one file with different variables are two truths.
    pub fn name(&self) -> String {
        let stem = |d: &std::path::Path| {
            d.file_stem()
                .map_or("dataset".into(), |s| s.to_string_lossy().to_string())
        };
        match self {
            Self::Preset(p) => format!("{p:?}"),
            Self::Dataset(d) => stem(d),
            // A variable in a group (`ocean/sst`) joined by `-`: the name is part of file names.
            Self::NetCdf { path, variable, select } => select.iter().fold(
                format!("{}-{}", stem(path), variable.trim_start_matches('/').replace('/', "-")),
                |name, (k, v)| format!("{name}-{k}{v}"),
            ),
        }
    }

    /// What the truth is, for a report: the simulator's preset, or the file (with the variable,
    /// its units and what `select` fixes, for NetCDF).
    pub fn describe(&self) -> String {
        match self {
            Self::Preset(p) => format!("the plasma-cloud simulator's `{p}`"),
            Self::Dataset(d) => format!("the dataset `{}`", d.display()),
            Self::NetCdf { path, variable, select } => {
                let units = self.units().map_or(String::new(), |u| format!(" ({u})"));
                let fixed = match select.is_empty() {
                    true => String::new(),
                    false => format!(" at {select:?}"),
                };
                format!("the variable `{variable}`{units} of `{}`{fixed}", path.display())
            }
        }
    }

    /// A dataset's `(frames, rows, cols)` from its file's header (`None` for a preset, or a
    /// file that cannot be read here).
    pub fn file_shape(&self) -> Option<Vec<usize>> {
        match self {
            Self::Preset(_) => None,
            Self::Dataset(path) => crate::npy::read_shape(path).ok(),
            Self::NetCdf { path, variable, select } => super::dataset::netcdf_shape(path, variable, select),
        }
    }

    /// The values' units where the file says them (a NetCDF variable's `units`).
    pub fn units(&self) -> Option<String> {
        self.said("units")
    }

    /// The variable's CF `standard_name`, where its file says one (what the field is, in the
    /// CF Standard Name Table's words).
    pub fn standard_name(&self) -> Option<String> {
        self.said("standard_name")
    }

    /// The dates of a NetCDF truth's frames, where its time coordinate has CF units.
    pub fn time_axis(&self) -> Option<super::netcdf::TimeAxis> {
        match self {
            Self::NetCdf { path, variable, select } => super::netcdf::time_axis(path, variable, select),
            Self::Preset(_) | Self::Dataset(_) => None,
        }
    }

    /// A text attribute of a NetCDF truth's variable.
    fn said(&self, name: &str) -> Option<String> {
        match self {
            Self::NetCdf { path, variable, .. } => super::netcdf::text_attribute(path, variable, name),
            Self::Preset(_) | Self::Dataset(_) => None,
        }
    }

    /// The field at full resolution: the simulator at `grid` `[rows, cols]` for `frames`
    /// frames (seeded), or the dataset as it is. `step_s`: the seconds between frames where a
    /// NetCDF file's time coordinate does not say them (a mission's `[time] step_s`).
    pub fn full(
        &self,
        (grid, frames, seed): ([usize; 2], usize, u64),
        step_s: Option<f64>,
        progress: impl FnMut(usize),
    ) -> Result<FieldSeries, TruthError> {
        match self {
            Self::Preset(preset) => {
                let mut p = preset.params();
                (p.ny, p.nx) = (grid[0], grid[1]);
                p.seed = seed;
                let sim_err = |source| TruthError::Simulation {
                    preset: *preset,
                    source,
                };
                let mut sim = PlasmaCloud::new(p).map_err(sim_err)?;
                sim.run(frames, progress).map_err(sim_err)
            }
            Self::Dataset(path) => super::dataset::load_truth(path, 1.0)
                .and_then(|f| super::dataset::in_units(f, path))
                .map_err(|source| TruthError::Dataset {
                    path: path.clone(),
                    source,
                }),
            Self::NetCdf { path, variable, select } => super::dataset::load_netcdf(path, variable, select, step_s)
                .and_then(|f| super::dataset::in_units(f, path))
                .map_err(|source| TruthError::Dataset {
                    path: path.clone(),
                    source,
                }),
        }
    }
}

/// What a data file is, by its first bytes (as GDAL and xarray tell a file's format, whatever
/// its name).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileKind {
    /// NetCDF-3: classic (`CDF\x01`), 64-bit offset (`CDF\x02`) or 64-bit data (`CDF\x05`).
    NetCdf3,
    /// NetCDF-4, an HDF5 file (`\x89HDF\r\n\x1a\n`).
    NetCdf4,
    /// A NumPy array (`\x93NUMPY`).
    Npy,
    /// Something else.
    Other,
}

/// The kind of the file at `path` by its magic bytes; `None` when it cannot be read (yet: a
/// mission's paths are read where they are used).
pub fn sniff(path: &std::path::Path) -> Option<FileKind> {
    use std::io::Read;
    let mut head = [0u8; 8];
    let mut f = std::fs::File::open(path).ok()?;
    let n = f.read(&mut head).ok()?;
    let head = &head[..n];
    Some(if head.starts_with(b"CDF") && matches!(head.get(3), Some(1 | 2 | 5)) {
        FileKind::NetCdf3
    } else if head.starts_with(b"\x89HDF\r\n\x1a\n") {
        FileKind::NetCdf4
    } else if head.starts_with(b"\x93NUMPY") {
        FileKind::Npy
    } else {
        FileKind::Other
    })
}

/// A NetCDF file: by its content when it can be read, else by its name (`.nc`, `.cdf`, `.nc3`,
/// `.netcdf`, `.nc4`).
pub fn is_netcdf(path: &std::path::Path) -> bool {
    match sniff(path) {
        Some(FileKind::NetCdf3 | FileKind::NetCdf4) => true,
        Some(FileKind::Npy) => false,
        Some(FileKind::Other) | None => path.extension().and_then(|e| e.to_str()).is_some_and(|e| {
            ["nc", "cdf", "nc3", "nc4", "netcdf"]
                .iter()
                .any(|n| e.eq_ignore_ascii_case(n))
        }),
    }
}

/// A `.npy` file: by its content when it can be read, else by its name.
pub fn is_npy(path: &std::path::Path) -> bool {
    match sniff(path) {
        Some(FileKind::Npy) => true,
        Some(FileKind::NetCdf3 | FileKind::NetCdf4) => false,
        Some(FileKind::Other) | None => path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("npy")),
    }
}

/// `full` area-averaged by `factor` in both directions (the model grid of that space rate).
pub fn averaged_by(full: &FieldSeries, factor: usize) -> Result<FieldSeries, TruthError> {
    let (rows, cols) = (full.rows / factor.max(1), full.cols / factor.max(1));
    if rows < 4 || cols < 4 {
        return Err(TruthError::TooCoarse {
            rows: full.rows,
            cols: full.cols,
            factor,
        });
    }
    Ok(full.area_averaged(rows, cols)?)
}
