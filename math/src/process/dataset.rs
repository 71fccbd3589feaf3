//! Datasets as field sources: any float64 `.npy` array of shape `(frames, rows, cols)` is a
//! truth field (what `fleet simulate` writes and numpy users load with `np.load`), and a JSON
//! sidecar beside it records how it was made; or one variable of a NetCDF file (classic or
//! NetCDF-4, [`super::netcdf`]), as environmental data usually comes.

use super::error::DatasetError;
use super::FieldSeries;
use crate::npy::{self, NpyError};
use faer::Mat;
use std::path::Path;

/// `field` if its values are in units the estimator holds exactly ([`super::units`]).
pub fn in_units(field: FieldSeries, path: &Path) -> Result<FieldSeries, DatasetError> {
    let mut spread = super::units::Spread::default();
    for col in field.snapshots.col_iter() {
        col.iter().for_each(|&v| spread.add(v));
    }
    match spread.check() {
        Ok(()) => Ok(field),
        Err(why) => Err(DatasetError::Units {
            path: path.display().to_string(),
            why,
        }),
    }
}

/// Load a truth `.npy`: as [`load`], except that a NaN is a value the truth does not have
/// (land, cloud: numpy's way of writing a masked field), which nothing senses or scores. A
/// field or a frame with no value at all is refused, and so is an infinity.
pub fn load_truth(path: impl AsRef<Path>, dt: f64) -> Result<FieldSeries, DatasetError> {
    let path = path.as_ref();
    let p = path.display().to_string();
    let a = npy::read(path)?;
    if let Some(index) = a.data.iter().position(|v| v.is_infinite()) {
        return Err(NpyError::NonFinite {
            path: p,
            index,
            value: a.data[index],
        }
        .into());
    }
    let holes = a.data.iter().any(|v| v.is_nan());
    // NaN is let through, the rest checked as `load` checks it: the array is not copied to
    // hide its holes (at 384 x 768 each copy of a mission's truth is 236 MB).
    let field = from_array(a, &p, dt, true)?;
    if holes {
        super::netcdf::check_holes(&field.snapshots).map_err(|why| DatasetError::Holes { path: p, why })?;
    }
    Ok(field)
}

/// Load a `(frames, rows, cols)` float64 `.npy`, checked for shape and finiteness. `dt` is
/// the time between frames (the file does not carry one).
pub fn load(path: impl AsRef<Path>, dt: f64) -> Result<FieldSeries, DatasetError> {
    let path = path.as_ref();
    let p = path.display().to_string();
    from_array(npy::read(path)?, &p, dt, false)
}

/// A `(frames, rows, cols)` array as a field, checked for shape and finiteness (`holes`: NaN
/// is a value the field does not have, and passes).
fn from_array(a: npy::Array, p: &str, dt: f64, holes: bool) -> Result<FieldSeries, DatasetError> {
    let p = p.to_string();
    let &[t, rows, cols] = a.shape.as_slice() else {
        return Err(DatasetError::Shape {
            path: p,
            shape: a.shape,
        });
    };
    if t < 1 || rows == 0 || cols == 0 {
        return Err(DatasetError::TooSmall {
            path: p,
            shape: a.shape,
            min: 1,
        });
    }
    if !holes {
        a.check_finite(&p)?;
    }
    let n = rows * cols;
    Ok(FieldSeries {
        rows,
        cols,
        dt,
        snapshots: Mat::from_fn(n, t, |i, j| a.data[j * n + i]),
    })
}

/// Load variable `variable` of a NetCDF file (classic or NetCDF-4) as a field, decoded
/// as xarray decodes it ([`super::netcdf::read`]): NaN where the file marks a value missing.
/// `step_s`: the seconds between frames where the file's time coordinate has no CF units
/// ([`super::netcdf::read_stepped`]).
pub fn load_netcdf(
    path: impl AsRef<Path>,
    variable: &str,
    select: &super::netcdf::Select,
    step_s: Option<f64>,
) -> Result<FieldSeries, DatasetError> {
    Ok(super::netcdf::read_stepped(path, variable, select, step_s)?.field)
}

/// The `(frames, rows, cols)` of a NetCDF variable after `select`, from the header.
pub fn netcdf_shape(path: impl AsRef<Path>, variable: &str, select: &super::netcdf::Select) -> Option<Vec<usize>> {
    super::netcdf::shape(path, variable, select)
}

/// Write a field as a `(frames, rows, cols)` float64 `.npy`, plus `sidecar` as pretty JSON at
/// `<path>.json` when given.
pub fn save(
    path: impl AsRef<Path>,
    field: &FieldSeries,
    sidecar: Option<&serde_json::Value>,
) -> Result<(), DatasetError> {
    let path = path.as_ref();
    let (n, t) = (field.dim(), field.frames());
    let mut data: Vec<f64> = Vec::with_capacity(n * t);
    for k in 0..t {
        data.extend(field.snapshots.col(k).iter());
    }
    npy::write(path, &[t, field.rows, field.cols], &data)?;
    if let Some(meta) = sidecar {
        let side = sidecar_path(path);
        let text = serde_json::to_string_pretty(meta).expect("JSON values serialise");
        std::fs::write(&side, text).map_err(|source| DatasetError::Io {
            path: side.display().to_string(),
            source,
        })?;
    }
    Ok(())
}

/// The time between frames a dataset's sidecar records (`"dt"`), if it has one.
pub fn sidecar_dt(path: &Path) -> Option<f64> {
    let text = std::fs::read_to_string(sidecar_path(path)).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    v.get("dt")?.as_f64().filter(|dt| dt.is_finite() && *dt > 0.0)
}

/// `cloud1.npy` -> `cloud1.json`.
pub fn sidecar_path(path: &Path) -> std::path::PathBuf {
    path.with_extension("json")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_rejections() {
        let dir = std::env::temp_dir().join(format!("hetfleet-ds-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = FieldSeries {
            rows: 2,
            cols: 3,
            dt: 0.5,
            snapshots: Mat::from_fn(6, 4, |i, j| (i * 10 + j) as f64),
        };
        let p = dir.join("f.npy");
        save(&p, &f, Some(&serde_json::json!({"a": 1}))).unwrap();
        let g = load(&p, 0.5).unwrap();
        assert_eq!((g.rows, g.cols, g.frames()), (2, 3, 4));
        assert_eq!(g.snapshots, f.snapshots);
        assert!(dir.join("f.json").exists());
        npy::write(dir.join("flat.npy"), &[6, 4], &[0.0; 24]).unwrap();
        assert!(matches!(
            load(dir.join("flat.npy"), 1.0),
            Err(DatasetError::Shape { .. })
        ));
        npy::write(dir.join("nan.npy"), &[1, 2, 2], &[0.0, f64::NAN, 0.0, 0.0]).unwrap();
        assert!(load(dir.join("nan.npy"), 1.0).is_err());
        assert!(load(dir.join("missing.npy"), 1.0).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A NetCDF-3 classic file with `name(time, y, x)` of doubles (written by `netcdf3`).
    fn write_nc(path: &Path, name: &str, shape: [usize; 3], data: &[f64]) {
        let mut ds = netcdf3::DataSet::new();
        for (d, n) in ["time", "y", "x"].iter().zip(shape) {
            ds.add_fixed_dim(d, n).unwrap();
        }
        ds.add_var_f64(name, &["time", "y", "x"]).unwrap();
        ds.add_var_f32("flat", &["y", "x"]).unwrap();
        let mut w = netcdf3::FileWriter::open(path).unwrap();
        w.set_def(&ds, netcdf3::Version::Classic, 0).unwrap();
        w.write_var_f64(name, data).unwrap();
        w.write_var_f32("flat", &vec![0.0; shape[1] * shape[2]]).unwrap();
        w.close().unwrap();
    }

    #[test]
    fn netcdf_datasets_load_like_npy_and_bad_ones_are_named() {
        let dir = std::env::temp_dir().join(format!("hetfleet-nc-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let data: Vec<f64> = (0..24).map(|k| k as f64 * 0.5 - 3.0).collect();
        let none = crate::process::netcdf::Select::new();
        let nc = dir.join("f.nc");
        write_nc(&nc, "density", [4, 2, 3], &data);
        let npy_path = dir.join("f.npy");
        npy::write(&npy_path, &[4, 2, 3], &data).unwrap();
        let (a, b) = (
            load_netcdf(&nc, "density", &none, None).unwrap(),
            load(&npy_path, 0.5).unwrap(),
        );
        assert_eq!((a.rows, a.cols, a.frames()), (2, 3, 4));
        assert_eq!(a.snapshots, b.snapshots, "the same field as the .npy");
        assert_eq!(netcdf_shape(&nc, "density", &none), Some(vec![4, 2, 3]));
        let e = load_netcdf(&nc, "temperature", &none, None).unwrap_err().to_string();
        assert!(
            e.contains("no variable \"temperature\"") && e.contains("density") && e.contains("f.nc"),
            "{e}"
        );
        assert!(matches!(
            load_netcdf(&nc, "flat", &none, None),
            Err(DatasetError::Cf { .. })
        ));
        let mut bad = data.clone();
        bad[7] = f64::NAN;
        write_nc(&dir.join("nan.nc"), "density", [4, 2, 3], &bad);
        // A NaN is a missing value (xarray's reading too): that cell of that frame only.
        let holed = load_netcdf(dir.join("nan.nc"), "density", &none, None).unwrap();
        assert!(holed.snapshots[(1, 1)].is_nan() && holed.snapshots.col(0).iter().all(|v| v.is_finite()));
        // Truncated anywhere (header or data): an error naming the file, never a panic.
        let bytes = std::fs::read(&nc).unwrap();
        for cut in [0, 3, 10, 40, bytes.len() / 2, bytes.len() - 1] {
            let t = dir.join(format!("cut{cut}.nc"));
            std::fs::write(&t, &bytes[..cut]).unwrap();
            let e = load_netcdf(&t, "density", &none, None).unwrap_err().to_string();
            assert!(e.contains(&format!("cut{cut}.nc")), "{e}");
        }
        assert!(load_netcdf(dir.join("missing.nc"), "density", &none, None).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn files_are_known_by_their_content_whatever_their_name() {
        use crate::process::truth::{is_netcdf, is_npy, sniff, FileKind, TruthSource};
        let dir = std::env::temp_dir().join(format!("hetfleet-kind-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let data: Vec<f64> = (0..24).map(|k| k as f64).collect();
        // A NetCDF-3 file called `.cdf` (Ferret's) or `.dat`, an array called `.nc`.
        let (cdf, dat, npy_nc) = (dir.join("f.cdf"), dir.join("f.dat"), dir.join("a.nc"));
        write_nc(&cdf, "density", [4, 2, 3], &data);
        std::fs::copy(&cdf, &dat).unwrap();
        npy::write(&npy_nc, &[4, 2, 3], &data).unwrap();
        assert_eq!(
            (sniff(&cdf), sniff(&npy_nc)),
            (Some(FileKind::NetCdf3), Some(FileKind::Npy))
        );
        assert!(is_netcdf(&dat) && !is_npy(&dat) && is_npy(&npy_nc) && !is_netcdf(&npy_nc));
        let none = crate::process::netcdf::Select::new();
        assert_eq!(load_netcdf(&dat, "density", &none, None).unwrap().frames(), 4);
        let keys = |d: &std::path::Path, var: Option<&str>| {
            let mut j = serde_json::json!({ "dataset": d });
            if let Some(v) = var {
                j["variable"] = v.into();
            }
            serde_json::from_value::<TruthSource>(j)
        };
        assert!(matches!(keys(&dat, Some("density")), Ok(TruthSource::NetCdf { .. })));
        assert!(matches!(keys(&npy_nc, None), Ok(TruthSource::Dataset(_))));
        assert!(
            keys(&dat, None).is_err(),
            "a NetCDF file needs its variable, whatever its name"
        );
        assert!(keys(&npy_nc, Some("density")).is_err(), "an array has no variables");
        // NetCDF-4 (HDF5) is read; one cut after its signature is refused in one line.
        let h5 = dir.join("g.nc");
        std::fs::write(&h5, b"\x89HDF\r\n\x1a\n\0\0\0\0").unwrap();
        assert_eq!(sniff(&h5), Some(FileKind::NetCdf4));
        let e = load_netcdf(&h5, "density", &none, None).unwrap_err().to_string();
        assert!(
            e.contains("g.nc") && e.contains("not a readable NetCDF file") && e.contains("HDF5") && !e.contains('\n'),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
