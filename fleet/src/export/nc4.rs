//! One NetCDF-4 file, defined and filled in memory and written whole, as `estimate.nc` and
//! `readings.nc` are: every array chunked and compressed as the netCDF-C library does it
//! (zlib after the byte shuffle, the filters `ncdump -s` reports as `_DeflateLevel` and
//! `_Shuffle`), through `netcdf-writer` (pure Rust: nothing native to install).

use super::ExportError;
use netcdf_writer::{DimensionId, NcAttrValue, NcFileBuilder, NcWriteFormat, NcWriteOptions, NcWriteType, VariableId};
use std::path::Path;

pub(super) use netcdf_writer::Error;

/// zlib's level: 4 is where netCDF users' own default (`nccopy -d4`, xarray's examples) sits,
/// close to level 9's size for a fraction of its time.
const DEFLATE_LEVEL: u8 = 4;

/// At most this many values per chunk of a 1-D array: 1 MiB of doubles, the HDF5 chunk cache's
/// default size, so a reader never decompresses more than its cache holds for one value.
const CHUNK_VALUES: u64 = 1 << 17;

/// A NetCDF-4 file being built.
pub(super) struct Nc4 {
    file: NcFileBuilder,
}

impl Nc4 {
    pub fn new() -> Self {
        Self {
            file: NcFileBuilder::new(),
        }
    }

    pub fn dim(&mut self, name: &str, len: usize) -> Result<DimensionId, Error> {
        self.file.add_dimension(name, len as u64)
    }

    /// Variable `name` over `dims` holding `values`, compressed in chunks of one time step (or
    /// of [`CHUNK_VALUES`] along a single dimension).
    pub fn var<T: NcWriteType>(
        &mut self,
        name: &str,
        dims: &[(DimensionId, usize)],
        values: &[T],
    ) -> Result<VariableId, Error> {
        let ids: Vec<DimensionId> = dims.iter().map(|d| d.0).collect();
        let var = self.file.add_variable::<T>(name, &ids)?;
        self.compress(var, dims)?;
        self.file.write_variable(var, values)?;
        Ok(var)
    }

    /// A fixed-width text variable over `(dim, width)`: one string per `dim`.
    pub fn strings(
        &mut self,
        name: &str,
        dims: [(DimensionId, usize); 2],
        values: &[String],
    ) -> Result<VariableId, Error> {
        let var = self.file.add_char_variable(name, &[dims[0].0, dims[1].0])?;
        self.file.write_char_variable_strings(var, values)?;
        Ok(var)
    }

    /// Chunks of one step for a `(time, y, x)` array, of at most [`CHUNK_VALUES`] otherwise.
    fn compress(&mut self, var: VariableId, dims: &[(DimensionId, usize)]) -> Result<(), Error> {
        if dims.is_empty() || dims.iter().any(|d| d.1 == 0) {
            return Ok(());
        }
        let chunk: Vec<u64> = match dims {
            [(_, n)] => vec![(*n as u64).min(CHUNK_VALUES)],
            [_, rest @ ..] => std::iter::once(1).chain(rest.iter().map(|d| d.1 as u64)).collect(),
            [] => unreachable!("an empty shape is returned above"),
        };
        self.file.set_variable_chunking(var, chunk)?;
        self.file.set_variable_deflate(var, Some(DEFLATE_LEVEL), true)
    }

    /// `_FillValue` of a float variable: where there is no value (land, no data), which
    /// xarray decodes to NaN and GDAL to nodata.
    pub fn fill_f32(&mut self, var: VariableId) -> Result<(), Error> {
        self.file.set_variable_fill_value(var, netcdf_writer::NC_FILL_FLOAT)
    }

    pub fn fill_f64(&mut self, var: VariableId) -> Result<(), Error> {
        self.file.set_variable_fill_value(var, netcdf_writer::NC_FILL_DOUBLE)
    }

    /// Text attributes of `var`.
    pub fn text(&mut self, var: VariableId, attrs: &[(&str, &str)]) -> Result<(), Error> {
        for (k, v) in attrs {
            self.attr(var, k, NcAttrValue::Chars(v.to_string()))?;
        }
        Ok(())
    }

    pub fn attr(&mut self, var: VariableId, name: &str, value: NcAttrValue) -> Result<(), Error> {
        self.file.add_variable_attribute(var, name, value)
    }

    pub fn global_text(&mut self, name: &str, value: impl Into<String>) -> Result<(), Error> {
        self.file.add_attribute(name, NcAttrValue::Chars(value.into()))
    }

    pub fn global(&mut self, name: &str, value: NcAttrValue) -> Result<(), Error> {
        self.file.add_attribute(name, value)
    }

    /// Encode and write to `path` through a temporary beside it, so a failed export leaves no
    /// half file under the name.
    pub fn write(self, path: &Path) -> Result<(), ExportError> {
        let failed = |why: String| ExportError::Write { path: path.into(), why };
        let options = NcWriteOptions {
            format: NcWriteFormat::Nc4,
        };
        let (_, bytes) = self.file.to_vec(options).map_err(|e| failed(e.to_string()))?;
        let tmp = path.with_extension("nc.partial");
        if let Err(e) = std::fs::write(&tmp, bytes) {
            let _ = std::fs::remove_file(&tmp);
            return Err(failed(e.to_string()));
        }
        std::fs::rename(&tmp, path).map_err(|e| failed(e.to_string()))
    }
}

/// A schema error as the export's.
pub(super) fn schema_error(path: &Path) -> impl Fn(Error) -> ExportError + '_ {
    move |e| ExportError::Write {
        path: path.into(),
        why: e.to_string(),
    }
}
