//! A NetCDF file as the field reader sees it, whatever its format: classic (CDF-1, 2, 5) or
//! NetCDF-4 (HDF5, with groups, chunks and deflate), both read by the pure-Rust
//! `netcdf-reader` (no netCDF-C or HDF5 library to install). A variable is named by its path
//! (`group/var`, as `xarray.open_dataset(group=...)` and `ncdump` name it); the coordinate
//! variable of one of its dimensions is looked up in its group and then in each enclosing
//! group, as netCDF-C resolves a dimension's name.

use netcdf_reader::{NcAttrValue, NcFile, NcType, NcVariable};
use std::path::Path;

/// An open NetCDF file.
pub(super) struct NcSource {
    file: NcFile,
}

/// One variable: its path in the file and its header.
#[derive(Clone)]
pub(super) struct Var<'a> {
    path: String,
    var: &'a NcVariable,
}

impl NcSource {
    pub(super) fn open(path: &Path) -> Result<Self, String> {
        NcFile::open(path).map(|file| Self { file }).map_err(|e| e.to_string())
    }

    /// A classic file is read to its end, every variable, as the netCDF-C library's `ncdump`
    /// would: one cut short anywhere is refused, not half used (its variables are laid one
    /// after another, so a cut in the one not read is a file damaged in transit). A NetCDF-4
    /// file's variables are its own objects, each checked as it is read. `except`: the one the
    /// caller reads itself (not read twice).
    pub(super) fn check_whole(&self, except: &str) -> Result<(), String> {
        let Some(classic) = self.file.as_classic() else {
            return Ok(());
        };
        for v in classic.root_group().variables.iter().filter(|v| v.name() != except) {
            let read = match is_number(v.dtype()) {
                true => self.file.read_variable_as_f64(v.name()).map(drop),
                false => self.file.read_variable_as_strings(v.name()).map(drop),
            };
            read.map_err(|e| format!("{}: {e}", v.name()))?;
        }
        Ok(())
    }

    /// The variable at `path` (`var` or `group/var`; a leading `/` is the root's).
    pub(super) fn var(&self, path: &str) -> Option<Var<'_>> {
        let path = path.trim_start_matches('/');
        let var = self.file.variable(path).ok()?;
        Some(Var { path: path.into(), var })
    }

    /// The group at `path` ("" is the root).
    fn group(&self, path: &str) -> Option<&netcdf_reader::NcGroup> {
        self.file.root_group().ok()?.group(path)
    }

    /// Every variable's path in the group of `near` (the root's for a bare name): what a
    /// refusal of a name lists.
    pub(super) fn names_near(&self, near: &str) -> Vec<String> {
        let group = group_of(near.trim_start_matches('/'));
        let prefix = if group.is_empty() {
            String::new()
        } else {
            format!("{group}/")
        };
        self.group(group)
            .map(|g| g.variables.as_slice())
            .unwrap_or_default()
            .iter()
            .map(|v| format!("{prefix}{}", v.name()))
            .collect()
    }

    /// The coordinate variable of dimension `dim` as `of` sees it: one dimension, named as the
    /// dimension, in `of`'s group or the nearest enclosing one.
    pub(super) fn coordinate(&self, of: &str, dim: &str) -> Option<Var<'_>> {
        let mut group = group_of(of.trim_start_matches('/'));
        loop {
            let found = self.group(group).and_then(|g| g.coordinate_variable(dim));
            if let Some(var) = found.filter(|v| v.is_coordinate_variable_for(dim)) {
                let path = match group {
                    "" => var.name().to_string(),
                    g => format!("{g}/{}", var.name()),
                };
                return Some(Var { path, var });
            }
            if group.is_empty() {
                return None;
            }
            group = group_of(group);
        }
    }

    /// Every value of `var` as a double, in the file's order (C order of its dimensions);
    /// `None` for characters, strings and user-defined types.
    pub(super) fn values(&self, var: &Var<'_>) -> Result<Option<Vec<f64>>, String> {
        if !is_number(var.dtype()) {
            return Ok(None);
        }
        let a = self.file.read_variable_as_f64(&var.path).map_err(|e| e.to_string())?;
        Ok(Some(a.iter().copied().collect()))
    }
}

/// The group part of a path (`a/b/v` is `a/b`; `v` is the root's, "").
fn group_of(path: &str) -> &str {
    path.rsplit_once('/').map_or("", |(g, _)| g)
}

/// Whether values of type `t` are numbers a field can hold.
pub(super) fn is_number(t: &NcType) -> bool {
    use NcType::*;
    matches!(
        t,
        Byte | Short | Int | Float | Double | UByte | UShort | UInt | Int64 | UInt64
    )
}

impl<'a> Var<'a> {
    pub(super) fn path(&self) -> &str {
        &self.path
    }

    pub(super) fn dtype(&self) -> &'a NcType {
        self.var.dtype()
    }

    /// Its dimensions' names and sizes, in the file's order.
    pub(super) fn dims(&self) -> Vec<(String, usize)> {
        self.var
            .dimensions()
            .iter()
            .map(|d| (d.name.clone(), d.size as usize))
            .collect()
    }

    pub(super) fn attr(&self, name: &str) -> Option<&'a NcAttrValue> {
        self.var.attribute(name).map(|a| &a.value)
    }

    /// A text attribute (`None` where it is missing or not text).
    pub(super) fn text(&self, name: &str) -> Option<String> {
        self.attr(name).and_then(NcAttrValue::as_string)
    }

    /// A text attribute, "" where it is missing.
    pub(super) fn said(&self, name: &str) -> String {
        self.text(name).unwrap_or_default()
    }

    /// A numeric attribute's values as doubles.
    pub(super) fn numbers(&self, name: &str) -> Option<Vec<f64>> {
        self.attr(name).and_then(NcAttrValue::as_f64_vec)
    }
}

/// The type an attribute's values are stored in.
pub(super) fn attr_type(a: &NcAttrValue) -> Option<NcType> {
    Some(match a {
        NcAttrValue::Bytes(_) => NcType::Byte,
        NcAttrValue::Shorts(_) => NcType::Short,
        NcAttrValue::Ints(_) => NcType::Int,
        NcAttrValue::Floats(_) => NcType::Float,
        NcAttrValue::Doubles(_) => NcType::Double,
        NcAttrValue::UBytes(_) => NcType::UByte,
        NcAttrValue::UShorts(_) => NcType::UShort,
        NcAttrValue::UInts(_) => NcType::UInt,
        NcAttrValue::Int64s(_) => NcType::Int64,
        NcAttrValue::UInt64s(_) => NcType::UInt64,
        NcAttrValue::Chars(_) | NcAttrValue::Strings(_) | NcAttrValue::UserDefined { .. } => return None,
    })
}
