"""A field with holes, written and checked the way xarray users would (tests/tests/holes.rs).

write PATH: a (time, depth, lat, lon) NetCDF-3 file through xarray: an island (missing in
every frame), a cloud over part of one frame, the values packed as shorts with scale_factor
and add_offset and a _FillValue, a singleton depth level, latitude stored north to south,
hourly CF time, units degC.

view PATH PORT: the live view's estimate (`/api/estimate.npy`) is NaN exactly on land.

check PATH RUN: what `fleet up` wrote in RUN against xarray's decoding of PATH (prints one
JSON line of what it measured; exits 1 with the reason on a mismatch).
"""
import json
import sys

import numpy as np
import xarray as xr

T, ROWS, COLS = 40, 24, 48
CLOUDY = 17


def field():
    t = np.arange(T)[:, None, None]
    r = np.arange(ROWS)[None, :, None]
    c = np.arange(COLS)[None, None, :]
    x = 12.0 + 2.0 * np.sin(2 * np.pi * (c - 0.6 * t) / 24.0) * np.cos(np.pi * r / 16.0)
    x = x + 0.8 * np.exp(-((r - 6 - 0.2 * t) ** 2 + (c - 10 - 0.5 * t) ** 2) / 18.0)
    land = (r - 12) ** 2 / 16.0 + (c - 30) ** 2 / 36.0 <= 1.0
    x = np.where(np.broadcast_to(land, x.shape), np.nan, x)
    x[CLOUDY, 2:8, 4:16] = np.nan
    return x


def write(path):
    x = field()
    lat = 45.0 + 0.0001 * np.arange(ROWS)  # cells of about 11 m: a bay a boat crosses in minutes
    ds = xr.Dataset(
        {"temp": (("time", "depth", "lat", "lon"), x[:, None, ::-1, :], {"units": "degC"})},
        coords={
            "time": ("time", np.arange(T, dtype="f8"), {"units": "hours since 2026-06-01 00:00:00"}),
            "depth": ("depth", [5.0], {"units": "m", "positive": "down"}),
            "lat": ("lat", lat[::-1], {"units": "degrees_north", "standard_name": "latitude"}),
            "lon": ("lon", -3.0 + 0.0001 * np.arange(COLS), {"units": "degrees_east"}),
        },
    )
    enc = {"temp": {"dtype": "int16", "scale_factor": 0.001, "add_offset": 12.0, "_FillValue": -32767}}
    ds.to_netcdf(path, format="NETCDF3_CLASSIC", engine="scipy", encoding=enc)


def fail(why):
    print(why)
    sys.exit(1)


def same_truth(truth, run):
    """RUN's `truth.npy` against `truth` (xarray's decoding): the same shape, missing at the same
    cells, the values to 1e-12; the largest difference."""
    ours = np.load(f"{run}/truth.npy")
    if ours.shape != truth.shape:
        fail(f"truth.npy has shape {ours.shape}, xarray {truth.shape}")
    if not np.array_equal(np.isnan(ours), np.isnan(truth)):
        fail("truth.npy is missing other cells than xarray")
    worst = float(np.nanmax(np.abs(ours - truth)))
    if worst > 1e-12:
        fail(f"truth.npy differs from xarray's decoding by {worst}")
    return worst


def check(path, run):
    # xarray's decoding, south to north, the level selected.
    truth = xr.open_dataset(path).temp.sel(depth=5.0).sortby("lat").values
    worst = same_truth(truth, run)
    land = np.isnan(truth).all(axis=0)
    est = np.load(f"{run}/estimate.npy")
    steps = est.shape[0]
    if not (np.isnan(est[:, land]).all() and np.isfinite(est[:, ~land]).all()):
        fail("estimate.npy is not NaN exactly on land")
    # MSE over the cells with a truth, per step, against the server's.
    summary = json.load(open(f"{run}/summary.json"))
    theirs = np.array(summary["mse"][:steps])
    mine = np.nanmean((est - truth[:steps]) ** 2, axis=(1, 2))
    rel = float(np.max(np.abs(theirs - mine) / mine))
    if rel > 1e-12:
        fail(f"per-step MSE differs from numpy's by {rel} (relative)")
    # No boat target on land (a disk may reach the coast: its land cells are not measured).
    plans = json.load(open(f"{run}/plans.json"))["plans"]
    flat_land = set(np.flatnonzero(land.reshape(-1)).tolist())
    targets = 0
    for p in plans:
        if p["kind"] != "boat":
            continue
        for (_epoch, _step, pos, radius) in p["targets"]:
            row, col = int(pos[1]), int(pos[0])
            targets += 1
            if row * COLS + col in flat_land:
                fail(f"a boat target at {pos} (radius {radius}) is on land")
    # estimate.nc: xarray sees the fill value as missing, on land only.
    nc = xr.open_dataset(f"{run}/estimate.nc")
    e = nc.estimate.values
    if not (np.isnan(e[:, land]).all() and np.isfinite(e[:, ~land]).all()):
        fail("estimate.nc is not missing exactly on land")
    # The site placed by the file's latitude and longitude (the mission gives no origin).
    src = xr.open_dataset(path)
    for ours, theirs in ((nc.lat.values, np.sort(src.lat.values)), (nc.lon.values, src.lon.values)):
        if np.max(np.abs(ours - theirs)) > 1e-6:
            fail(f"estimate.nc's cell centres {ours[:3]}... are not the file's {theirs[:3]}...")
    units = nc.estimate.attrs.get("units")
    if units != "degC":
        fail(f"estimate.nc says units {units!r}, the file degC")
    print(json.dumps({"land_cells": int(land.sum()), "steps": steps, "worst_truth": worst,
                      "mse_rel": rel, "boat_targets": targets}))


def view(path, port):
    import io
    import urllib.request

    land = np.isnan(xr.open_dataset(path).temp.sel(depth=5.0).sortby("lat").values).all(axis=0)
    est = np.load(io.BytesIO(urllib.request.urlopen(f"http://127.0.0.1:{port}/api/estimate.npy").read()))
    est = est.reshape(land.shape)
    if not (np.isnan(est[land]).all() and np.isfinite(est[~land]).all()):
        fail("the live view's estimate is not NaN exactly on land")
    print(json.dumps({"view_land_cells": int(land.sum())}))


if __name__ == "__main__":
    {
        "write": lambda: write(sys.argv[2]),
        "check": lambda: check(sys.argv[2], sys.argv[3]),
        "view": lambda: view(sys.argv[2], sys.argv[3]),
    }[sys.argv[1]]()
