#!/usr/bin/env python3
"""Is the reported uncertainty where the error is? Reads a run's estimate.nc (`fleet up`'s, or
`fleet export`'s) and prints, from a given step on, the squared error of the fused estimate
against the truth in deciles of the reported variance and in deciles of the estimate's squared
gradient |grad x|^2 (a displacement error of an advected front is about delta . grad x), with the
per-step correlation of each with the squared error. Calibration on average (error^2 / variance
near 1 overall) says nothing about this: placement by uncertainty needs the variance to be high
where the error is. Usage: python3 bench/where_is_the_error.py RUN/estimate.nc [--from 24]"""
import argparse
import os
import sys
import numpy as np
import xarray as xr


def bad(why):
    """Bad input: one line naming the file, exit 2."""
    print(f"where_is_the_error: {why}", file=sys.stderr)
    sys.exit(2)


def deciles(key, err2, var, name):
    edges = np.quantile(key, np.linspace(0, 1, 11))
    print(f"\n| {name} decile | mean {name} | mean error^2 | mean reported variance | error^2 / variance |")
    print("|---|---|---|---|---|")
    for i in range(10):
        m = (key >= edges[i]) & (key <= edges[i + 1])
        print(f"| {i + 1} | {key[m].mean():.2e} | {err2[m].mean():.2e} | {var[m].mean():.2e} | {err2[m].mean() / var[m].mean():.2f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("netcdf")
    ap.add_argument("--from", dest="start", type=int, default=24, help="first step scored (default 24: the default mission's first boat sample)")
    a = ap.parse_args()
    if not os.path.isfile(a.netcdf):
        bad(f"{a.netcdf}: no such file")
    try:
        ds = xr.open_dataset(a.netcdf)
    except Exception as e:  # xarray raises several kinds for a file that is not NetCDF
        bad(f"{a.netcdf}: cannot be read as NetCDF ({str(e).splitlines()[0]})")
    if "truth" not in ds:
        bad(f"{a.netcdf}: no truth variable (a run without a known truth cannot be scored)")
    est, var, truth = (ds[v].values[a.start:] for v in ("estimate", "variance", "truth"))
    err2 = (est - truth) ** 2
    gy, gx = np.gradient(est, axis=(1, 2))
    grad2 = gx**2 + gy**2
    corr = lambda x: np.mean([np.corrcoef(x[k].ravel(), err2[k].ravel())[0, 1] for k in range(len(est))])
    print(f"{a.netcdf}, steps {a.start}-{a.start + len(est) - 1}: mean error^2 {err2.mean():.3e}, mean reported variance {var.mean():.3e}, mean error^2 / variance {(err2 / var).mean():.3f}")
    print(f"per-step correlation with error^2 over the cells: reported variance {corr(var):+.3f}, squared gradient {corr(grad2):+.3f}")
    deciles(var.ravel(), err2.ravel(), var.ravel(), "variance")
    deciles(grad2.ravel(), err2.ravel(), var.ravel(), "squared gradient")


if __name__ == "__main__":
    main()
