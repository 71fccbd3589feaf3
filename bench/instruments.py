"""Readings from outside instruments against the simulated sensors (issue 34), paired by seed.

usage: python3 bench/instruments.py [--seeds 10] [--step-s 1.0] [--out DIR]

For each seed, the tiny mission (its `[team] seed` set, so the truth is the seed's) runs five
times on the clock (`[time]`, steps of `--step-s`) with `fleet up`, all runs at once on their
own ports (`--together` seeds at a time, so 2 cores are not overloaded: a boat whose plan
comes late senses where its old plan said, and that confounds the arms):
  - `sim`: every vehicle senses the truth itself (the simulated sensors);
  - `udp`: boat-1 and boat-2 read UDP sensor ports and boat-3 its standard input, fed by
    `instrument_emulator` (a separate process that hears where each boat really is from the
    ground-station stream and sends the readings a disk instrument there takes of the same
    truth, with the mission's boat noise); the aerials as in `sim` (the same noise);
  - `all`: the boats as in `udp`, and every aerial reads a directory of GeoTIFF frames the
    emulator writes (the truth over the site, one pixel per cell, with the aerial's noise at
    each cell's distance from where the aerial really is);
  - `sim0` and `mavlink`: a point instrument (`radius = 0`: the boat's own cell), simulated, or
    every boat on `mavlink:SONDE`, its sonde a companion computer on the simulated autopilot's
    companion link sending one NAMED_VALUE_FLOAT a sampling step (paired with `sim0`).
Each differs from its `sim` arm only in noise draws and in where the vehicles really were. Prints the
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


RESERVED = set()


def free_port(kind=socket.SOCK_STREAM):
    """A port free now and not handed out before in this run (the runs start at once: a port
    free now may be another run's before its node binds it)."""
    while True:
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in RESERVED:
            RESERVED.add(port)
            return port


def mission(path, seed, start, step_s, boat_ports, frame_dirs, point=False, companion=None):
    text = open(os.path.join(ROOT, "config/mission-tiny.toml")).read()
    if point:
        text = text.replace("radius = 3.0", "radius = 0.0")
    ep = f"tcp/127.0.0.1:{free_port()}"
    text = text.replace("tcp/127.0.0.1:7461", ep).replace("seed = 5", f"seed = {seed}")
    gcs = free_port(socket.SOCK_DGRAM)
    text = text.replace("[mavlink]\n", f'[mavlink]\ngcs = "udpout:127.0.0.1:{gcs}"\n')
    if companion:
        text = text.replace("[mavlink]\n", f"[mavlink]\nsim_companion_port = {companion}\n")
    stamp = datetime.datetime.fromtimestamp(start, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    text += f'\n[time]\nstart = "{stamp}"\nstep_s = {step_s}\n'
    if boat_ports:
        text += "\n[sensors]\n" + "".join(f'boat-{i + 1} = "udp:127.0.0.1:{p}"\n' for i, p in enumerate(boat_ports))
        text += 'boat-3 = "stdin"\n'
        text += "".join(f'av-{i + 1} = "geotiff:{d}"\n' for i, d in enumerate(frame_dirs))
    if companion:
        text += "\n[sensors]\n" + "".join(f'boat-{i} = "mavlink:SONDE"\n' for i in (1, 2, 3))
    open(path, "w").write(text)
    return gcs


def companion_base():
    """A base port whose next 5 UDP ports are free (a simulated autopilot's companion link is the
    base plus its system id)."""
    import random
    while True:
        # Below the kernel's ephemeral range (32768 up): no socket bound to port 0 takes it
        # before the autopilots bind it.
        base = random.randrange(20000, 32000)
        if any(base + i in RESERVED for i in range(1, 6)):
            continue
        try:
            for i in range(1, 6):
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.bind(("127.0.0.1", base + i))
        except OSError:
            continue
        RESERVED.update(base + i for i in range(1, 6))
        return base


def start_run(dir_, seed, start, step_s, arm, bins):
    os.makedirs(dir_, exist_ok=True)
    udp = arm in ("udp", "all")
    ports = [free_port(socket.SOCK_DGRAM) for _ in range(2)] if udp else []
    frames = [os.path.join(dir_, f"av-{i + 1}") for i in range(2)] if arm == "all" else []
    for d in frames:
        os.makedirs(d, exist_ok=True)
    companion = companion_base() if arm == "mavlink" else None
    m = os.path.join(dir_, "mission.toml")
    gcs = mission(m, seed, start, step_s, ports, frames, point=arm in ("sim0", "mavlink"), companion=companion)
    procs, stdin = [], subprocess.DEVNULL
    if udp or companion:
        args = [bins["instrument_emulator"], "--mission", m, "--gcs-port", str(gcs), "--seed", str(1000 + seed),
                "--log", os.path.join(dir_, "sent.ndjson")]
        for i, p in enumerate(ports):
            args += ["--send", f"boat-{i + 1}=127.0.0.1:{p}"]
        if udp:
            args += ["--send", "boat-3=-"]
        for i, d in enumerate(frames):
            args += ["--frames", f"av-{i + 1}={d}"]
        if companion:
            # The tiny mission's system ids: the aerials 1 and 2, the boats 3 to 5.
            args += [a for i in (1, 2, 3) for a in ("--mavlink", f"boat-{i}={companion + 2 + i}")]
        emulator = subprocess.Popen(args, stderr=subprocess.DEVNULL, stdout=subprocess.PIPE)
        procs.append(emulator)
        stdin = emulator.stdout
    log = open(os.path.join(dir_, "up.log"), "w")
    fleet = subprocess.Popen([bins["fleet"], "up", m, "--out", os.path.join(dir_, "run")], stdout=log, stderr=log,
                             stdin=stdin)
    return fleet, procs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--step-s", type=float, default=1.0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--together", type=int, default=2,
                    help="seeds run at once (each its five arms): more overloads 2 cores, and late plans confound")
    a = ap.parse_args()
    out = a.out or tempfile.mkdtemp(prefix="hetfleet-instruments-")
    bins = {b: os.path.join(ROOT, "target/release", b) for b in ("fleet", "instrument_emulator")}
    arms = ("sim", "udp", "all", "sim0", "mavlink")
    mse = {}
    for wave in range(0, a.seeds, a.together):
        seeds = range(wave, min(a.seeds, wave + a.together))
        start = int(time.time()) + 20 + 2 * len(seeds) * len(arms)
        runs = {}
        for seed in seeds:
            for arm in arms:
                d = os.path.join(out, f"seed{seed}-{arm}")
                runs[(seed, arm)] = (d, *start_run(d, seed, start, a.step_s, arm, bins))
        for (seed, arm), (d, fleet, procs) in runs.items():
            if fleet.wait() != 0:
                raise SystemExit(f"fleet up failed: see {d}/up.log")
            for p in procs:
                p.wait()
            mse[(seed, arm)] = json.load(open(os.path.join(d, "run", "summary.json")))["mean_mse"]
    result = {"seeds": a.seeds, "step_s": a.step_s, "out": out}
    for arm in arms:
        result[f"{arm}_mean_mse"] = [mse[(s, arm)] for s in range(a.seeds)]
    pairs = (("udp", "sim"), ("all", "sim"), ("mavlink", "sim0"))
    for arm, base in pairs:
        base_mean = statistics.mean(mse[(s, base)] for s in range(a.seeds))
        diffs = [mse[(s, arm)] - mse[(s, base)] for s in range(a.seeds)]
        m, sd = statistics.mean(diffs), statistics.stdev(diffs)
        half = T975.get(a.seeds - 1, 1.96) * sd / a.seeds ** 0.5
        result[f"{arm}_minus_{base}"] = {"mean": m, "ci95": [m - half, m + half], "relative_to_base": m / base_mean,
                                         "base_mean_mse": base_mean}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
