#!/usr/bin/env python3
"""Where the reported variance misses the error, in time and by source. Reads a `fleet up` run
directory (its estimate.nc with the truth, mission.toml and plans.json) and prints, from a given
step on, error^2 / reported variance (means over cells, then their ratio):
- on the aerials' lattice and between it;
- per step of the boat cycle (0: a boat step), in the first and second half of the scored steps:
  a variance whose level does not follow the error's over time sorts its deciles by time;
- in the disks the boats sampled at the cycle's boat step against the other cells between the
  lattice: a boat's correction held in place while the field moves on.
Usage: python3 bench/where_the_variance_misses.py RUN_DIR [--from 24]"""
import argparse
import json
import os
import sys
import tomllib
import numpy as np
import xarray as xr


def bad(why):
    """Bad input: one line naming the file, exit 2."""
    print(f"where_the_variance_misses: {why}", file=sys.stderr)
    sys.exit(2)


def load(run):
    names = [("nc", "estimate.nc"), ("toml", "mission.toml"), ("plans", "plans.json")]
    paths = {k: os.path.join(run, f) for k, f in names}
    for p in paths.values():
        if not os.path.isfile(p):
            bad(f"{p}: no such file (a `fleet up --out DIR` run directory is expected)")
    try:
        ds = xr.open_dataset(paths["nc"])
    except Exception as e:  # xarray raises several kinds for a file that is not NetCDF
        bad(f"{paths['nc']}: cannot be read as NetCDF ({str(e).splitlines()[0]})")
    if "truth" not in ds:
        bad(f"{paths['nc']}: no truth variable (a run without a known truth cannot be scored)")
    try:
        with open(paths["toml"], "rb") as f:
            team = tomllib.load(f)["team"]
        stride, radius = int(team["aerial_stride"]), float(team["radius"])
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as e:
        bad(f"{paths['toml']}: no [team] aerial_stride and radius ({e})")
    try:
        with open(paths["plans"]) as f:
            plans = json.load(f)["plans"]
        disks = {}
        for p in plans:
            if p["kind"] == "boat":
                for _, step, xy, _ in p["targets"]:
                    disks.setdefault(int(step), []).append((float(xy[0]), float(xy[1])))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        bad(f"{paths['plans']}: not a run's plans ({e})")
    return ds, stride, radius, disks


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run")
    ap.add_argument("--from", dest="start", type=int, default=24, help="first step scored (default 24)")
    a = ap.parse_args()
    ds, stride, radius, disks = load(a.run)
    est, var, truth = (ds[v].values for v in ("estimate", "variance", "truth"))
    steps, (n_steps, rows, cols) = ds["step"].values.astype(int), est.shape
    err2 = (est - truth) ** 2
    lattice = np.zeros((rows, cols), bool)
    lattice[::stride, ::stride] = True
    scored = steps >= a.start
    everywhere = np.ones((rows, cols), bool)

    def ratio(when, where=everywhere):
        """Mean error^2 over mean variance at the steps `when` and the cells `where`."""
        return err2[when][:, where].mean() / var[when][:, where].mean()

    print(f"{a.run}, steps {a.start}-{steps.max()}: error^2 / variance {ratio(scored):.2f} overall, "
          f"{ratio(scored, lattice):.2f} on the aerials' lattice, {ratio(scored, ~lattice):.2f} between it")
    boat_steps = sorted(k for k in disks if k >= a.start)
    if len(boat_steps) < 2:
        bad(f"{a.run}: fewer than two boat steps from step {a.start}")
    period = boat_steps[1] - boat_steps[0]
    phase = (steps - boat_steps[0]) % period
    half = steps >= (a.start + steps.max()) / 2
    print(f"\n| step of the boat cycle | " + " | ".join(str(p) for p in range(period)) + " |")
    print("|---|" + "---|" * period)
    for name, h in [("first half", ~half), ("second half", half)]:
        cells = [ratio(scored & h & (phase == p)) for p in range(period)]
        print(f"| {name} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    ys, xs = ds["y"].values, ds["x"].values
    cell_m = float(xs[1] - xs[0]) if cols > 1 else 1.0
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    print("\n| step of the boat cycle | last disks: error^2 | variance | ratio "
          "| elsewhere between the lattice: error^2 | ratio |")
    print("|---|---|---|---|---|---|")
    for p in range(period):
        e_in, v_in, e_out, v_out = [], [], [], []
        for k0 in boat_steps:
            k = int(np.searchsorted(steps, k0 + p))
            if k >= n_steps or steps[k] != k0 + p:
                continue
            inside = np.zeros((rows, cols), bool)
            for x, y in disks[k0]:
                inside |= (xx - x) ** 2 + (yy - y) ** 2 <= (radius * cell_m) ** 2
            inside &= ~lattice
            other = ~inside & ~lattice
            e_in.append(err2[k][inside].mean()), v_in.append(var[k][inside].mean())
            e_out.append(err2[k][other].mean()), v_out.append(var[k][other].mean())
        if e_in:
            print(f"| {p} | {np.mean(e_in):.2e} | {np.mean(v_in):.2e} | {np.mean(e_in) / np.mean(v_in):.2f} | "
                  f"{np.mean(e_out):.2e} | {np.mean(e_out) / np.mean(v_out):.2f} |")


if __name__ == "__main__":
    main()
