//! How a variable's stored values become data, as xarray's CF decoding makes them: missing
//! where `_FillValue` or `missing_value` says (compared in the stored type), outside
//! `valid_min`/`valid_max`/`valid_range` (as netCDF4-python masks), `_Unsigned` integers read
//! unsigned, packed integers unpacked with `scale_factor` and `add_offset`.

use super::file::{attr_type, Var};
use netcdf_reader::NcType;

/// How stored values become data: which are missing, and the unpacking.
pub(super) struct Decode {
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
    pub(super) fn of(var: &Var<'_>) -> Result<Self, String> {
        let stored = var.dtype();
        let unsigned = unsigned_span(var, stored)?;
        let in_type = |v: f64| match unsigned {
            // A fill written unsigned (65535 for a short) is already the value as read.
            Some(_) if v >= 0.0 => v,
            _ => as_unsigned(unsigned, cast(v, stored)),
        };
        let mut missing: Vec<f64> = vec![];
        for name in ["_FillValue", "missing_value"] {
            missing.extend(var.numbers(name).unwrap_or_default().into_iter().map(in_type));
        }
        let mut valid = (f64::NEG_INFINITY, f64::INFINITY);
        let mut typed = vec![];
        if let Some(r) = var.numbers("valid_range") {
            let [lo, hi] = r[..] else {
                return Err(format!("valid_range has {} values, not 2", r.len()));
            };
            valid = (lo, hi);
            typed.push("valid_range");
        }
        if let Some(&[lo]) = var.numbers("valid_min").as_deref() {
            valid.0 = lo;
            typed.push("valid_min");
        }
        if let Some(&[hi]) = var.numbers("valid_max").as_deref() {
            valid.1 = hi;
            typed.push("valid_max");
        }
        let valid_packed = typed
            .iter()
            .all(|n| var.attr(n).and_then(attr_type).is_some_and(|t| &t == stored));
        if valid_packed {
            valid = (as_unsigned(unsigned, valid.0), as_unsigned(unsigned, valid.1));
        }
        let one = |name: &str, default: f64| -> Result<f64, String> {
            match var.numbers(name).as_deref() {
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

    /// The data from the stored values, NaN where missing.
    pub(super) fn values(&self, stored: Vec<f64>) -> Vec<f64> {
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
            .collect()
    }

    /// Half the step between two stored values, in the data's units: how far a value can be
    /// from what was meant by being stored (`None`: exact, a plain integer).
    pub(super) fn rounding(&self, stored: &NcType, magnitude: f64) -> Option<f64> {
        let relative = match stored {
            NcType::Float => f64::from(f32::EPSILON) / 2.0,
            NcType::Double => f64::EPSILON / 2.0,
            _ if self.scale != 1.0 => return Some(self.scale.abs() / 2.0),
            _ => return None,
        };
        Some(relative * magnitude.abs())
    }
}

/// `_Unsigned = "true"` (the NUG's way to store unsigned integers in NetCDF-3, which has none:
/// GOES-R's products are shorts so marked, with `valid_range = 0S, -6S`): the stored type's span
/// `2^bits`, which a negative stored value is read with, as netCDF4-python and netCDF-Java read
/// it, and so are its fill values and a valid range in the stored type (xarray converts only
/// `_FillValue`, leaving a `missing_value` of 254 in a byte as data). Read as signed, a byte of
/// 200 would be -56: data altered in silence. `"false"` or no attribute: signed. Anything else,
/// or `"true"` on a type that is not an integer, is refused (no setting ignored). NetCDF-4's
/// own unsigned types are read unsigned whatever the attribute says, as netCDF-C does.
fn unsigned_span(var: &Var<'_>, stored: &NcType) -> Result<Option<f64>, String> {
    let Some(said) = var.attr("_Unsigned") else {
        return Ok(None);
    };
    let said = said.as_string().unwrap_or_default();
    match (said.trim().to_ascii_lowercase().as_str(), stored) {
        ("false", _) => Ok(None),
        ("true", NcType::Byte) => Ok(Some(256.0)),
        ("true", NcType::Short) => Ok(Some(65_536.0)),
        ("true", NcType::Int) => Ok(Some(4_294_967_296.0)),
        ("true", NcType::UByte | NcType::UShort | NcType::UInt | NcType::UInt64) => Ok(None),
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

/// `v` as the stored type holds it (xarray casts a fill value to the variable's type before
/// comparing: 1e20 as a float is 100000002004087734272).
fn cast(v: f64, t: &NcType) -> f64 {
    match t {
        NcType::Float => f64::from(v as f32),
        NcType::Byte => f64::from(v as i8),
        NcType::Short => f64::from(v as i16),
        NcType::Int => f64::from(v as i32),
        NcType::UByte => f64::from(v as u8),
        NcType::UShort => f64::from(v as u16),
        NcType::UInt => f64::from(v as u32),
        _ => v,
    }
}
