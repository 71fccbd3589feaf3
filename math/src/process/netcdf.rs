//! One variable of a NetCDF-3 file as a field, decoded the way xarray decodes it (CF
//! conventions): a value equal to `_FillValue` or `missing_value` (compared in the variable's
//! own type, as xarray casts them) or outside `valid_min`/`valid_max`/`valid_range` (as
//! netCDF4-python masks them) is missing, never data; integers marked `_Unsigned = "true"` are
//! read unsigned, and packed integers unpacked with `scale_factor` and `add_offset`; `units` is
//! carried along.
//!
//! Dimensions are taken the way files have them: `select` fixes a dimension (by coordinate
//! value where the dimension has a coordinate variable, xarray's `sel`; by index where it has
//! none, `isel`), singleton dimensions other than the first are squeezed, and what is left must
//! be `(time, y, x)`. Rows run south to north (the grid's `y` is north): a file whose `y`
//! coordinate decreases (latitude from the pole down, as many reanalyses are stored) is
//! flipped, and so is a decreasing `x`. A coordinate that is not strictly monotonic is refused.
//! The time between frames comes from the time coordinate and its CF `units`
//! (`"hours since 1-1-1"`): their mean spacing in seconds (years of winters are 365 or 366
//! days apart).
//!
//! A missing value is NaN in the field; a variable missing everywhere, or a frame with no value
//! at all, is refused.

use super::dataset::DatasetError;
use super::FieldSeries;
use faer::Mat;
use netcdf3::{DataSet, DataType, DataVector, Variable};
use std::collections::BTreeMap;
use std::path::Path;

/// Dimensions the field does not keep, each fixed at one coordinate value (or index).
pub type Select = BTreeMap<String, f64>;

/// A NetCDF variable read as a field, with what the file says about it.
#[derive(Debug, Clone)]
pub struct NetCdfField {
    /// The field, NaN where the file marks a value missing.
    pub field: FieldSeries,
    /// The variable's `units`, if it has them.
    pub units: Option<String>,
    /// The `y` and `x` coordinates in the field's order (south to north, west to east).
    pub y: Option<Vec<f64>>,
    pub x: Option<Vec<f64>>,
    /// How many values are missing.
    pub missing: usize,
}

/// The `(frames, rows, cols)` of `variable` after `select` and squeezing, from the header and
/// the selected coordinates.
pub fn shape(path: impl AsRef<Path>, variable: &str, select: &Select) -> Option<Vec<usize>> {
    let mut reader = netcdf3::FileReader::open(path).ok()?;
    let named: Vec<String> = select
        .keys()
        .filter(|d| is_coordinate(reader.data_set(), d))
        .cloned()
        .collect();
    let coords: BTreeMap<String, Vec<f64>> = named
        .into_iter()
        .filter_map(|d| {
            let raw = reader.read_var(&d).ok()?;
            Some((d.clone(), coordinate(reader.data_set(), &d, &raw).ok()??))
        })
        .collect();
    let var = reader.data_set().get_var(variable)?;
    let layout = Layout::of(reader.data_set(), var, select, &coords, &|why| why).ok()?;
    Some(layout.kept.iter().map(|&d| layout.sizes[d]).collect())
}

/// Where `variable` lies on the Earth, `[south, west, north, east]` (degrees, cell edges), when
/// its `y` and `x` coordinates are latitude and longitude (CF `units` `degrees_north` and
/// `degrees_east`, or those `standard_name`s) evenly spaced; longitude in [-180, 180).
pub fn bounds(path: impl AsRef<Path>, variable: &str, select: &Select) -> Option<[f64; 4]> {
    let mut reader = netcdf3::FileReader::open(path).ok()?;
    let ds = reader.data_set();
    let var = ds.get_var(variable)?;
    let names = var.dim_names();
    let lat = names.iter().find(|n| is_geographic(ds, n, true))?.clone();
    let lon = names.iter().find(|n| is_geographic(ds, n, false))?.clone();
    if select.contains_key(&lat) || select.contains_key(&lon) {
        return None;
    }
    let edges = |v: Vec<f64>| -> Option<(f64, f64)> {
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let step = (hi - lo) / (v.len().max(2) - 1) as f64;
        let even = v
            .windows(2)
            .all(|w| ((w[1] - w[0]).abs() - step).abs() <= 1e-6 * step.max(1e-12));
        (v.len() >= 2 && step > 0.0 && even).then_some((lo - step / 2.0, hi + step / 2.0))
    };
    let (lat_raw, lon_raw) = (reader.read_var(&lat).ok()?, reader.read_var(&lon).ok()?);
    let ds = reader.data_set();
    let (south, north) = edges(coordinate(ds, &lat, &lat_raw).ok()??)?;
    let (west, east) = edges(across_the_dateline(coordinate(ds, &lon, &lon_raw).ok()??))?;
    let wrapped = crate::longitude::wrap_longitude(west);
    Some([south, wrapped, north, wrapped + (east - west)])
}

/// The `units` attribute of `variable`, from the header.
pub fn units(path: impl AsRef<Path>, variable: &str) -> Option<String> {
    netcdf3::FileReader::open(path)
        .ok()?
        .data_set()
        .get_var_attr_as_string(variable, "units")
}

/// Whether `units` are degrees north (`north`) or east, in any of CF's spellings
/// (`degrees_north`, `degree_N`, `degreesN`, ...).
fn in_degrees(units: &str, north: bool) -> bool {
    let u = units.trim().to_ascii_lowercase();
    let spellings = match north {
        true => ["degrees_n", "degree_n", "degreesn", "degreen"],
        false => ["degrees_e", "degree_e", "degreese", "degreee"],
    };
    spellings.iter().any(|e| u.starts_with(e))
}

/// Whether dimension `dim` is a latitude (`north`) or a longitude: its coordinate in degrees
/// north or east, or so named by its `standard_name`.
fn is_geographic(ds: &DataSet, dim: &str, north: bool) -> bool {
    let attr = |a: &str| ds.get_var_attr_as_string(dim, a).unwrap_or_default();
    let name = if north { "latitude" } else { "longitude" };
    is_coordinate(ds, dim) && (in_degrees(&attr("units"), north) || attr("standard_name").trim() == name)
}

/// Longitudes that cross the dateline made continuous: a step of more than 180 degrees is a
/// wrap, and the values after it move by 360 (`170, 175, -180, -175` is `170 ... 185`: a
/// Pacific box cut from a file in -180..180, as `cdo sellonlatbox,150,-150` writes it). Read
/// as they stand they are not monotonic and the file was refused; xarray and GDAL read it.
fn across_the_dateline(mut lon: Vec<f64>) -> Vec<f64> {
    let mut shift = 0.0;
    for i in 1..lon.len() {
        let step = lon[i] + shift - lon[i - 1];
        shift += match step {
            s if s < -180.0 => 360.0,
            s if s > 180.0 => -360.0,
            _ => 0.0,
        };
        lon[i] += shift;
    }
    lon
}

/// A coordinate variable: one dimension, named as the variable.
fn is_coordinate(ds: &DataSet, name: &str) -> bool {
    ds.get_var(name).is_some_and(|v| v.dim_names() == [name.to_string()])
}

/// A NetCDF-4 file (HDF5) is refused in one line saying what it is and how to convert it.
fn refuse_netcdf4(path: &Path) -> Result<(), DatasetError> {
    if super::truth::sniff(path) != Some(super::truth::FileKind::NetCdf4) {
        return Ok(());
    }
    Err(DatasetError::NetCdf {
        path: path.display().to_string(),
        why: "it is NetCDF-4 (HDF5), and only NetCDF-3 is read: convert it with `nccopy -k classic IN OUT` (or \
              xarray's `open_dataset(IN).to_netcdf(OUT, format=\"NETCDF3_64BIT\")`)"
            .into(),
    })
}

/// Read `variable` of the NetCDF-3 file at `path` (classic or 64-bit offset). Every variable of
/// the file is read: a file cut short anywhere is refused, not half used.
pub fn read(path: impl AsRef<Path>, variable: &str, select: &Select) -> Result<NetCdfField, DatasetError> {
    let path = path.as_ref();
    let p = path.display().to_string();
    let cf = |why: String| DatasetError::Cf {
        path: p.clone(),
        variable: variable.into(),
        why,
    };
    let unreadable = |e: netcdf3::error::ReadError| DatasetError::NetCdf {
        path: p.clone(),
        why: format!("{e:?}"),
    };
    refuse_netcdf4(path)?;
    let mut reader = netcdf3::FileReader::open(path).map_err(unreadable)?;
    let mut all = reader.read_all_vars().map_err(unreadable)?;
    let ds = reader.data_set();
    let Some(var) = ds.get_var(variable) else {
        return Err(DatasetError::NoVariable {
            path: p,
            variable: variable.into(),
            have: ds.get_var_names().join(", "),
        });
    };
    let raw = all.remove(variable).ok_or_else(|| cf("no data".into()))?;
    let coords = coordinates(ds, &all).map_err(&cf)?;
    let layout = Layout::of(ds, var, select, &coords, &cf)?;
    let coord = |d: usize| coords.get(&layout.names[d]).cloned();
    let [t_dim, y_dim, x_dim] = [layout.kept[0], layout.kept[1], layout.kept[2]];
    let (times, mut y, mut x) = (coord(t_dim), coord(y_dim), coord(x_dim));
    if is_geographic(ds, &layout.names[x_dim], false) {
        x = x.map(across_the_dateline);
    }
    let flip_y = orientation(&layout.names[y_dim], y.as_deref()).map_err(&cf)?;
    let flip_x = orientation(&layout.names[x_dim], x.as_deref()).map_err(&cf)?;
    if let (true, Some(v)) = (flip_y, y.as_mut()) {
        v.reverse();
    }
    if let (true, Some(v)) = (flip_x, x.as_mut()) {
        v.reverse();
    }
    let dt = time_step(ds, &layout.names[t_dim], times.as_deref()).map_err(&cf)?;
    let decode = Decode::of(var, raw_type(&raw)).map_err(&cf)?;
    let values = decode.values(&raw).ok_or_else(|| {
        cf(format!(
            "is {:?}; a field needs numbers (byte, short, int, float or double)",
            var.data_type()
        ))
    })?;
    let (t, rows, cols) = (layout.sizes[t_dim], layout.sizes[y_dim], layout.sizes[x_dim]);
    let n = rows * cols;
    let mut snapshots = Mat::zeros(n, t);
    for k in 0..t {
        for r in 0..rows {
            for c in 0..cols {
                let (fr, fc) = (
                    if flip_y { rows - 1 - r } else { r },
                    if flip_x { cols - 1 - c } else { c },
                );
                snapshots[(r * cols + c, k)] = values[layout.flat(&[(t_dim, k), (y_dim, fr), (x_dim, fc)])];
            }
        }
    }
    let missing = check_holes(&snapshots).map_err(&cf)?;
    Ok(NetCdfField {
        field: FieldSeries {
            rows,
            cols,
            dt,
            snapshots,
        },
        units: var.get_attr_as_string("units"),
        y,
        x,
        missing,
    })
}

/// Refuse a field missing everywhere or in a whole frame; the number of missing values.
pub(crate) fn check_holes(snapshots: &Mat<f64>) -> Result<usize, String> {
    let mut missing = 0;
    for k in 0..snapshots.ncols() {
        let here = snapshots.col(k).iter().filter(|v| v.is_nan()).count();
        if here == snapshots.nrows() {
            return Err(
                if k == 0 && (1..snapshots.ncols()).all(|j| snapshots.col(j).iter().all(|v| v.is_nan())) {
                    "every value is missing (fill value, missing_value or outside the valid range)".into()
                } else {
                    format!("frame {k} has no value: every cell is missing")
                },
            );
        }
        missing += here;
    }
    Ok(missing)
}

/// Where the variable's values sit: its dimensions, which are kept (time, y, x) and the index
/// every other one is fixed at.
struct Layout {
    names: Vec<String>,
    sizes: Vec<usize>,
    fixed: Vec<Option<usize>>,
    kept: Vec<usize>,
}

impl Layout {
    /// `coords`: the values of the coordinate variables of the dimensions `select` names. The
    /// kept dimensions come out as `(time, y, x)`: in the file's order, or in the order their
    /// coordinates' CF attributes give ([`Axis`]) where those say otherwise.
    fn of<E>(
        ds: &DataSet,
        var: &Variable,
        select: &Select,
        coords: &BTreeMap<String, Vec<f64>>,
        err: &dyn Fn(String) -> E,
    ) -> Result<Self, E> {
        let names: Vec<String> = var.dim_names();
        let sizes: Vec<usize> = var.get_dims().iter().map(|d| d.size()).collect();
        let listed = || {
            names
                .iter()
                .zip(&sizes)
                .map(|(n, s)| format!("{n} {s}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let mut fixed = vec![None; names.len()];
        for (dim, &value) in select {
            let Some(d) = names.iter().position(|n| n == dim) else {
                return Err(err(format!(
                    "select names {dim:?}, which is not a dimension of it (it has: {})",
                    listed()
                )));
            };
            fixed[d] = Some(pick(dim, sizes[d], coords.get(dim), value).map_err(err)?);
        }
        let mut kept: Vec<usize> = (0..names.len()).filter(|&d| fixed[d].is_none()).collect();
        // Squeeze singletons (never the first, the time axis) until three are left.
        while kept.len() > 3 {
            let Some(i) = kept.iter().skip(1).position(|&d| sizes[d] == 1) else {
                break;
            };
            fixed[kept[i + 1]] = Some(0);
            kept.remove(i + 1);
        }
        if kept.len() != 3 {
            let free: Vec<&str> = kept.iter().skip(1).map(|&d| names[d].as_str()).collect();
            return Err(err(format!(
                "has dimensions ({}); a field needs (time, y, x){}",
                listed(),
                if kept.len() > 3 {
                    format!(": fix the others with select = {{ {} = <value> }}", free[0])
                } else {
                    String::new()
                }
            )));
        }
        if sizes[kept[0]] < 1 || sizes[kept[1]] == 0 || sizes[kept[2]] == 0 {
            return Err(err(format!("has dimensions ({}): no values", listed())));
        }
        let axes = [0, 1, 2].map(|i| Axis::of(ds, &names[kept[i]]));
        let kept = field_order([kept[0], kept[1], kept[2]], axes).ok_or_else(|| {
            let said = (0..3)
                .map(|i| format!("{} {}", names[kept[i]], axes[i].map_or("?", Axis::name)))
                .collect::<Vec<_>>()
                .join(", ");
            err(format!(
                "has dimensions ({said}) by its coordinates' CF attributes, which do not settle which is \
                 time, y and x: write it as (time, y, x), e.g. `ncpdq -a time,lat,lon IN OUT`"
            ))
        })?;
        Ok(Self {
            names,
            sizes,
            fixed,
            kept: kept.to_vec(),
        })
    }

    /// The flat index of a value from the kept dimensions' indices.
    fn flat(&self, at: &[(usize, usize)]) -> usize {
        let mut i = 0;
        for d in 0..self.sizes.len() {
            let k = self.fixed[d].unwrap_or_else(|| at.iter().find(|(dd, _)| *dd == d).map_or(0, |&(_, k)| k));
            i = i * self.sizes[d] + k;
        }
        i
    }
}

/// What a dimension is to a field, as its coordinate variable's CF attributes say (`axis`,
/// a time's `units` "<unit> since <date>", latitude's and longitude's `units` or a
/// `standard_name`, projected ones included), the attributes xarray's and GDAL's readers go by.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Axis {
    Time,
    Y,
    X,
}

impl Axis {
    /// The axis of dimension `dim`: `None` where it has no coordinate variable or that says none
    /// of these (a level's `Z`).
    fn of(ds: &DataSet, dim: &str) -> Option<Self> {
        if !is_coordinate(ds, dim) {
            return None;
        }
        let attr = |a: &str| ds.get_var_attr_as_string(dim, a).unwrap_or_default();
        let (axis, units) = (attr("axis").trim().to_ascii_uppercase(), attr("units"));
        let standard = attr("standard_name");
        let is = |letter: &str, north: bool, names: &[&str]| {
            axis == letter || in_degrees(&units, north) || names.contains(&standard.trim())
        };
        if axis == "T" || units.contains(" since ") || standard.trim() == "time" {
            Some(Self::Time)
        } else if is("Y", true, &["latitude", "projection_y_coordinate", "grid_latitude"]) {
            Some(Self::Y)
        } else if is("X", false, &["longitude", "projection_x_coordinate", "grid_longitude"]) {
            Some(Self::X)
        } else {
            None
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Time => "(time)",
            Self::Y => "(y)",
            Self::X => "(x)",
        }
    }
}

/// The three kept dimensions (in the file's order) as `(time, y, x)`, given what each is
/// (`None`: not said). The file's order where nothing says otherwise; the order the axes give
/// where they do (a `(time, lon, lat)` file, read as it stands, would be the field transposed
/// and its map's latitude the longitude); `None` where they cannot settle it (two dimensions
/// the same axis, or one out of place and two unsaid).
fn field_order(kept: [usize; 3], axes: [Option<Axis>; 3]) -> Option<[usize; 3]> {
    const WANT: [Axis; 3] = [Axis::Time, Axis::Y, Axis::X];
    if (0..3).all(|i| axes[i].is_none_or(|a| a == WANT[i])) {
        return Some(kept);
    }
    let unsaid: Vec<usize> = (0..3).filter(|&i| axes[i].is_none()).collect();
    let missing: Vec<Axis> = WANT.into_iter().filter(|a| !axes.contains(&Some(*a))).collect();
    if unsaid.len() > 1 || missing.len() != unsaid.len() {
        return None;
    }
    let mut axes = axes;
    if let (Some(&i), Some(&a)) = (unsaid.first(), missing.first()) {
        axes[i] = Some(a);
    }
    let at = |want: Axis| kept[axes.iter().position(|&a| a == Some(want)).unwrap_or(0)];
    Some(WANT.map(at))
}

/// The index `value` names along `dim`: a coordinate value where the file has a coordinate
/// variable for it (`coordinate`, its values), else an index.
fn pick(dim: &str, size: usize, coordinate: Option<&Vec<f64>>, value: f64) -> Result<usize, String> {
    let Some(values) = coordinate else {
        return match value {
            v if v >= 0.0 && v.fract() == 0.0 && (v as usize) < size => Ok(v as usize),
            _ => Err(format!(
                "select {dim} = {value}: {dim} has no coordinate variable, so it takes an index from 0 to {}",
                size.saturating_sub(1)
            )),
        };
    };
    let tol = 1e-6 * value.abs().max(1.0);
    values.iter().position(|c| (c - value).abs() <= tol).ok_or_else(|| {
        format!(
            "select {dim} = {value}: no such {dim} (it has: {})",
            values.iter().map(|v| v.to_string()).collect::<Vec<_>>().join(", ")
        )
    })
}

/// Every coordinate variable's values among `all`, decoded ([`coordinate`]); the error names
/// the one whose attributes cannot be read.
fn coordinates<S: std::hash::BuildHasher>(
    ds: &DataSet,
    all: &std::collections::HashMap<String, DataVector, S>,
) -> Result<BTreeMap<String, Vec<f64>>, String> {
    let mut coords = BTreeMap::new();
    for (name, v) in all.iter().filter(|(name, _)| is_coordinate(ds, name)) {
        if let Some(values) = coordinate(ds, name, v).map_err(|why| format!("coordinate {name:?}: {why}"))? {
            coords.insert(name.clone(), values);
        }
    }
    Ok(coords)
}

/// A coordinate variable's values as xarray decodes them, as the variable's are: packed
/// integers unpacked (a latitude stored as shorts of 0.01 degrees is 20 to 60, not 2000 to
/// 6000), a fill value NaN (so refused as not monotonic); `None` for characters.
fn coordinate(ds: &DataSet, name: &str, raw: &DataVector) -> Result<Option<Vec<f64>>, String> {
    let Some(var) = ds.get_var(name) else { return Ok(None) };
    Ok(Decode::of(var, raw_type(raw))?.values(raw))
}

/// Any numeric vector as doubles (`None` for characters).
fn numbers(v: &DataVector) -> Option<Vec<f64>> {
    Some(match v {
        DataVector::I8(v) => v.iter().map(|&x| f64::from(x)).collect(),
        DataVector::I16(v) => v.iter().map(|&x| f64::from(x)).collect(),
        DataVector::I32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        DataVector::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        DataVector::F64(v) => v.clone(),
        DataVector::U8(_) => return None,
    })
}

fn raw_type(v: &DataVector) -> DataType {
    match v {
        DataVector::I8(_) => DataType::I8,
        DataVector::U8(_) => DataType::U8,
        DataVector::I16(_) => DataType::I16,
        DataVector::I32(_) => DataType::I32,
        DataVector::F32(_) => DataType::F32,
        DataVector::F64(_) => DataType::F64,
    }
}

/// Whether a coordinate runs backwards (and the axis is to be flipped); refused when it is not
/// strictly monotonic (or not finite).
fn orientation(dim: &str, values: Option<&[f64]>) -> Result<bool, String> {
    let Some(v) = values else { return Ok(false) };
    let up = v.windows(2).all(|w| w[1] > w[0]);
    let down = v.windows(2).all(|w| w[1] < w[0]);
    if !(up || down) || v.iter().any(|x| !x.is_finite()) {
        return Err(format!("coordinate {dim:?} is not strictly monotonic ({v:?})"));
    }
    Ok(down && v.len() > 1)
}

/// Seconds between frames: the time coordinate's mean spacing in its CF `units` (`"<unit> since
/// <date>"`); 1 where the file has no time coordinate or one frame. A time axis that does not
/// increase is refused, and so are units that are not time.
fn time_step(ds: &DataSet, dim: &str, times: Option<&[f64]>) -> Result<f64, String> {
    let Some(t) = times.filter(|t| t.len() > 1) else {
        return Ok(1.0);
    };
    if !t.windows(2).all(|w| w[1] > w[0]) || t.iter().any(|x| !x.is_finite()) {
        return Err(format!("time coordinate {dim:?} does not increase"));
    }
    let units = ds.get_var_attr_as_string(dim, "units").unwrap_or_default();
    let unit = units.split_whitespace().next().unwrap_or("").to_ascii_lowercase();
    let seconds = match unit.as_str() {
        _ if !units.contains(" since ") => return Ok((t[t.len() - 1] - t[0]) / (t.len() - 1) as f64),
        "days" | "day" | "d" => 86_400.0,
        "hours" | "hour" | "hr" | "h" => 3_600.0,
        "minutes" | "minute" | "min" => 60.0,
        "seconds" | "second" | "sec" | "s" => 1.0,
        "milliseconds" | "millisecond" | "ms" => 1e-3,
        _ => {
            return Err(format!(
                "time units {units:?}: expected days, hours, minutes or seconds since a date"
            ))
        }
    };
    Ok((t[t.len() - 1] - t[0]) / (t.len() - 1) as f64 * seconds)
}

/// How stored values become data: which are missing, and the unpacking.
struct Decode {
    missing: Vec<f64>,
    valid: (f64, f64),
    /// Whether the valid range is in packed units (its type is the variable's).
    valid_packed: bool,
    scale: f64,
    offset: f64,
    /// `_Unsigned = "true"`: the stored type's span, `2^bits` (see [`unsigned_span`]).
    unsigned: Option<f64>,
}

impl Decode {
    fn of(var: &Variable, stored: DataType) -> Result<Self, String> {
        let attr = |name: &str| var.get_attr(name).and_then(attr_numbers);
        let unsigned = unsigned_span(var, &stored)?;
        let in_type = |v: f64| match unsigned {
            // A fill written unsigned (65535 for a short) is already the value as read.
            Some(_) if v >= 0.0 => v,
            _ => as_unsigned(unsigned, cast(v, &stored)),
        };
        let mut missing: Vec<f64> = vec![];
        for name in ["_FillValue", "missing_value"] {
            missing.extend(attr(name).unwrap_or_default().into_iter().map(in_type));
        }
        let mut valid = (f64::NEG_INFINITY, f64::INFINITY);
        let mut typed = vec![];
        if let Some(r) = attr("valid_range") {
            let [lo, hi] = r[..] else {
                return Err(format!("valid_range has {} values, not 2", r.len()));
            };
            valid = (lo, hi);
            typed.push("valid_range");
        }
        if let Some(&[lo]) = attr("valid_min").as_deref() {
            valid.0 = lo;
            typed.push("valid_min");
        }
        if let Some(&[hi]) = attr("valid_max").as_deref() {
            valid.1 = hi;
            typed.push("valid_max");
        }
        let valid_packed = typed
            .iter()
            .all(|n| var.get_attr(n).is_some_and(|a| a.data_type() == stored));
        if valid_packed {
            valid = (as_unsigned(unsigned, valid.0), as_unsigned(unsigned, valid.1));
        }
        let one = |name: &str, default: f64| -> Result<f64, String> {
            match attr(name).as_deref() {
                None => Ok(default),
                Some(&[v]) if v.is_finite() => Ok(v),
                Some(v) => Err(format!("{name} is {v:?}; CF wants one finite number")),
            }
        };
        Ok(Self {
            missing,
            valid,
            valid_packed,
            scale: one("scale_factor", 1.0)?,
            offset: one("add_offset", 0.0)?,
            unsigned,
        })
    }

    /// The data, NaN where missing (`None`: not numbers).
    fn values(&self, raw: &DataVector) -> Option<Vec<f64>> {
        let stored = numbers(raw)?;
        Some(
            stored
                .into_iter()
                .map(|s| {
                    let s = as_unsigned(self.unsigned, s);
                    let v = s * self.scale + self.offset;
                    let checked = if self.valid_packed { s } else { v };
                    let out_of_range = checked < self.valid.0 || checked > self.valid.1;
                    if s.is_nan() || self.missing.contains(&s) || out_of_range || !v.is_finite() {
                        f64::NAN
                    } else {
                        v
                    }
                })
                .collect(),
        )
    }
}

/// `_Unsigned = "true"` (the NUG's way to store unsigned integers in NetCDF-3, which has none:
/// GOES-R's products are shorts so marked, with `valid_range = 0S, -6S`): the stored type's span
/// `2^bits`, which a negative stored value is read with, as netCDF4-python and netCDF-Java read
/// it, and so are its fill values and a valid range in the stored type (xarray converts only
/// `_FillValue`, leaving a `missing_value` of 254 in a byte as data). Read as signed, a byte of
/// 200 would be -56: data altered in silence. `"false"` or no attribute: signed. Anything else,
/// or `"true"` on a type that is not an integer, is refused (no setting ignored).
fn unsigned_span(var: &Variable, stored: &DataType) -> Result<Option<f64>, String> {
    let Some(said) = var.get_attr("_Unsigned") else {
        return Ok(None);
    };
    let said = said.get_as_string().unwrap_or_default();
    match (said.trim().to_ascii_lowercase().as_str(), stored) {
        ("false", _) => Ok(None),
        ("true", DataType::I8) => Ok(Some(256.0)),
        ("true", DataType::I16) => Ok(Some(65_536.0)),
        ("true", DataType::I32) => Ok(Some(4_294_967_296.0)),
        ("true", t) => Err(format!(
            "_Unsigned is \"true\" on a variable of {t:?}: only integers are unsigned"
        )),
        _ => Err(format!("_Unsigned is {said:?}; the NUG wants \"true\" or \"false\"")),
    }
}

/// A stored integer as `_Unsigned` reads it: a negative one plus the type's span.
fn as_unsigned(span: Option<f64>, stored: f64) -> f64 {
    match span {
        Some(span) if stored < 0.0 => stored + span,
        _ => stored,
    }
}

/// An attribute's numbers as doubles.
fn attr_numbers(a: &netcdf3::Attribute) -> Option<Vec<f64>> {
    let f = |v: Option<&[f32]>| v.map(|v| v.iter().map(|&x| f64::from(x)).collect());
    let i = |v: Option<Vec<f64>>| v;
    a.get_f64()
        .map(|v| v.to_vec())
        .or_else(|| f(a.get_f32()))
        .or_else(|| i(a.get_i32().map(|v| v.iter().map(|&x| f64::from(x)).collect())))
        .or_else(|| i(a.get_i16().map(|v| v.iter().map(|&x| f64::from(x)).collect())))
        .or_else(|| i(a.get_i8().map(|v| v.iter().map(|&x| f64::from(x)).collect())))
}

/// `v` as the stored type holds it (xarray casts a fill value to the variable's type before
/// comparing: 1e20 as a float is 100000002004087734272).
fn cast(v: f64, t: &DataType) -> f64 {
    match t {
        DataType::F32 => f64::from(v as f32),
        DataType::I8 => f64::from(v as i8),
        DataType::I16 => f64::from(v as i16),
        DataType::I32 => f64::from(v as i32),
        DataType::U8 | DataType::F64 => v,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh directory for one test's files (removed at its end).
    fn scratch(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// `v(time, level, lat, lon)` of shorts with the attributes given, `lat` and `level`
    /// coordinates; written by `netcdf3`.
    fn write(path: &Path, data: &[i16], lat: &[f64], attrs: &[(&str, f64)]) {
        write_with(path, data, lat, attrs, |_| {});
    }

    /// [`write`], with `more` adding what a double cannot say (strings, typed pairs).
    fn write_with(path: &Path, data: &[i16], lat: &[f64], attrs: &[(&str, f64)], more: impl Fn(&mut DataSet)) {
        let (t, rows, cols) = (data.len() / (lat.len() * 3), lat.len(), 3);
        let mut ds = netcdf3::DataSet::new();
        for (d, n) in [("time", t), ("level", 1), ("lat", rows), ("lon", cols)] {
            ds.add_fixed_dim(d, n).unwrap();
        }
        ds.add_var_i16("v", &["time", "level", "lat", "lon"]).unwrap();
        for (k, x) in attrs {
            match *k {
                "scale_factor" | "add_offset" => ds.add_var_attr_f32("v", k, vec![*x as f32]).unwrap(),
                // (doubles: the `netcdf3` crate pads a lone short attribute wrongly and cannot
                // read its own file back; a double fill value is cast to the type, as xarray does)
                _ => ds.add_var_attr_f64("v", k, vec![*x]).unwrap(),
            }
        }
        ds.add_var_attr_string("v", "units", "K").unwrap();
        more(&mut ds);
        ds.add_var_f64("lat", &["lat"]).unwrap();
        ds.add_var_f64("level", &["level"]).unwrap();
        ds.add_var_f64("time", &["time"]).unwrap();
        ds.add_var_attr_string("time", "units", "days since 2000-01-01")
            .unwrap();
        let mut w = netcdf3::FileWriter::open(path).unwrap();
        w.set_def(&ds, netcdf3::Version::Classic, 0).unwrap();
        w.write_var_i16("v", data).unwrap();
        w.write_var_f64("lat", lat).unwrap();
        w.write_var_f64("level", &[850.0]).unwrap();
        w.write_var_f64("time", &(0..t).map(|k| 2.0 * k as f64).collect::<Vec<_>>())
            .unwrap();
        w.close().unwrap();
    }

    #[test]
    fn packed_shorts_with_fill_values_decode_as_cf_says_and_bad_files_are_named() {
        let dir = scratch("hetfleet-cf");
        let p = dir.join("v.nc");
        // 2 frames of 2 x 3; lat north to south; -999 is the fill, 30000 (15010 unpacked) above
        // valid_max (a double: in unpacked units).
        let data = [1, 2, 3, 4, -999, 6, 7, 8, 9, 30000, -999, 12];
        let attrs = [
            ("_FillValue", -999.0),
            ("valid_max", 10000.0),
            ("scale_factor", 0.5),
            ("add_offset", 10.0),
        ];
        write(&p, &data, &[60.0, 50.0], &attrs);
        let f = read(&p, "v", &Select::new()).unwrap();
        assert_eq!((f.field.rows, f.field.cols, f.field.frames()), (2, 3, 2));
        assert_eq!(f.units.as_deref(), Some("K"));
        assert_eq!(f.y, Some(vec![50.0, 60.0]), "rows run south to north");
        assert_eq!(f.field.dt, 2.0 * 86_400.0, "CF time: 2 days");
        let col = |k: usize| -> Vec<f64> { f.field.snapshots.col(k).iter().copied().collect() };
        // Frame 0: the southern row (stored second) first; value * 0.5 + 10.
        let want0 = [12.0, f64::NAN, 13.0, 10.5, 11.0, 11.5];
        let want1 = [f64::NAN, f64::NAN, 16.0, 13.5, 14.0, 14.5];
        for (got, want) in [(col(0), want0), (col(1), want1)] {
            for (g, w) in got.iter().zip(want) {
                assert!(g == &w || (g.is_nan() && w.is_nan()), "{got:?} vs {want:?}");
            }
        }
        assert_eq!(f.missing, 3);
        // The singleton level, fixed by its coordinate or squeezed; a level not there refused.
        let at = |v: f64| Select::from([("level".to_string(), v)]);
        let bits = |m: &Mat<f64>| -> Vec<u64> {
            (0..m.ncols())
                .flat_map(|k| m.col(k).iter().map(|v| v.to_bits()).collect::<Vec<_>>())
                .collect()
        };
        assert_eq!(
            bits(&read(&p, "v", &at(850.0)).unwrap().field.snapshots),
            bits(&f.field.snapshots)
        );
        let e = read(&p, "v", &at(500.0)).unwrap_err().to_string();
        assert!(e.contains("no such level (it has: 850)") && e.contains("v.nc"), "{e}");
        let e = read(&p, "v", &Select::from([("depth".to_string(), 0.0)]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a dimension"), "{e}");
        // Refused: a frame with no value, a variable with none, coordinates out of order.
        let mut holed = data;
        holed[6..].iter_mut().for_each(|v| *v = -999);
        write(&p, &holed, &[60.0, 50.0], &attrs);
        assert!(read(&p, "v", &Select::new())
            .unwrap_err()
            .to_string()
            .contains("frame 1 has no value"));
        write(&p, &[-999; 12], &[60.0, 50.0], &attrs);
        assert!(read(&p, "v", &Select::new())
            .unwrap_err()
            .to_string()
            .contains("every value is missing"));
        write(&p, &data[..9], &[60.0, 50.0, 55.0], &attrs);
        assert!(read(&p, "v", &Select::new())
            .unwrap_err()
            .to_string()
            .contains("not strictly monotonic"));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn unsigned_shorts_read_as_netcdf4_python_reads_them_and_a_bad_mark_is_named() {
        let dir = scratch("hetfleet-unsigned");
        let p = dir.join("u.nc");
        // GOES-R's marking: `_Unsigned = "true"`, `_FillValue = -1S` (65535), `valid_range = 0S,
        // -6S` (0 to 65530, in the stored type). Stored -5 is 65531, past the range; -7 is
        // 65529, in it; -32768 is 32768. Signed, every value below 0 would be outside the
        // range, and the file refused as missing everywhere.
        let data = [100, -1, -7, -5, -32768, 0];
        let unsigned = |said: &'static str| {
            move |ds: &mut DataSet| {
                ds.add_var_attr_string("v", "_Unsigned", said).unwrap();
                ds.add_var_attr_i16("v", "valid_range", vec![0, -6]).unwrap();
            }
        };
        let attrs = [("_FillValue", -1.0), ("scale_factor", 0.5), ("add_offset", 10.0)];
        write_with(&p, &data, &[50.0, 60.0], &attrs, unsigned("true"));
        let f = read(&p, "v", &Select::new()).unwrap();
        let got: Vec<f64> = f.field.snapshots.col(0).iter().copied().collect();
        let want = [
            60.0,
            f64::NAN,
            65_529.0 * 0.5 + 10.0,
            f64::NAN,
            32_768.0 * 0.5 + 10.0,
            10.0,
        ];
        for (g, w) in got.iter().zip(want) {
            assert!(g == &w || (g.is_nan() && w.is_nan()), "{got:?} vs {want:?}");
        }
        assert_eq!(f.missing, 2);
        // "TRUE" is true (netCDF-Java compares without case); "false" is signed, so the range
        // 0 to -6 holds nothing: refused, as the file was before `_Unsigned` was read.
        write_with(&p, &data, &[50.0, 60.0], &attrs, unsigned("TRUE"));
        assert_eq!(read(&p, "v", &Select::new()).unwrap().missing, 2);
        write_with(&p, &data, &[50.0, 60.0], &attrs, unsigned("false"));
        let e = read(&p, "v", &Select::new()).unwrap_err().to_string();
        assert!(e.contains("every value is missing"), "{e}");
        // A mark that is neither is refused, naming it, not read one way or the other.
        write_with(&p, &data, &[50.0, 60.0], &attrs, unsigned("yes"));
        let e = read(&p, "v", &Select::new()).unwrap_err().to_string();
        assert!(e.contains("_Unsigned is \"yes\"") && e.contains("u.nc"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// `v` of doubles over `dims` (name, size) in that order, each dimension with a coordinate
    /// variable (0, 1, 2, ...) whose `units` are given, or none where they are "".
    fn write_dims(path: &Path, dims: &[(&str, usize, &str)], data: &[f64]) {
        write_dims_with(path, dims, data, |_, n| (0..n).map(|k| 10.0 + k as f64).collect());
    }

    /// [`write_dims`] with each coordinate's values `coord(name, size)`.
    fn write_dims_with(
        path: &Path,
        dims: &[(&str, usize, &str)],
        data: &[f64],
        coord: impl Fn(&str, usize) -> Vec<f64>,
    ) {
        let mut ds = netcdf3::DataSet::new();
        for &(d, n, units) in dims {
            ds.add_fixed_dim(d, n).unwrap();
            if !units.is_empty() {
                ds.add_var_f64(d, &[d]).unwrap();
                ds.add_var_attr_string(d, "units", units).unwrap();
            }
        }
        ds.add_var_f64("v", &dims.iter().map(|d| d.0).collect::<Vec<_>>())
            .unwrap();
        let mut w = netcdf3::FileWriter::open(path).unwrap();
        w.set_def(&ds, netcdf3::Version::Classic, 0).unwrap();
        w.write_var_f64("v", data).unwrap();
        for &(d, n, units) in dims {
            if !units.is_empty() {
                w.write_var_f64(d, &coord(d, n)).unwrap();
            }
        }
        w.close().unwrap();
    }

    #[test]
    fn dimensions_in_another_order_are_read_by_their_axes_or_refused() {
        let dir = scratch("hetfleet-axes");
        let (t, lat, lon) = (
            ("time", 2, "days since 2000-01-01"),
            ("lat", 3, "degrees_north"),
            ("lon", 4, "degrees_east"),
        );
        // value = 100 t + 10 y + x, stored (time, lat, lon) and (lon, time, lat).
        let value = |k: usize, y: usize, x: usize| (100 * k + 10 * y + x) as f64;
        let stored: Vec<f64> = (0..2)
            .flat_map(|k| (0..3).flat_map(move |y| (0..4).map(move |x| value(k, y, x))))
            .collect();
        let turned: Vec<f64> = (0..4)
            .flat_map(|x| (0..2).flat_map(move |k| (0..3).map(move |y| value(k, y, x))))
            .collect();
        let (a, b) = (dir.join("a.nc"), dir.join("b.nc"));
        write_dims(&a, &[t, lat, lon], &stored);
        write_dims(&b, &[lon, t, lat], &turned);
        let (fa, fb) = (
            read(&a, "v", &Select::new()).unwrap(),
            read(&b, "v", &Select::new()).unwrap(),
        );
        let want: Vec<f64> = (0..2)
            .flat_map(|k| (0..12).map(move |c| value(k, c / 4, c % 4)))
            .collect();
        for f in [&fa, &fb] {
            assert_eq!(
                (f.field.rows, f.field.cols, f.field.frames(), f.field.dt),
                (3, 4, 2, 86_400.0)
            );
            let got: Vec<f64> = (0..2)
                .flat_map(|k| f.field.snapshots.col(k).iter().copied().collect::<Vec<_>>())
                .collect();
            assert_eq!(got, want, "the field as (time, lat, lon)");
            assert_eq!(
                (f.y.as_deref(), f.x.as_deref()),
                (Some(&[10.0, 11.0, 12.0][..]), Some(&[10.0, 11.0, 12.0, 13.0][..]))
            );
        }
        assert_eq!(shape(&b, "v", &Select::new()), Some(vec![2, 3, 4]));
        assert_eq!(bounds(&b, "v", &Select::new()), bounds(&a, "v", &Select::new()));
        // Unsaid dimensions keep the file's order; one axis out of place among two unsaid is
        // refused, not guessed.
        let bare = [("t", 2, ""), ("y", 3, ""), ("x", 4, "")];
        write_dims(&a, &bare, &stored);
        assert_eq!(
            read(&a, "v", &Select::new()).unwrap().field.snapshots,
            fa.field.snapshots
        );
        write_dims(&b, &[("x", 4, "degrees_east"), ("t", 2, ""), ("y", 3, "")], &turned);
        let e = read(&b, "v", &Select::new()).unwrap_err().to_string();
        assert!(e.contains("x (x), t ?, y ?") && e.contains("ncpdq"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn longitudes_across_the_dateline_are_one_box() {
        let dir = scratch("hetfleet-dateline");
        let p = dir.join("pacific.nc");
        let dims = [
            ("time", 2, "days since 2000-01-01"),
            ("lat", 3, "degrees_north"),
            ("lon", 4, "degrees_east"),
        ];
        let data: Vec<f64> = (0..24).map(f64::from).collect();
        let lon = |d: &str, n: usize| match d {
            "lon" => vec![170.0, 175.0, -180.0, -175.0],
            _ => (0..n).map(|k| 10.0 + k as f64).collect(),
        };
        write_dims_with(&p, &dims, &data, lon);
        let f = read(&p, "v", &Select::new()).unwrap();
        assert_eq!(f.x, Some(vec![170.0, 175.0, 180.0, 185.0]));
        assert_eq!(bounds(&p, "v", &Select::new()), Some([9.5, 167.5, 12.5, 187.5]));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_packed_coordinate_is_unpacked_as_its_variable_would_be() {
        let dir = scratch("hetfleet-packed-lat");
        let p = dir.join("packed.nc");
        let mut ds = netcdf3::DataSet::new();
        for (d, n) in [("time", 2), ("lat", 2), ("lon", 3)] {
            ds.add_fixed_dim(d, n).unwrap();
        }
        ds.add_var_f64("v", &["time", "lat", "lon"]).unwrap();
        ds.add_var_i16("lat", &["lat"]).unwrap();
        ds.add_var_attr_string("lat", "units", "degrees_north").unwrap();
        ds.add_var_attr_f64("lat", "scale_factor", vec![0.5]).unwrap();
        ds.add_var_f64("lon", &["lon"]).unwrap();
        ds.add_var_attr_string("lon", "units", "degrees_east").unwrap();
        let mut w = netcdf3::FileWriter::open(&p).unwrap();
        w.set_def(&ds, netcdf3::Version::Classic, 0).unwrap();
        w.write_var_f64("v", &(0..12).map(f64::from).collect::<Vec<_>>())
            .unwrap();
        w.write_var_i16("lat", &[120, 100]).unwrap();
        w.write_var_f64("lon", &[1.0, 2.0, 3.0]).unwrap();
        w.close().unwrap();
        // Stored 120, 100 (north first): 60 and 50 degrees, flipped to run south to north. Raw,
        // the map would have been placed at 100 to 120 degrees of latitude.
        let f = read(&p, "v", &Select::new()).unwrap();
        assert_eq!(f.y, Some(vec![50.0, 60.0]));
        assert_eq!(bounds(&p, "v", &Select::new()), Some([45.0, 0.5, 65.0, 3.5]));
        let at = |lat: f64| Select::from([("lat".to_string(), lat)]);
        assert!(
            read(&p, "v", &at(60.0)).is_err(),
            "lat selected leaves (time, lon): not a field"
        );
        let e = read(&p, "v", &at(120.0)).unwrap_err().to_string();
        assert!(e.contains("no such lat (it has: 60, 50)"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
