"""Readings from outside instruments against the simulated sensors (issue 34), paired by seed.

usage: python3 bench/instruments.py [--seeds 10] [--step-s 1.0] [--out DIR]

For each seed, the tiny mission (its `[team] seed` set, so the truth is the seed's) runs three
times on the clock (`[time]`, steps of `--step-s`) with `fleet up`, all runs at once on their
own ports:
  - `sim`: every vehicle senses the truth itself (the simulated sensors);
  - `udp`: every boat reads a UDP sensor port, fed by `instrument_emulator` (a separate process
    that hears where each boat really is from the ground-station stream and sends the readings
    a disk instrument there takes of the same truth, with the mission's boat noise); the
    aerials as in `sim` (the same noise);
  - `all`: the boats as in `udp`, and every aerial reads a directory of GeoTIFF frames the
    emulator writes (the truth over the site, one pixel per cell, with the aerial's noise at
    each cell's distance from where the aerial really is).
Each differs from `sim` only in noise draws and in where the vehicles really were. Prints the
mean of each run's per-step MSE, the paired differences (arm - sim) and their mean with a 95%
t-interval, as one JSON object. Not a test: nothing is asserted.
"""
import argparse
import datetime
import json
import os
import socket
import statistics
import subprocess
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
T975 = {9: 2.262, 10: 2.228, 11: 2.201, 12: 2.179, 14: 2.145, 19: 2.093, 29: 2.045}


def free_port(kind=socket.SOCK_STREAM):
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mission(path, seed, start, step_s, boat_ports, frame_dirs):
    text = open(os.path.join(ROOT, "config/mission-tiny.toml")).read()
    ep = f"tcp/127.0.0.1:{free_port()}"
    text = text.replace("tcp/127.0.0.1:7461", ep).replace("seed = 5", f"seed = {seed}")
    gcs = free_port(socket.SOCK_DGRAM)
    text = text.replace("[mavlink]\n", f'[mavlink]\ngcs = "udpout:127.0.0.1:{gcs}"\n')
    stamp = datetime.datetime.fromtimestamp(start, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    text += f'\n[time]\nstart = "{stamp}"\nstep_s = {step_s}\n'
    if boat_ports:
        text += "\n[sensors]\n" + "".join(f'boat-{i + 1} = "udp:127.0.0.1:{p}"\n' for i, p in enumerate(boat_ports))
        text += "".join(f'av-{i + 1} = "geotiff:{d}"\n' for i, d in enumerate(frame_dirs))
    open(path, "w").write(text)
    return gcs


def start_run(dir_, seed, start, step_s, arm, bins):
    os.makedirs(dir_, exist_ok=True)
    udp = arm != "sim"
    ports = [free_port(socket.SOCK_DGRAM) for _ in range(3)] if udp else []
    frames = [os.path.join(dir_, f"av-{i + 1}") for i in range(2)] if arm == "all" else []
    for d in frames:
        os.makedirs(d, exist_ok=True)
    m = os.path.join(dir_, "mission.toml")
    gcs = mission(m, seed, start, step_s, ports, frames)
    procs = []
    if udp:
        args = [bins["instrument_emulator"], "--mission", m, "--gcs-port", str(gcs), "--seed", str(1000 + seed),
                "--log", os.path.join(dir_, "sent.ndjson")]
        for i, p in enumerate(ports):
            args += ["--send", f"boat-{i + 1}=127.0.0.1:{p}"]
        for i, d in enumerate(frames):
            args += ["--frames", f"av-{i + 1}={d}"]
        procs.append(subprocess.Popen(args, stderr=subprocess.DEVNULL))
    log = open(os.path.join(dir_, "up.log"), "w")
    fleet = subprocess.Popen([bins["fleet"], "up", m, "--out", os.path.join(dir_, "run")], stdout=log, stderr=log)
    return fleet, procs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--step-s", type=float, default=1.0)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    out = a.out or tempfile.mkdtemp(prefix="hetfleet-instruments-")
    bins = {b: os.path.join(ROOT, "target/release", b) for b in ("fleet", "instrument_emulator")}
    arms = ("sim", "udp", "all")
    start = int(time.time()) + 30 + 3 * a.seeds
    runs = {}
    for seed in range(a.seeds):
        for arm in arms:
            d = os.path.join(out, f"seed{seed}-{arm}")
            runs[(seed, arm)] = (d, *start_run(d, seed, start, a.step_s, arm, bins))
    mse = {}
    for (seed, arm), (d, fleet, procs) in runs.items():
        if fleet.wait() != 0:
            raise SystemExit(f"fleet up failed: see {d}/up.log")
        for p in procs:
            p.wait()
        mse[(seed, arm)] = json.load(open(os.path.join(d, "run", "summary.json")))["mean_mse"]
    result = {"seeds": a.seeds, "step_s": a.step_s, "out": out}
    sim_mean = statistics.mean(mse[(s, "sim")] for s in range(a.seeds))
    for arm in arms:
        result[f"{arm}_mean_mse"] = [mse[(s, arm)] for s in range(a.seeds)]
    for arm in arms[1:]:
        diffs = [mse[(s, arm)] - mse[(s, "sim")] for s in range(a.seeds)]
        m, sd = statistics.mean(diffs), statistics.stdev(diffs)
        half = T975.get(a.seeds - 1, 1.96) * sd / a.seeds ** 0.5
        result[f"{arm}_minus_sim"] = {"mean": m, "ci95": [m - half, m + half], "relative_to_sim": m / sim_mean}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
