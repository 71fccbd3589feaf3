//! One variable of a NetCDF file as a field, decoded the way xarray decodes it (CF
//! conventions, [`decode`]): classic or NetCDF-4, a variable in a group named by its path
//! (`group/var`), chunked and compressed variables read whole ([`file`]).
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

mod calendar;
mod decode;
mod file;

pub use calendar::TimeAxis;

use super::error::DatasetError;
use super::FieldSeries;
use decode::Decode;
use faer::Mat;
use file::{NcSource, Var};
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
    let src = NcSource::open(path.as_ref()).ok()?;
    let var = src.var(variable)?;
    let coords = coordinates(&src, &var, |d| select.contains_key(d)).ok()?;
    let layout = Layout::of(&src, &var, select, &coords, &|why| why).ok()?;
    Some(layout.kept.iter().map(|&d| layout.sizes[d]).collect())
}

/// Where `variable` lies on the Earth, `[south, west, north, east]` (degrees, cell edges), when
/// its `y` and `x` coordinates are latitude and longitude (CF `units` `degrees_north` and
/// `degrees_east`, or those `standard_name`s); longitude in [-180, 180). `None` where they are
/// not (or one is selected). A latitude or longitude that is not evenly spaced within what its
/// storage can hold ([`regular_span`]) is refused: a site placed from it would be placed wrong.
pub fn bounds(path: impl AsRef<Path>, variable: &str, select: &Select) -> Result<Option<[f64; 4]>, DatasetError> {
    let path = path.as_ref();
    let cf = |why: String| DatasetError::Cf {
        path: path.display().to_string(),
        variable: variable.into(),
        why,
    };
    let Ok(src) = NcSource::open(path) else { return Ok(None) };
    let Some(var) = src.var(variable) else { return Ok(None) };
    let names: Vec<String> = var.dims().into_iter().map(|(n, _)| n).collect();
    let geographic = |north: bool| {
        names
            .iter()
            .find_map(|n| src.coordinate(var.path(), n).filter(|c| is_geographic(c, north)))
    };
    let (Some(lat), Some(lon)) = (geographic(true), geographic(false)) else {
        return Ok(None);
    };
    if [&lat, &lon]
        .iter()
        .any(|c| select.contains_key(c.path().rsplit('/').next().unwrap_or("")))
    {
        return Ok(None);
    }
    let span = |c: &Var<'_>, wrap: bool| -> Result<(f64, f64), DatasetError> {
        let v = coordinate(&src, c)
            .map_err(&cf)?
            .ok_or_else(|| cf(format!("{} is not numbers", c.path())))?;
        let v = if wrap { across_the_dateline(v) } else { v };
        let decode = Decode::of(c).map_err(&cf)?;
        let rounding = |x: f64| decode.rounding(c.dtype(), x).unwrap_or(0.0);
        regular_span(&v, rounding).map_err(|why| cf(format!("coordinate {:?} {why}", c.path())))
    };
    let (south, north) = span(&lat, false)?;
    let (west, east) = span(&lon, true)?;
    let wrapped = crate::longitude::wrap_longitude(west);
    Ok(Some([south, wrapped, north, wrapped + (east - west)]))
}

/// The cell edges `(low, high)` of an evenly spaced coordinate `v` (either way round): its
/// values are taken as even when none is further from the line between the first and the last
/// than its storage can hold (twice `rounding(value)`, the half-step of its type: a latitude in
/// 32-bit floats is off by up to 1e-5 of a quarter-degree step, and GDAL and xarray place it as
/// regular) or a millionth of a step (doubles written as sums). Else refused, naming the
/// largest departure: the map would be stretched in silence.
fn regular_span(v: &[f64], rounding: impl Fn(f64) -> f64) -> Result<(f64, f64), String> {
    let n = v.len();
    if n < 2 {
        return Err(format!("has {n} value: a site needs two to be placed"));
    }
    let step = (v[n - 1] - v[0]) / (n - 1) as f64;
    let (worst, at) = (0..n)
        .map(|i| ((v[i] - (v[0] + step * i as f64)).abs(), i))
        .fold((0.0, 0), |a, b| if b.0 > a.0 { b } else { a });
    let allowed = (1e-6 * step.abs()).max(2.0 * rounding(v[at]) + 2.0 * rounding(v[0]).max(rounding(v[n - 1])));
    if !(step != 0.0 && worst <= allowed) {
        return Err(format!(
            "is not evenly spaced: value {at} ({}) is {worst:.3e} from an even step of {step} (allowed \
             {allowed:.1e}); an irregular or curvilinear grid is not placed: regrid it (`cdo remapbil`) or \
             give [mavlink] origin and size_m",
            v[at]
        ));
    }
    let (lo, hi) = if step > 0.0 { (v[0], v[n - 1]) } else { (v[n - 1], v[0]) };
    Ok((lo - step.abs() / 2.0, hi + step.abs() / 2.0))
}

/// The time coordinate of `variable`'s frames (after `select`), where it has CF units
/// (`"<unit> since <date>"`): what dates the frames are.
pub fn time_axis(path: impl AsRef<Path>, variable: &str, select: &Select) -> Option<TimeAxis> {
    let src = NcSource::open(path.as_ref()).ok()?;
    let var = src.var(variable)?;
    let coords = coordinates(&src, &var, |d| !select.contains_key(d)).ok()?;
    let layout = Layout::of(&src, &var, select, &coords, &|why| why).ok()?;
    let dim = &layout.names[layout.kept[0]];
    let c = src.coordinate(var.path(), dim)?;
    let units = c.text("units").filter(|u| u.contains(" since "))?;
    Some(TimeAxis {
        units,
        calendar: c.text("calendar").unwrap_or_default(),
        values: coords.get(dim)?.clone(),
    })
}

/// The `units` attribute of `variable`, from the header.
pub fn units(path: impl AsRef<Path>, variable: &str) -> Option<String> {
    text_attribute(path, variable, "units")
}

/// A text attribute of `variable` (`units`, `standard_name`), from the header.
pub fn text_attribute(path: impl AsRef<Path>, variable: &str, name: &str) -> Option<String> {
    NcSource::open(path.as_ref()).ok()?.var(variable)?.text(name)
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

/// Whether a coordinate is a latitude (`north`) or a longitude: in degrees north or east, or
/// so named by its `standard_name`.
fn is_geographic(c: &Var<'_>, north: bool) -> bool {
    let name = if north { "latitude" } else { "longitude" };
    in_degrees(&c.said("units"), north) || c.said("standard_name").trim() == name
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

/// Read `variable` (a path, `group/var` in a NetCDF-4 file's group) of the NetCDF file at
/// `path`, classic or NetCDF-4; a time coordinate without CF units is refused.
pub fn read(path: impl AsRef<Path>, variable: &str, select: &Select) -> Result<NetCdfField, DatasetError> {
    read_stepped(path, variable, select, None)
}

/// [`read`], with `step_s` the seconds between frames where the file's time coordinate does
/// not say them (a mission's `[time] step_s`).
pub fn read_stepped(
    path: impl AsRef<Path>,
    variable: &str,
    select: &Select,
    step_s: Option<f64>,
) -> Result<NetCdfField, DatasetError> {
    let path = path.as_ref();
    let p = path.display().to_string();
    let cf = |why: String| DatasetError::Cf {
        path: p.clone(),
        variable: variable.into(),
        why,
    };
    let unreadable = |why: String| DatasetError::NetCdf { path: p.clone(), why };
    let src = NcSource::open(path).map_err(unreadable)?;
    src.check_whole(variable.trim_start_matches('/')).map_err(unreadable)?;
    let Some(var) = src.var(variable) else {
        return Err(DatasetError::NoVariable {
            path: p.clone(),
            variable: variable.into(),
            have: src.names_near(variable).join(", "),
        });
    };
    let raw = src.values(&var).map_err(unreadable)?.ok_or_else(|| {
        cf(format!(
            "is {:?}; a field needs numbers (byte, short, int, float or double)",
            var.dtype()
        ))
    })?;
    let coords = coordinates(&src, &var, |_| true).map_err(&cf)?;
    let layout = Layout::of(&src, &var, select, &coords, &cf)?;
    let coord = |d: usize| coords.get(&layout.names[d]).cloned();
    let [t_dim, y_dim, x_dim] = [layout.kept[0], layout.kept[1], layout.kept[2]];
    let (times, mut y, mut x) = (coord(t_dim), coord(y_dim), coord(x_dim));
    let coordinate_of = |d: usize| src.coordinate(var.path(), &layout.names[d]);
    if coordinate_of(x_dim).is_some_and(|c| is_geographic(&c, false)) {
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
    let dt = time_step(
        coordinate_of(t_dim).as_ref(),
        &layout.names[t_dim],
        times.as_deref(),
        step_s,
    )
    .map_err(&cf)?;
    let values = Decode::of(&var).map_err(&cf)?.values(raw);
    let (rows, cols) = (layout.sizes[y_dim], layout.sizes[x_dim]);
    let snapshots = layout.snapshots(&values, (flip_y, flip_x));
    let missing = check_holes(&snapshots).map_err(&cf)?;
    Ok(NetCdfField {
        field: FieldSeries {
            rows,
            cols,
            dt,
            snapshots,
        },
        units: var.text("units"),
        y,
        x,
        missing,
    })
}

/// Refuse a field missing everywhere; the number of missing values. A frame missing at every
/// cell (a fully cloudy image, an analysis time with no value) is a frame in which nothing
/// was seen: its step has no observation and is not scored, and the file is not refused.
pub(crate) fn check_holes(snapshots: &Mat<f64>) -> Result<usize, String> {
    let missing = snapshots
        .col_iter()
        .map(|c| c.iter().filter(|v| v.is_nan()).count())
        .sum();
    if missing == snapshots.nrows() * snapshots.ncols() {
        return Err("every value is missing (fill value, missing_value or outside the valid range)".into());
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
        src: &NcSource,
        var: &Var<'_>,
        select: &Select,
        coords: &BTreeMap<String, Vec<f64>>,
        err: &dyn Fn(String) -> E,
    ) -> Result<Self, E> {
        let (names, sizes): (Vec<String>, Vec<usize>) = var.dims().into_iter().unzip();
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
        let axes = [0, 1, 2].map(|i| Axis::of(src.coordinate(var.path(), &names[kept[i]]).as_ref()));
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

    /// The kept `(time, y, x)` of the file's `values` as snapshots (a column a frame, rows south
    /// to north): `flip` says which of `y` and `x` the file stores backwards.
    fn snapshots(&self, values: &[f64], (flip_y, flip_x): (bool, bool)) -> Mat<f64> {
        let [t_dim, y_dim, x_dim] = [self.kept[0], self.kept[1], self.kept[2]];
        let (t, rows, cols) = (self.sizes[t_dim], self.sizes[y_dim], self.sizes[x_dim]);
        let mut snapshots = Mat::zeros(rows * cols, t);
        for k in 0..t {
            for r in 0..rows {
                for c in 0..cols {
                    let (fr, fc) = (
                        if flip_y { rows - 1 - r } else { r },
                        if flip_x { cols - 1 - c } else { c },
                    );
                    snapshots[(r * cols + c, k)] = values[self.flat(&[(t_dim, k), (y_dim, fr), (x_dim, fc)])];
                }
            }
        }
        snapshots
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
    /// The axis of a dimension whose coordinate variable is `c`: `None` where it has none or
    /// that says none of these (a level's `Z`).
    fn of(c: Option<&Var<'_>>) -> Option<Self> {
        let c = c?;
        let (axis, units) = (c.said("axis").trim().to_ascii_uppercase(), c.said("units"));
        let standard = c.said("standard_name");
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

/// The decoded values of the coordinate variables of `var`'s dimensions that `wanted` names.
fn coordinates(
    src: &NcSource,
    var: &Var<'_>,
    wanted: impl Fn(&str) -> bool,
) -> Result<BTreeMap<String, Vec<f64>>, String> {
    let mut coords = BTreeMap::new();
    for (dim, _) in var.dims().into_iter().filter(|(d, _)| wanted(d)) {
        let Some(c) = src.coordinate(var.path(), &dim) else {
            continue;
        };
        if let Some(values) = coordinate(src, &c).map_err(|why| format!("coordinate {dim:?}: {why}"))? {
            coords.insert(dim, values);
        }
    }
    Ok(coords)
}

/// A coordinate variable's values as xarray decodes them, as the variable's are: packed
/// integers unpacked (a latitude stored as shorts of 0.01 degrees is 20 to 60, not 2000 to
/// 6000), a fill value NaN (so refused as not monotonic); `None` for characters.
fn coordinate(src: &NcSource, c: &Var<'_>) -> Result<Option<Vec<f64>>, String> {
    let decode = Decode::of(c)?;
    Ok(src.values(c)?.map(|raw| decode.values(raw)))
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
/// <date>"`, any of CF's calendars: a day is 86,400 s in each, so the step is the same); 1 where
/// the file has no time coordinate or one frame. A time axis that does not increase is refused,
/// and so are units that are not time, a calendar CF does not name, and a time coordinate
/// without units unless `step_s` gives the step (its numbers were taken as seconds: a storm's
/// 6-hourly `timestep` of 6 was a step of 6 s).
fn time_step(c: Option<&Var<'_>>, dim: &str, times: Option<&[f64]>, step_s: Option<f64>) -> Result<f64, String> {
    let (Some(c), Some(t)) = (c, times.filter(|t| t.len() > 1)) else {
        return Ok(1.0);
    };
    if !t.windows(2).all(|w| w[1] > w[0]) || t.iter().any(|x| !x.is_finite()) {
        return Err(format!("time coordinate {dim:?} does not increase"));
    }
    check_calendar(dim, &c.said("calendar"))?;
    let units = c.said("units");
    let unit = units.split_whitespace().next().unwrap_or("").to_ascii_lowercase();
    let seconds = match unit.as_str() {
        _ if !units.contains(" since ") => {
            return step_s.ok_or_else(|| {
                format!(
                    "time coordinate {dim:?} has units {units:?}, not CF's \"<unit> since <date>\": how long a step \
                     is is not in the file; give the mission's [time] start and step_s, or the file units \
                     (`ncatted -a units,{dim},o,c,\"hours since 2000-01-01\" IN`)"
                )
            })
        }
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

/// A time coordinate's `calendar` is one CF names (CF 1.11, 4.4.2; "" is the default,
/// `standard`); any other is refused rather than read as one it is not.
fn check_calendar(dim: &str, calendar: &str) -> Result<(), String> {
    const CF: [&str; 10] = [
        "standard",
        "gregorian",
        "proleptic_gregorian",
        "noleap",
        "365_day",
        "all_leap",
        "366_day",
        "360_day",
        "julian",
        "none",
    ];
    let c = calendar.trim().to_ascii_lowercase();
    match c.is_empty() || CF.contains(&c.as_str()) {
        true => Ok(()),
        false => Err(format!(
            "time coordinate {dim:?} has calendar {calendar:?}, which CF does not name (it names {})",
            CF.join(", ")
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use netcdf3::DataSet;

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
        // A frame with no value is read as one (nothing seen then); refused: a variable with no
        // value, coordinates out of order.
        let mut holed = data;
        holed[6..].iter_mut().for_each(|v| *v = -999);
        write(&p, &holed, &[60.0, 50.0], &attrs);
        let f = read(&p, "v", &Select::new()).unwrap();
        assert_eq!(f.missing, 1 + 6, "frame 0's fill and all of frame 1");
        assert!(f.field.snapshots.col(1).iter().all(|v| v.is_nan()));
        assert_eq!(f.field.snapshots.col(0).iter().filter(|v| v.is_finite()).count(), 5);
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
        assert_eq!(
            bounds(&b, "v", &Select::new()).unwrap(),
            bounds(&a, "v", &Select::new()).unwrap()
        );
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
        assert_eq!(
            bounds(&p, "v", &Select::new()).unwrap(),
            Some([9.5, 167.5, 12.5, 187.5])
        );
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
        assert_eq!(bounds(&p, "v", &Select::new()).unwrap(), Some([45.0, 0.5, 65.0, 3.5]));
        let at = |lat: f64| Select::from([("lat".to_string(), lat)]);
        assert!(
            read(&p, "v", &at(60.0)).is_err(),
            "lat selected leaves (time, lon): not a field"
        );
        let e = read(&p, "v", &at(120.0)).unwrap_err().to_string();
        assert!(e.contains("no such lat (it has: 60, 50)"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// `v(time, y, x)` of 2 x 2 doubles over 3 frames, its time coordinate `time` (6-hourly
    /// numbers) with the attributes given.
    fn write_timed(path: &Path, attrs: &[(&str, &str)]) {
        let mut ds = netcdf3::DataSet::new();
        for (d, n) in [("time", 3), ("y", 2), ("x", 2)] {
            ds.add_fixed_dim(d, n).unwrap();
        }
        ds.add_var_f64("v", &["time", "y", "x"]).unwrap();
        ds.add_var_f64("time", &["time"]).unwrap();
        for (k, v) in attrs {
            ds.add_var_attr_string("time", k, v).unwrap();
        }
        let mut w = netcdf3::FileWriter::open(path).unwrap();
        w.set_def(&ds, netcdf3::Version::Classic, 0).unwrap();
        w.write_var_f64("v", &(0..12).map(f64::from).collect::<Vec<_>>())
            .unwrap();
        w.write_var_f64("time", &[0.0, 6.0, 12.0]).unwrap();
        w.close().unwrap();
    }

    #[test]
    fn time_is_taken_as_cf_says_or_from_the_mission_never_guessed() {
        let dir = scratch("hetfleet-time");
        let p = dir.join("t.nc");
        let none = Select::new();
        // CF units in any of CF's calendars: 6 hours (a day is 86,400 s in each).
        for calendar in ["", "360_day", "noleap", "all_leap", "julian", "proleptic_gregorian"] {
            write_timed(&p, &[("units", "hours since 2000-01-01"), ("calendar", calendar)]);
            assert_eq!(read(&p, "v", &none).unwrap().field.dt, 21_600.0, "{calendar:?}");
        }
        write_timed(&p, &[("units", "hours since 2000-01-01"), ("calendar", "lunar")]);
        let e = read(&p, "v", &none).unwrap_err().to_string();
        assert!(e.contains("calendar \"lunar\", which CF does not name"), "{e}");
        // No units: 6 was taken as 6 seconds; now refused, naming the coordinate, unless the
        // mission gives the step.
        write_timed(&p, &[]);
        let e = read(&p, "v", &none).unwrap_err().to_string();
        assert!(
            e.contains("time coordinate \"time\" has units \"\"") && e.contains("[time]"),
            "{e}"
        );
        assert!(!e.contains('\n'), "{e}");
        assert_eq!(read_stepped(&p, "v", &none, Some(21_600.0)).unwrap().field.dt, 21_600.0);
        std::fs::remove_dir_all(&dir).ok();
    }
}
