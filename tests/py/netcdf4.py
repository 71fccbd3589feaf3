"""NetCDF-4 files as data centres publish them, written by netCDF4-python (tests/tests/netcdf4.rs).

write PATH: a NetCDF-4 (HDF5) file with the field in group `ocean` as `sst(time, lat, lon)`:
bytes marked `_Unsigned = "true"`, packed with scale_factor and add_offset, a _FillValue, zlib
with shuffle in chunks of (5, 10, 20); latitude and longitude in 32-bit floats over an
equatorial band (their spacings differ by about 1e-5 of a step once rounded); time in days of a
360_day calendar, the unlimited dimension, at the root. Frame 17 has no value at any cell.

write PATH uneven: the same with latitudes not evenly spaced (a Gaussian grid's kind): a site
cannot be placed from them.

write PATH unitless: the same with a time coordinate of 6-hourly steps without units (a storm
file's `timestep`): how long a step is is not in the file.

check PATH RUN: what a run wrote in RUN (`truth.npy`, `estimate.nc`) against xarray's decoding
of PATH: the truth to 1e-12, the cell centres to 1e-4 degrees. Prints one JSON line of what it
measured; exits 1 with the reason on a mismatch.
"""
import json
import os
import sys

import netCDF4
import numpy as np
import xarray as xr
from holes import fail, same_truth

T, ROWS, COLS = 30, 20, 40
EMPTY = 17


def field():
    t = np.arange(T)[:, None, None]
    r = np.arange(ROWS)[None, :, None]
    c = np.arange(COLS)[None, None, :]
    x = 26.0 + 2.0 * np.sin(2 * np.pi * (c - 0.6 * t) / 24.0) * np.cos(np.pi * r / 16.0)
    return x + 0.8 * np.exp(-((r - 6 - 0.2 * t) ** 2 + (c - 10 - 0.5 * t) ** 2) / 18.0)


def write(path, variant=None):
    with netCDF4.Dataset(path, "w", format="NETCDF4") as ds:
        ds.Conventions = "CF-1.8"
        g = ds.createGroup("ocean")
        ds.createDimension("time", None)
        g.createDimension("lat", ROWS)
        g.createDimension("lon", COLS)
        time = ds.createVariable("time", "f8", ("time",))
        time.units, time.calendar = "days since 2000-01-01", "360_day"
        time[:] = np.arange(T, dtype="f8")
        if variant == "unitless":
            time.delncattr("units")
            time.delncattr("calendar")
            time[:] = 6.0 * np.arange(T)
        lat = g.createVariable("lat", "f4", ("lat",))
        lat.units, lat.standard_name = "degrees_north", "latitude"
        lat[:] = np.linspace(-0.0095, 0.0095, ROWS).astype("f4")  # cells of 0.001 degrees (111 m)
        if variant == "uneven":
            lat[:] = (0.0095 * np.sin(np.linspace(-1.2, 1.2, ROWS)) / np.sin(1.2)).astype("f4")
        lon = g.createVariable("lon", "f4", ("lon",))
        lon.units = "degrees_east"
        lon[:] = (150.0005 + 0.001 * np.arange(COLS)).astype("f4")
        v = g.createVariable(
            "sst", "i1", ("time", "lat", "lon"), zlib=True, shuffle=True, chunksizes=(5, 10, 20), fill_value=np.int8(-1)
        )
        v.setncattr("_Unsigned", "true")
        v.scale_factor, v.add_offset, v.units = 0.05, 20.0, "degC"
        v.set_auto_maskandscale(False)
        raw = np.round((field() - 20.0) / 0.05).astype(np.int64)
        raw[3, 2:5, 2:5] = 255  # the fill, as unsigned: a patch of cloud
        raw[EMPTY] = 255  # a time with no value at all: a fully cloudy image
        assert raw.min() >= 0 and raw.max() <= 255
        v[:] = raw.astype(np.uint8).view(np.int8)


def check(path, run):
    sst = xr.open_dataset(path, group="ocean", decode_times=False).sst
    worst = same_truth(sst.values, run)
    # The frame with no value: nothing to score there (null in summary.json), every other step
    # scored; the estimate goes on through it.
    mse = json.load(open(f"{run}/summary.json"))["mse"]
    if mse[EMPTY] is not None or any(m is None for k, m in enumerate(mse) if k != EMPTY):
        fail(f"summary.json's per-step MSE is not null exactly at step {EMPTY}: {mse}")
    if not np.isfinite(np.load(f"{run}/estimate.npy")[EMPTY]).all():
        fail(f"the estimate at step {EMPTY} has a hole")
    est = xr.open_dataset(f"{run}/estimate.nc")
    lat_off = float(np.max(np.abs(est.lat.values - sst.lat.values.astype("f8"))))
    lon_off = float(np.max(np.abs(est.lon.values - sst.lon.values.astype("f8"))))
    if max(lat_off, lon_off) > 1e-4:
        fail(f"estimate.nc's cell centres are {lat_off:.2e} (lat) and {lon_off:.2e} (lon) degrees from the file's")
    # Time as the file says it: estimate.nc's steps are the file's dates in its 360_day calendar
    # (cftime decodes both), and the report names the first and last as cftime writes them.
    theirs = xr.open_dataset(path, use_cftime=True).time.values[: len(mse)]
    ours = est.time.values
    if list(ours) != list(theirs):
        fail(f"estimate.nc's times {ours[:3]}... are not the file's {theirs[:3]}...")
    report = open(f"{run}/report.md").read()
    said = f"step 0 is {theirs[0].strftime('%Y-%m-%d %H:%M:%S')} and step {len(mse) - 1} is " \
        f"{theirs[-1].strftime('%Y-%m-%d %H:%M:%S')}, in the `360_day` calendar"
    if said not in report:
        fail(f"the report does not say {said!r}")
    readings = f"{run}/readings.nc"
    if os.path.exists(readings):
        r = xr.open_dataset(readings, use_cftime=True)
        if not set(r.time.values) <= set(theirs):
            fail(f"readings.nc's times {r.time.values[:3]}... are not the file's dates")
    print(json.dumps({"truth_max_abs_diff": worst, "lat_off_deg": lat_off, "lon_off_deg": lon_off}))


if __name__ == "__main__":
    {"write": write, "check": check}[sys.argv[1]](*sys.argv[2:])
