"""The vehicle node as an actor, measured (issue 33): CPU time while idle between steps, and
the latency from a ground-station HOLD to the node leaving the allocation.

usage: python3 bench/vehicle_actor.py [--window-s 60] [--holds 10] [--fleet target/release/fleet]

It runs the bundled mission paced (`[pace] step_ms = 3000`: every vehicle waits out each step,
as a real fleet does) with `fleet up`, and:
  1. over `--window-s` seconds, reads every vehicle process's CPU time from /proc, per thread:
     the simulated autopilot's threads (`sim-autopilot*`, the stand-in for the autopilot a real
     boat carries) apart from the node's own;
  2. as a ground station on UDP 14550 (where the mission's gateway sends), puts boat-2 on HOLD
     (SET_MODE) and times, on a Python Zenoh subscriber, the first telemetry of boat-2 that
     says it is no longer available (`autopilot.guided` false): the server leaves it out of the
     next allocation on that message. Then GUIDED again, and repeat.
Prints one JSON object. Not a test: no timing is asserted anywhere.
"""
import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time

os.environ["MAVLINK20"] = "1"
import cbor2  # noqa: E402
import zenoh  # noqa: E402
from pymavlink import mavutil  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TICK = os.sysconf("SC_CLK_TCK")
HOLD, GUIDED = 4, 15  # ArduRover's custom modes


def vehicle_pids():
    out = {}
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")
        except OSError:
            continue
        if cmd and cmd[0].endswith(b"/vehicle") and b"--id" in cmd:
            out[int(pid)] = cmd[cmd.index(b"--id") + 1].decode()
    return out


def cpu_by_thread(pid):
    """(sim-autopilot ticks, node ticks) of a process, summed over its live threads."""
    sim = node = 0
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0, 0
    for tid in tids:
        try:
            stat = open(f"/proc/{pid}/task/{tid}/stat").read()
        except OSError:
            continue
        name = stat[stat.index("(") + 1 : stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2 :].split()
        ticks = int(fields[11]) + int(fields[12])
        if name.startswith("sim-autopilot"):
            sim += ticks
        else:
            node += ticks
    return sim, node


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--fleet", default=os.path.join(ROOT, "target/release/fleet"))
    ap.add_argument("--window-s", type=float, default=60.0)
    ap.add_argument("--holds", type=int, default=10)
    args = ap.parse_args()
    work = tempfile.mkdtemp(prefix="vehicle-actor-")
    mission = open(os.path.join(ROOT, "config/mission.toml")).read()
    mission = re.sub(r"step_ms = \d+", "step_ms = 3000", mission)
    path = os.path.join(work, "mission.toml")
    open(path, "w").write(mission)
    up = subprocess.Popen([args.fleet, "up", path, "--out", os.path.join(work, "run")],
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        result = measure(args, up)
    finally:
        os.killpg(up.pid, signal.SIGTERM)
        up.wait()
    print(json.dumps(result, indent=1))


def measure(args, up):
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=255, source_component=190)
    # The fleet up and every vehicle past its start (its first epochs driven).
    deadline = time.time() + 60
    pids = {}
    while time.time() < deadline and len(pids) < 7:
        pids = vehicle_pids()
        time.sleep(0.5)
    if len(pids) < 7:
        sys.exit(f"only {len(pids)} vehicle processes came up")
    time.sleep(10)
    before = {p: cpu_by_thread(p) for p in pids}
    t0 = time.time()
    time.sleep(args.window_s)
    after = {p: cpu_by_thread(p) for p in pids}
    wall = time.time() - t0
    per = {pids[p]: {"sim_autopilot_s": (after[p][0] - before[p][0]) / TICK,
                     "node_s": (after[p][1] - before[p][1]) / TICK} for p in pids}
    node = [v["node_s"] / wall * 60 for v in per.values()]
    sim = [v["sim_autopilot_s"] / wall * 60 for v in per.values()]
    return {
        "window_s": round(wall, 1),
        "node_cpu_s_per_vehicle_minute": {"mean": statistics.mean(node), "max": max(node)},
        "sim_autopilot_cpu_s_per_vehicle_minute": {"mean": statistics.mean(sim), "max": max(sim)},
        "per_vehicle": per,
        "hold_to_unavailable_ms": holds(args, gcs),
    }


def holds(args, gcs):
    """Milliseconds from a ground station's SET_MODE HOLD to boat-2's telemetry saying it is
    out of the allocation."""
    seen = threading.Event()
    want = {"guided": None}

    def on_telemetry(sample):
        t = cbor2.loads(sample.payload.to_bytes())
        ap = t.get("autopilot") or {}
        if want["guided"] is not None and ap.get("guided") == want["guided"]:
            seen.set()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    sysid = 4  # boat-2: the mission's fourth vehicle
    out = []
    # (A `udpin:` ground station answers its last sender: hear the gateway first.)
    while gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5) is None:
        pass
    with zenoh.open(conf) as session:
        session.declare_subscriber("fleet/default/vehicle/boat-2/telemetry", on_telemetry)
        for _ in range(args.holds):
            for mode, guided in ((HOLD, False), (GUIDED, True)):
                seen.clear()
                want["guided"] = guided
                t = time.perf_counter()
                gcs.mav.set_mode_send(sysid, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)
                if not seen.wait(10):
                    out.append(None)
                    continue
                if not guided:
                    out.append((time.perf_counter() - t) * 1e3)
                time.sleep(1.0)
    got = sorted(x for x in out if x is not None)
    return {"count": len(got), "missed": len(out) - len(got),
            "p50": statistics.median(got) if got else None, "max": max(got) if got else None}


if __name__ == "__main__":
    main()
