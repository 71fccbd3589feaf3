"""Readings from an outside instrument against the simulated sensor (issue 34), paired by seed.

usage: python3 bench/instruments.py [--seeds 10] [--step-s 1.0] [--out DIR]

For each seed, the tiny mission (its `[team] seed` set, so the truth and the aerials' noise are
the seed's) runs twice on the clock (`[time]`, steps of `--step-s`) with `fleet up`, all seeds
at once on their own ports:
  - `sim`: every boat senses its disk of the truth itself (the simulated sensor);
  - `udp`: every boat reads a UDP sensor port, fed by `instrument_emulator` (a separate process
    that hears where each boat really is from the ground-station stream and sends the readings
    a disk instrument there takes of the same truth, with the mission's boat noise).
The two differ only in the boats' noise draws and in where the boats really were. Prints the
mean of each run's per-step MSE, the paired differences (udp - sim) and their mean with a
95% t-interval, as one JSON object. Not a test: nothing is asserted.
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


def mission(path, seed, start, step_s, boat_ports):
    text = open(os.path.join(ROOT, "config/mission-tiny.toml")).read()
    ep = f"tcp/127.0.0.1:{free_port()}"
    text = text.replace("tcp/127.0.0.1:7461", ep).replace("seed = 5", f"seed = {seed}")
    gcs = free_port(socket.SOCK_DGRAM)
    text = text.replace("[mavlink]\n", f'[mavlink]\ngcs = "udpout:127.0.0.1:{gcs}"\n')
    stamp = datetime.datetime.fromtimestamp(start, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    text += f'\n[time]\nstart = "{stamp}"\nstep_s = {step_s}\n'
    if boat_ports:
        text += "\n[sensors]\n" + "".join(f'boat-{i + 1} = "udp:127.0.0.1:{p}"\n' for i, p in enumerate(boat_ports))
    open(path, "w").write(text)
    return gcs


def start_run(dir_, seed, start, step_s, udp, bins):
    os.makedirs(dir_, exist_ok=True)
    ports = [free_port(socket.SOCK_DGRAM) for _ in range(3)] if udp else []
    m = os.path.join(dir_, "mission.toml")
    gcs = mission(m, seed, start, step_s, ports)
    procs = []
    if udp:
        args = [bins["instrument_emulator"], "--mission", m, "--gcs-port", str(gcs), "--seed", str(1000 + seed),
                "--log", os.path.join(dir_, "sent.ndjson")]
        for i, p in enumerate(ports):
            args += ["--send", f"boat-{i + 1}=127.0.0.1:{p}"]
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
    start = int(time.time()) + 30 + 2 * a.seeds
    runs = {}
    for seed in range(a.seeds):
        for udp in (False, True):
            d = os.path.join(out, f"seed{seed}-{'udp' if udp else 'sim'}")
            runs[(seed, udp)] = (d, *start_run(d, seed, start, a.step_s, udp, bins))
    mse = {}
    for (seed, udp), (d, fleet, procs) in runs.items():
        if fleet.wait() != 0:
            raise SystemExit(f"fleet up failed: see {d}/up.log")
        for p in procs:
            p.wait()
        mse[(seed, udp)] = json.load(open(os.path.join(d, "run", "summary.json")))["mean_mse"]
    diffs = [mse[(s, True)] - mse[(s, False)] for s in range(a.seeds)]
    m, sd = statistics.mean(diffs), statistics.stdev(diffs)
    half = T975.get(a.seeds - 1, 1.96) * sd / a.seeds ** 0.5
    print(json.dumps({
        "seeds": a.seeds, "step_s": a.step_s, "out": out,
        "sim_mean_mse": [mse[(s, False)] for s in range(a.seeds)],
        "udp_mean_mse": [mse[(s, True)] for s in range(a.seeds)],
        "udp_minus_sim": {"mean": m, "ci95": [m - half, m + half],
                          "relative_to_sim": m / statistics.mean(mse[(s, False)] for s in range(a.seeds))},
    }, indent=1))


if __name__ == "__main__":
    main()
