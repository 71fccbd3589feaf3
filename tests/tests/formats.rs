//! What a run leaves, opened by the tools field teams use: xarray reads `estimate.nc`, GDAL
//! places the GeoTIFFs on the site, QGroundControl's plan schema holds the boats' places, and
//! the Python `mcap` package reads the recording.

use hetfleet_tests::{free_port, root, run, scratch, tiny_mission};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Off the default site and in the southern and eastern hemispheres, on a physical extent
/// other than the grid's metres, so a swapped or unscaled axis shows.
const ORIGIN: [f64; 3] = [-33.8568, 151.2153, 12.0];
const SIZE_M: [f64; 2] = [450.0, 300.0];

/// A finished tiny mission on that site (`fleet up`), its run directory.
fn finished_run(dir: &Path) -> PathBuf {
    let port = free_port();
    let ep = vec![format!("tcp/127.0.0.1:{port}")];
    let mission = tiny_mission(dir, &ep, &ep);
    let text = std::fs::read_to_string(&mission).unwrap();
    let site = format!(
        "origin = [{}, {}, {}]\nsize_m = [{}, {}]\n",
        ORIGIN[0], ORIGIN[1], ORIGIN[2], SIZE_M[0], SIZE_M[1]
    );
    std::fs::write(&mission, text.replace("[mavlink]\n", &format!("[mavlink]\n{site}"))).unwrap();
    let out = dir.join("run");
    let o = run(
        "fleet",
        &["up", mission.to_str().unwrap(), "--out", out.to_str().unwrap()],
    );
    assert!(
        o.status.success(),
        "fleet up failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

fn python(script: &str) -> String {
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .current_dir(root())
        .output()
        .expect("python3");
    assert!(
        o.status.success(),
        "python failed:\n{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The site's corners as the mission defines them, computed here on their own (spherical
/// Earth of the WGS-84 equatorial radius, flat over the site), as `[west, south, east, north]`.
const CORNERS_PY: &str = "
import math
R = 6378137.0
lat0, lon0 = ORIGIN_LAT, ORIGIN_LON
west, south = lon0, lat0
north = lat0 + math.degrees(SIZE_N / R)
east = lon0 + math.degrees(SIZE_E / (R * math.cos(math.radians(lat0))))
";

fn corners_py() -> String {
    CORNERS_PY
        .replace("ORIGIN_LAT", &ORIGIN[0].to_string())
        .replace("ORIGIN_LON", &ORIGIN[1].to_string())
        .replace("SIZE_N", &SIZE_M[1].to_string())
        .replace("SIZE_E", &SIZE_M[0].to_string())
}

#[test]
fn xarray_gdal_and_qgc_read_what_a_run_leaves() {
    let dir = scratch("formats");
    let out = finished_run(&dir);

    // NetCDF: xarray reads the dims, coordinates, units and the run's own values; the per-step
    // error of `estimate` against `truth` is the MSE the server reported.
    let nc = out.join("estimate.nc");
    let said = python(&format!(
        "{corners}
import json, numpy as np, xarray as xr
ds = xr.open_dataset({nc:?})
run = {out:?}
assert ds.estimate.dims == ('time', 'y', 'x'), ds.estimate.dims
assert dict(ds.sizes) == {{'time': 40, 'y': 24, 'x': 48}}, dict(ds.sizes)
for name in ('lat', 'lon', 'time', 'x', 'y'):
    assert name in ds.coords, (name, list(ds.coords))
assert ds.lat.dims == ('y',) and ds.lon.dims == ('x',)
assert ds.lat.attrs['units'] == 'degrees_north' and ds.lon.attrs['units'] == 'degrees_east'
assert ds.x.attrs['units'] == 'm' and ds.y.attrs['units'] == 'm' and ds.time.attrs['units'] == 's'
assert ds.attrs['Conventions'] == 'CF-1.8, ACDD-1.3' and ds.attrs['mission'] == 'tiny' and ds.attrs['seed'] == '5'
assert ds.attrs['fusion'] and ds.attrs['placement']
for v in ('estimate', 'variance', 'truth'):
    assert ds[v].attrs['long_name'] and 'units' in ds[v].attrs, v
# NetCDF-4, compressed; the estimate and its variance single precision (each value within half a
# float32 ulp, 2^-24 of itself, of the server's double), the truth double and exact.
import netCDF4
with netCDF4.Dataset({nc:?}) as raw:
    assert raw.data_model == 'NETCDF4', raw.data_model
    for v in ('estimate', 'variance', 'truth'):
        f = raw[v].filters()
        assert f['zlib'] and f['shuffle'] and raw[v].chunking() == [1, 24, 48], (v, f, raw[v].chunking())
    assert raw['estimate'].dtype == np.float32 and raw['truth'].dtype == np.float64
est64, var64 = np.load(run + '/estimate.npy'), np.load(run + '/variance.npy')
for got, want in ((ds.estimate.values, est64), (ds.variance.values, var64)):
    assert got.dtype == np.float32 and np.array_equal(np.isnan(got), np.isnan(want))
    assert np.nanmax(np.abs(got - want) / np.abs(want)) <= 2.0 ** -24, np.nanmax(np.abs(got - want) / np.abs(want))
assert np.array_equal(ds.truth.values, np.load(run + '/truth.npy')[:40])
# cell centres: half a cell in from the site's edges
dlat, dlon = (north - south) / 24, (east - west) / 48
assert abs(ds.lat.values[0] - (south + dlat / 2)) < 1e-9 and abs(ds.lat.values[-1] - (north - dlat / 2)) < 1e-9, ds.lat.values[[0, -1]]
assert abs(ds.lon.values[0] - (west + dlon / 2)) < 1e-9 and abs(ds.lon.values[-1] - (east - dlon / 2)) < 1e-9, ds.lon.values[[0, -1]]
assert abs(ds.x.values[-1] - ({e} - {e} / 96)) < 1e-9 and abs(ds.y.values[-1] - ({n} - {n} / 48)) < 1e-9
# The server's per-step MSE, from the file: rounding the estimate e by d (|d| <= 2^-24 |e|) moves
# (e - t)^2 by at most 2|d||e - t| + d^2, which bounds the difference of the means.
mse = np.array(json.load(open(run + '/summary.json'))['mse'])
e, t = ds.estimate.values.astype(float)[:len(mse)], ds.truth.values[:len(mse)]
err = ((e - t) ** 2).mean(axis=(1, 2))
d = 2.0 ** -24 * np.abs(est64[:len(mse)])
bound = (2 * d * np.abs(est64[:len(mse)] - t) + d ** 2).mean(axis=(1, 2))
assert (np.abs(err - mse) <= bound + 1e-12 * mse).all(), (err[:5], mse[:5], bound[:5])
print('ok', len(mse))
",
        corners = corners_py(),
        e = SIZE_M[0],
        n = SIZE_M[1],
    ));
    assert!(said.starts_with("ok"), "{said}");

    // The boats' readings: a CF trajectory file xarray and cf_xarray open (its featureType, the
    // trajectory ids, the coordinates, the flag); each value at a cell centre of the estimate's
    // grid, at its step, within 5 of its sigmas of the truth there.
    let said = python(&format!(
        "import numpy as np, xarray as xr, cf_xarray
ds = xr.open_dataset({readings:?})
est = xr.open_dataset({nc:?})
truth = np.load({out:?} + '/truth.npy')
assert ds.attrs['featureType'] == 'trajectory' and ds.attrs['Conventions'] == 'CF-1.8, ACDD-1.3'
assert ds.cf.cf_roles == {{'trajectory_id': ['vehicle']}}, ds.cf.cf_roles
ids = [t.decode() if isinstance(t, bytes) else str(t) for t in ds.vehicle.values]
assert ids == ['boat-1', 'boat-2', 'boat-3'], ids
assert ds.rowSize.attrs['sample_dimension'] == 'obs' and int(ds.rowSize.sum()) == ds.sizes['obs'] > 0
for key, name in (('latitude', 'lat'), ('longitude', 'lon'), ('time', 'time')):
    assert ds.cf[key].name == name, (key, ds.cf[key].name)
assert ds.flag.cf.is_flag_variable and (ds.flag.cf == 'ok').all(), ds.flag.attrs
rows = np.searchsorted(est.lat.values, ds.lat.values)
cols = np.searchsorted(est.lon.values, ds.lon.values)
assert np.allclose(est.lat.values[rows], ds.lat.values, rtol=0, atol=1e-12) and np.allclose(est.lon.values[cols], ds.lon.values, rtol=0, atol=1e-12)
steps = ds.step.values
assert np.array_equal(ds.time.values, steps.astype(float) * float(est.time.values[1] - est.time.values[0]))
z = (ds.value.values - truth[steps, rows, cols]) / ds.sigma.values
assert (ds.sigma.values > 0).all() and np.abs(z).max() < 5, np.abs(z).max()
print('ok', ds.sizes['obs'])
",
        readings = out.join("readings.nc"),
    ));
    assert!(said.starts_with("ok"), "{said}");

    // GeoTIFF: GDAL finds WGS 84 and the site's corners within 1e-6 degrees; the band is the
    // final estimate, north up.
    let geo = dir.join("geo");
    let o = run(
        "fleet",
        &["export", out.to_str().unwrap(), "--geotiff", geo.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for name in ["estimate", "variance"] {
        let tif = geo.join(format!("{name}.tif"));
        let info = Command::new("gdalinfo")
            .arg("-json")
            .arg(&tif)
            .output()
            .expect("gdalinfo (Debian gdal-bin; scripts/test.sh installs it)");
        assert!(
            info.status.success(),
            "gdalinfo: {}",
            String::from_utf8_lossy(&info.stderr)
        );
        let info_path = dir.join(format!("{name}.json"));
        std::fs::write(&info_path, &info.stdout).unwrap();
        let said = python(&format!(
            "{corners}
import json, numpy as np
info = json.load(open({info_path:?}))
c = info['cornerCoordinates']
want = {{'upperLeft': [west, north], 'lowerLeft': [west, south], 'upperRight': [east, north], 'lowerRight': [east, south]}}
for k, (lon, lat) in want.items():
    assert abs(c[k][0] - lon) < 1e-6 and abs(c[k][1] - lat) < 1e-6, (k, c[k], (lon, lat))
wkt = info['coordinateSystem']['wkt']
assert 'WGS 84' in wkt and '4326' in wkt, wkt[:200]
assert info['size'] == [48, 24] and info['bands'][0]['type'] == 'Float64', (info['size'], info['bands'][0]['type'])
nodata = info['bands'][0].get('noDataValue')
assert isinstance(nodata, str) and nodata.lower() == 'nan' or nodata != nodata, ('no-data', nodata)
print('ok')
",
            corners = corners_py(),
        ));
        assert!(said.starts_with("ok"), "{name}: {said}");
    }
    // The pixels themselves, through GDAL's own reader (gdal_translate to an ASCII grid).
    let asc = dir.join("estimate.asc");
    let t = Command::new("gdal_translate")
        .args(["-q", "-of", "AAIGrid"])
        .arg(geo.join("estimate.tif"))
        .arg(&asc)
        .output()
        .expect("gdal_translate");
    assert!(t.status.success(), "{}", String::from_utf8_lossy(&t.stderr));
    let said = python(&format!(
        "import numpy as np
rows = [l.split() for l in open({asc:?}) if not l[:1].isalpha()]
a = np.array([[float(v) for v in r] for r in rows])
want = np.load({est:?})[-1][::-1]
assert a.shape == want.shape and np.allclose(a, want, rtol=1e-12, atol=1e-15), (a.shape, abs(a - want).max())
print('ok')
",
        est = out.join("estimate.npy"),
    ));
    assert!(said.starts_with("ok"), "{said}");

    // QGroundControl plans: one per boat, QGC's schema fields, a waypoint at each planned
    // sensing place of the plans published last, inside the site's fence.
    let plan = dir.join("next.plan");
    let o = run(
        "fleet",
        &["export", out.to_str().unwrap(), "--qgc-plan", plan.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let said = python(&format!(
        "{corners}
import json, math
plans = json.load(open({plans:?}))
last = max(p['epoch'] for p in plans['plans'])
boats = [p for p in plans['plans'] if p['epoch'] == last and p['kind'] == 'boat']
assert len(boats) == 3, boats
for b in boats:
    doc = json.load(open({dir:?} + '/next.' + b['vehicle'] + '.plan'))
    assert doc['fileType'] == 'Plan' and doc['groundStation'] == 'QGroundControl' and doc['version'] == 1
    m = doc['mission']
    assert m['version'] == 2 and len(m['plannedHomePosition']) == 3
    places = [t[2] for t in b['targets'] if t[3] > 0]
    assert len(m['items']) == len(places) > 0, (len(m['items']), places)
    for item, (x, y) in zip(m['items'], places):
        assert item['type'] == 'SimpleItem' and item['command'] == 16 and item['frame'] == 3
        lat, lon = item['params'][4], item['params'][5]
        assert abs(lat - (south + (north - south) * y / 24)) < 1e-9 and abs(lon - (west + (east - west) * x / 48)) < 1e-9, (lat, lon, x, y)
        assert south < lat < north and west < lon < east
    fence = doc['geoFence']['polygons'][0]
    assert fence['inclusion'] and len(fence['polygon']) == 4
print('ok')
",
        corners = corners_py(),
        plans = out.join("plans.json"),
        dir = dir,
    ));
    assert!(said.starts_with("ok"), "{said}");

    // MCAP: the Python `mcap` package reads the recording; it holds every batch the server
    // counted (this run has no restart, so every one arrived on a measurements channel) and the
    // core's operations, the first in step with the models published.
    let said = python(&format!(
        "import json
from mcap.reader import make_reader
summary = json.load(open({summary:?}))
topics, ops, models = {{}}, 0, 0
with open({rec:?}, 'rb') as f:
    r = make_reader(f)
    header = {{m.name: m.metadata for m in r.iter_metadata()}}
    for schema, channel, message in r.iter_messages():
        topics[channel.topic] = topics.get(channel.topic, 0) + 1
        assert message.log_time > 1.7e18, message.log_time
assert 'hetfleet' in header and int(header['hetfleet']['rows']) == 24, header.keys()
batches = sum(n for t, n in topics.items() if t.endswith('/measurements'))
assert batches == summary['counters']['batches'], (batches, summary['counters'])
assert topics.get('server/core', 0) >= batches, topics
# A lean recording (the default) keeps one model in 50 and the last.
v = summary['model_version']
assert sum(n for t, n in topics.items() if t.endswith('/model/latest')) == v // 50 + (v % 50 != 0), topics
assert any(t.endswith('/telemetry') for t in topics) and any('/plan/' in t for t in topics) and any(t.endswith('/ack') for t in topics), sorted(topics)
assert topics['server/events'] >= summary['epochs'], topics
print('ok', batches)
",
        summary = out.join("summary.json"),
        rec = out.join("recording.mcap"),
    ));
    assert!(said.starts_with("ok"), "{said}");

    // Foxglove: every /foxglove channel decodes with Foxglove's published schemas (protobuf) or
    // its own JSON schema; each LocationFix is where its telemetry says, on this site; each
    // Grid is estimate.nc at its model's step.
    let o = Command::new("python3")
        .arg("tests/py/foxglove_check.py")
        .arg(out.join("recording.mcap"))
        .arg(out.join("estimate.nc"))
        .args([ORIGIN[0], ORIGIN[1], SIZE_M[0], SIZE_M[1]].map(|v| v.to_string()))
        .current_dir(root())
        .output()
        .expect("python3");
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{said}{}", String::from_utf8_lossy(&o.stderr));
    assert!(said.contains("\"vehicles\""), "{said}");

    // On mission time ([time]), the NetCDF's time axis is CF time that xarray decodes to UTC
    // datetimes, and the GeoTIFF's DateTime is when the last step began (GDAL's
    // TIFFTAG_DATETIME).
    let timed = dir.join("timed");
    std::fs::create_dir_all(&timed).unwrap();
    for f in [
        "summary.json",
        "estimate.npy",
        "variance.npy",
        "truth.npy",
        "plans.json",
    ] {
        std::fs::copy(out.join(f), timed.join(f)).unwrap();
    }
    std::fs::create_dir_all(timed.join("state")).unwrap();
    std::fs::copy(out.join("state/tiny.redb"), timed.join("state/tiny.redb")).unwrap();
    let mission = std::fs::read_to_string(out.join("mission.toml")).unwrap();
    let clock = "\n[time]\nstart = \"2026-11-25T09:00:00Z\"\nstep_s = 60.0\n";
    std::fs::write(timed.join("mission.toml"), format!("{mission}{clock}")).unwrap();
    let (nc, geo, readings) = (
        dir.join("timed.nc"),
        dir.join("timed-geo"),
        dir.join("timed-readings.nc"),
    );
    let o = run(
        "fleet",
        &[
            "export",
            timed.to_str().unwrap(),
            "--netcdf",
            nc.to_str().unwrap(),
            "--geotiff",
            geo.to_str().unwrap(),
            "--readings",
            readings.to_str().unwrap(),
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let info = Command::new("gdalinfo")
        .arg("-json")
        .arg(geo.join("estimate.tif"))
        .output()
        .unwrap();
    std::fs::write(dir.join("timed-info.json"), &info.stdout).unwrap();
    let said = python(&format!(
        "import json, numpy as np, xarray as xr
ds = xr.open_dataset({nc:?})
assert np.issubdtype(ds.time.dtype, np.datetime64), ds.time.dtype
want = np.datetime64('2026-11-25T09:00:00') + np.arange(40) * np.timedelta64(60, 's')
assert (ds.time.values == want).all(), ds.time.values[:3]
md = json.load(open({info:?}))['metadata']['']
assert md['TIFFTAG_DATETIME'] == '2026:11:25 09:39:00', md
assert '2026-11-25T09:39:00Z' in md['TIFFTAG_IMAGEDESCRIPTION'], md
# The IOOS compliance checker, as a data centre runs it: no high-priority failure of CF-1.8;
# of ACDD-1.3 only the standard_name a simulated field does not have (CF names no variance).
from compliance_checker.runner import ComplianceChecker, CheckSuite
CheckSuite.load_all_available_checkers()
ComplianceChecker.run_checker({nc:?}, ['cf:1.8', 'acdd:1.3'], 0, 'normal', output_filename={cc:?}, output_format='json')
report = json.load(open({cc:?}))
failed = {{k: [(h['name'], h.get('msgs')) for h in v['high_priorities'] if h['value'][0] != h['value'][1]] for k, v in report.items()}}
assert failed['cf:1.8'] == [], failed
assert all(m == ['standard_name'] for _, m in failed['acdd:1.3']) and len(failed['acdd:1.3']) == 3, failed
assert ds.attrs['Conventions'] == 'CF-1.8, ACDD-1.3' and ds.estimate.attrs['coverage_content_type'] == 'modelResult'
# The trajectory file: CF-1.8's discrete sampling geometry as the checker judges it, its time UTC.
ComplianceChecker.run_checker({readings:?}, ['cf:1.8'], 0, 'normal', output_filename={rcc:?}, output_format='json')
report = json.load(open({rcc:?}))
failed = [(h['name'], h.get('msgs')) for h in report['cf:1.8']['high_priorities'] if h['value'][0] != h['value'][1]]
assert failed == [], failed
r = xr.open_dataset({readings:?})
assert (r.time.values == np.datetime64('2026-11-25T09:00:00') + r.step.values * np.timedelta64(60, 's')).all()
print('ok')
",
        info = dir.join("timed-info.json"),
        cc = dir.join("timed-compliance.json"),
        rcc = dir.join("timed-readings-compliance.json"),
    ));
    assert!(said.starts_with("ok"), "{said}");

    // A damaged run: each damaged file is named on one line, exit 2, and nothing half written.
    let damaged = dir.join("damaged");
    std::fs::create_dir_all(&damaged).unwrap();
    for f in [
        "mission.toml",
        "summary.json",
        "estimate.npy",
        "variance.npy",
        "truth.npy",
        "plans.json",
    ] {
        std::fs::copy(out.join(f), damaged.join(f)).unwrap();
    }
    let est = std::fs::read(damaged.join("estimate.npy")).unwrap();
    std::fs::write(damaged.join("estimate.npy"), &est[..est.len() / 2]).unwrap();
    let nc = dir.join("damaged.nc");
    let o = run(
        "fleet",
        &["export", damaged.to_str().unwrap(), "--netcdf", nc.to_str().unwrap()],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("estimate.npy") && err.trim().lines().count() == 1, "{err}");
    assert!(!nc.exists() && !dir.join("damaged.nc.partial").exists());
    std::fs::write(damaged.join("estimate.npy"), &est).unwrap();
    std::fs::write(damaged.join("plans.json"), b"{\"horizon\": 2, \"plans\": [").unwrap();
    let o = run(
        "fleet",
        &[
            "export",
            damaged.to_str().unwrap(),
            "--qgc-plan",
            dir.join("d.plan").to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("plans.json") && err.trim().lines().count() == 1, "{err}");
    // A damaged recording stops only what needs it (the plans' fence), not the fields.
    std::fs::copy(out.join("plans.json"), damaged.join("plans.json")).unwrap();
    std::fs::write(damaged.join("recording.mcap"), b"\x89MCAP0\r\ncut").unwrap();
    let o = run(
        "fleet",
        &["export", damaged.to_str().unwrap(), "--netcdf", nc.to_str().unwrap()],
    );
    assert!(
        o.status.success() && nc.exists(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let o = run(
        "fleet",
        &[
            "export",
            damaged.to_str().unwrap(),
            "--qgc-plan",
            dir.join("d.plan").to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("recording.mcap") && err.trim().lines().count() == 1,
        "{err}"
    );
    a_run_that_stopped_exports_the_steps_it_made(&out, &dir);
}

/// A server stopped mid-mission leaves its steps in the `.part` files (written with the
/// server's own [`StepFile`]), and no summary; stopped between its two files' writes, the
/// variance has one step more. `fleet export` writes the steps both hold, each the run's own
/// value, says so, and refuses the readings (whose flags only the summary holds) in one line.
fn a_run_that_stopped_exports_the_steps_it_made(out: &Path, dir: &Path) {
    use fleet_mission::step_file::StepFile;
    let stopped = dir.join("stopped");
    std::fs::create_dir_all(stopped.join("state")).unwrap();
    for f in ["mission.toml", "truth.npy", "plans.json", "state/tiny.redb"] {
        std::fs::copy(out.join(f), stopped.join(f)).unwrap();
    }
    let (made, cells) = (17, 24 * 48);
    for (name, steps) in [("estimate", made), ("variance", made + 1)] {
        let whole = fleet_math::npy::read(out.join(format!("{name}.npy"))).unwrap();
        let mut part = StepFile::create(stopped.join(format!("{name}.npy.part")), 24, 48).unwrap();
        for k in 0..steps {
            part.append(whole.data[k * cells..(k + 1) * cells].iter().copied())
                .unwrap();
        }
    }
    let nc = dir.join("stopped.nc");
    let o = run(
        "fleet",
        &["export", stopped.to_str().unwrap(), "--netcdf", nc.to_str().unwrap()],
    );
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        said.contains("stopped before the mission's end") && said.contains("the 17 steps"),
        "{said}"
    );
    let said = python(&format!(
        "import numpy as np, xarray as xr
ds = xr.open_dataset({nc:?})
assert ds.sizes['time'] == 17 and 'stopped before' in ds.attrs['summary'], (dict(ds.sizes), ds.attrs['summary'])
want = np.load({out:?} + '/estimate.npy')[:17]
assert np.array_equal(ds.estimate.values, want.astype(np.float32), equal_nan=True)
print('ok')
"
    ));
    assert!(said.starts_with("ok"), "{said}");
    let readings = dir.join("stopped-readings.nc");
    let o = run(
        "fleet",
        &[
            "export",
            stopped.to_str().unwrap(),
            "--readings",
            readings.to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("quality flags") && err.trim().lines().count() == 1,
        "{err}"
    );
    assert!(!readings.exists());
}

#[test]
fn a_directory_that_is_not_a_finished_run_is_one_clear_line_and_exit_2() {
    let dir = scratch("formats-bad");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let nc = dir.join("x.nc");
    let o = run(
        "fleet",
        &["export", empty.to_str().unwrap(), "--netcdf", nc.to_str().unwrap()],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("not a finished run directory: it has no mission.toml") && err.trim().lines().count() == 1,
        "{err}"
    );
    assert!(!nc.exists());
    let o = run("fleet", &["export", empty.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("nothing to export"));
}

/// A camera frame GDAL wrote (`gdal_translate` from an ASCII grid, Float32, with no-data) in
/// geographic WGS 84 and in UTM zones north and south of the equator: hetfleet reads each
/// pixel where GDAL and PROJ (`gdaltransform`) put it. The pixel centres' WGS 84 positions
/// come from `gdaltransform`, not from our own UTM code, so a wrong zone, hemisphere, axis or
/// half-pixel shift shows.
#[test]
fn frames_gdal_writes_are_read_where_gdal_puts_them() {
    let dir = scratch("gdal-frames");
    // (EPSG, west, north, pixel size): Sydney's UTM zone 56 south, Copenhagen's 33 north.
    let cases = [
        (4326, 151.2, -33.85, 0.001),
        (32756, 334_000.0, 6_253_000.0, 25.0),
        (32633, 347_000.0, 6_174_000.0, 25.0),
    ];
    let (cols, rows) = (5usize, 4usize);
    for (epsg, west, north, px) in cases {
        let values: Vec<f64> = (0..rows * cols).map(|i| 10.0 + i as f64).collect();
        let mut asc = format!(
            "ncols {cols}\nnrows {rows}\nxllcorner {west}\nyllcorner {}\ncellsize {px}\nNODATA_value -9999\n",
            north - rows as f64 * px
        );
        for r in 0..rows {
            let row: Vec<String> = (0..cols)
                .map(|c| {
                    if (r, c) == (1, 2) {
                        "-9999".into()
                    } else {
                        values[r * cols + c].to_string()
                    }
                })
                .collect();
            asc.push_str(&(row.join(" ") + "\n"));
        }
        let (a, tif) = (dir.join(format!("{epsg}.asc")), dir.join(format!("{epsg}.tif")));
        std::fs::write(&a, asc).unwrap();
        let o = Command::new("gdal_translate")
            .args([
                "-q",
                "-of",
                "GTiff",
                "-ot",
                "Float32",
                "-a_srs",
                &format!("EPSG:{epsg}"),
            ])
            .args([a.to_str().unwrap(), tif.to_str().unwrap()])
            .output()
            .expect("gdal_translate (Debian gdal-bin; scripts/test.sh installs it)");
        assert!(
            o.status.success(),
            "gdal_translate: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let frame = fleet_mission::instrument::raster::decode(&std::fs::read(&tif).unwrap()).unwrap();
        // Every pixel centre, to WGS 84 by PROJ.
        let centres: String = (0..rows * cols)
            .map(|i| {
                let (r, c) = (i / cols, i % cols);
                format!("{} {}\n", west + (c as f64 + 0.5) * px, north - (r as f64 + 0.5) * px)
            })
            .collect();
        let mut t = Command::new("gdaltransform")
            .args(["-s_srs", &format!("EPSG:{epsg}"), "-t_srs", "EPSG:4326", "-output_xy"])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("gdaltransform");
        use std::io::Write;
        t.stdin.take().unwrap().write_all(centres.as_bytes()).unwrap();
        let out = String::from_utf8(t.wait_with_output().unwrap().stdout).unwrap();
        for (i, line) in out.lines().enumerate() {
            let xy: Vec<f64> = line.split_whitespace().map(|v| v.parse().unwrap()).collect();
            // gdaltransform to EPSG:4326 with -output_xy: longitude then latitude.
            let got = frame.at(xy[1], xy[0]);
            let want = (i != cols + 2).then_some(values[i]);
            assert_eq!(got, want, "EPSG:{epsg} pixel {i}");
        }
    }
}
