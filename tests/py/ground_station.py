"""A ground station made of pymavlink, against a running hetfleet fleet (tests/tests/mavlink.rs).

It listens where the fleet's gateway sends (udpin), and:
  1. discovers every vehicle by HEARTBEAT (system id, MAV_TYPE, autopilot);
  2. watches each vehicle's guided target (POSITION_TARGET_LOCAL_NED) and position
     (LOCAL_POSITION_NED), both from its EKF origin (GPS_GLOBAL_ORIGIN, reported too), and
     reports how far it was from its target, first and last;
  3. uploads a 3-item mission to one vehicle with the standard handshake
     (MISSION_COUNT -> MISSION_REQUEST_INT -> MISSION_ITEM_INT ... -> MISSION_ACK; item 0 is
     home, as ArduPilot has it), sets AUTO and waits for MISSION_ITEM_REACHED 1, 2, 3;
  4. puts another vehicle on HOLD (SET_MODE) and waits for its HEARTBEAT to show it;
  5. times every autopilot's HEARTBEAT over the whole run (rate, longest gap).
Prints one JSON object with what it saw; the Rust test checks it against the server.
"""

import argparse
import json
import math
import os
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--port", type=int, required=True)
ap.add_argument("--vehicles", required=True, help="sysid:type,... e.g. 1:2,3:11")
ap.add_argument("--mission-sysid", type=int, required=True)
ap.add_argument("--hold-sysid", type=int, required=True)
ap.add_argument("--hold-mode", type=int, default=4)
ap.add_argument("--auto-mode", type=int, default=10)
ap.add_argument("--watch-s", type=float, default=15.0)
ap.add_argument("--heartbeat-s", type=float, default=22.0, help="seconds of heartbeats timed from discovery")
args = ap.parse_args()

want = {int(s): int(t) for s, t in (p.split(":") for p in args.vehicles.split(","))}
m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{args.port}", source_system=255, source_component=190)
out = {"heartbeats": {}, "targets": {}, "approach": {}, "mission": {}, "hold": {}}
# When each autopilot's HEARTBEAT arrived, whatever the steps below wait for: a ground station
# judges the link by them (QGroundControl calls a vehicle lost after 3.5 s without one).
heard = {}


def on_message(_conn, msg):
    if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
        heard.setdefault(msg.get_srcSystem(), []).append(time.monotonic())


m.message_hooks.append(on_message)


def fail(why):
    out["error"] = why
    print(json.dumps(out))
    sys.exit(1)


def recv(types, timeout):
    msg = m.recv_match(type=types, blocking=True, timeout=timeout)
    return msg


# 1. Discovery.
deadline = time.time() + 30
while time.time() < deadline and set(out["heartbeats"]) != set(want):
    hb = recv("HEARTBEAT", 1.0)
    if hb is None or hb.get_srcComponent() != 1:
        continue
    out["heartbeats"][hb.get_srcSystem()] = {"type": hb.type, "autopilot": hb.autopilot, "mode": hb.custom_mode}
if set(out["heartbeats"]) != set(want):
    fail(f"heartbeats from {sorted(out['heartbeats'])}, wanted {sorted(want)}")
discovered = time.monotonic()

# 2. Targets and positions: distance to the newest guided target, first and last seen, until
# every vehicle with a target has reached it (or the watch ends); and over all its targets, the
# most metres a vehicle was seen to close on one (a vehicle at 20 m/s reaches a near target
# within a tick of the 10 Hz stream: the newest target alone may show no approach while an
# earlier one showed metres).
first, last, targets, since, current, closed = {}, {}, {}, {}, {}, {}
# GUIDED's custom mode: ArduRover's 15, ArduCopter's 4 (MAV_TYPE 2, a quadrotor).
GUIDED = {False: 15, True: 4}
# Each autopilot says its EKF origin once, at its fix: ask for it again (MAV_CMD_REQUEST_MESSAGE),
# and again every 2 s until it answers (a command over UDP and the fleet's links may be lost).
watch_end, asked = time.time() + args.watch_s, 0.0
while time.time() < watch_end:
    if time.time() - asked > 2.0:
        for s in want:
            if s not in out.get("origins", {}):
                m.mav.command_long_send(s, 1, mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 49, 0, 0, 0, 0, 0, 0)
        asked = time.time()
    msg = recv(["POSITION_TARGET_LOCAL_NED", "LOCAL_POSITION_NED", "GPS_GLOBAL_ORIGIN", "HEARTBEAT"], 0.5)
    if msg is None:
        continue
    s = msg.get_srcSystem()
    if msg.get_type() == "HEARTBEAT":
        # Out of GUIDED (the fleet's end sends it home, a failsafe to RTL or HOLD) it drives to
        # no guided target: its approach is measured again from its next one.
        if msg.get_srcComponent() == 1 and s in want and msg.custom_mode != GUIDED[want[s] == 2]:
            current.pop(s, None)
            first.pop(s, None)
            last.pop(s, None)
    elif msg.get_type() == "GPS_GLOBAL_ORIGIN":
        # Local NED is from each autopilot's EKF origin (where it booted), not the site's corner.
        out.setdefault("origins", {})[s] = [msg.latitude, msg.longitude]
    elif msg.get_type() == "POSITION_TARGET_LOCAL_NED":
        t = (round(msg.x, 3), round(msg.y, 3))
        targets.setdefault(s, [])
        if t not in targets[s]:
            targets[s].append(t)
        if current.get(s) != t:
            # A new target, or a return to an earlier one: measure the approach to it afresh.
            current[s] = t
            first.pop(s, None)
            last.pop(s, None)
    elif s in current:
        tx, ty = current[s]
        d = math.hypot(msg.x - tx, msg.y - ty)
        if s not in first:
            first[s], since[s] = d, time.time()
        last[s] = d
        closed[s] = max(closed.get(s, 0.0), first[s] - d)
        boats = [v for v, t in want.items() if t == 11]
        origins = out.get("origins", {})
        if (
            all(b in last and last[b] < 0.5 for b in boats)
            and any(closed.get(b, 0.0) > 2.0 for b in boats)
            and all(v in origins for v in targets)
        ):
            break
out["targets"] = {s: [list(t) for t in ts] for s, ts in targets.items()}
# Per vehicle: the newest target's first and last distance and seconds watched, then the most
# metres closed on any target.
out["approach"] = {s: [first[s], last[s], time.time() - since[s], closed[s]] for s in last}

# 3a. Home and the parameter list of the mission vehicle, as MAVProxy and QGC ask on connecting.
sysid = args.mission_sysid
m.mav.command_long_send(sysid, 1, mavutil.mavlink.MAV_CMD_GET_HOME_POSITION, 0, 0, 0, 0, 0, 0, 0, 0)
home, t = None, time.time()
while home is None and time.time() - t < 5:
    msg = recv("HOME_POSITION", 1.0)
    if msg is not None and msg.get_srcSystem() == sysid:
        home = msg
if home is None:
    fail("no HOME_POSITION after MAV_CMD_GET_HOME_POSITION")
out["home"] = [home.latitude, home.longitude]
m.mav.param_request_list_send(sysid, 1)
params, t = {}, time.time()
while time.time() - t < 5:
    msg = recv("PARAM_VALUE", 1.0)
    if msg is None or msg.get_srcSystem() != sysid:
        continue
    params[msg.param_id] = msg.param_value
    if len(params) == msg.param_count:
        break
out["params"] = params

# 3b. The site's fence and rally points as the bridge uploaded them (downloaded by type), and a
# reposition far outside the fence refused.
def download(kind):
    m.mav.mission_request_list_send(sysid, 1, kind)
    count, t = None, time.time()
    while count is None and time.time() - t < 5:
        msg = recv("MISSION_COUNT", 1.0)
        if msg is not None and msg.get_srcSystem() == sysid and msg.mission_type == kind:
            count = msg.count
    if count is None:
        fail(f"no MISSION_COUNT for mission type {kind}")
    items = []
    for seq in range(count):
        m.mav.mission_request_int_send(sysid, 1, seq, kind)
        it, t = None, time.time()
        while it is None and time.time() - t < 5:
            msg = recv("MISSION_ITEM_INT", 1.0)
            if msg is not None and msg.get_srcSystem() == sysid and msg.mission_type == kind and msg.seq == seq:
                it = msg
        if it is None:
            fail(f"no item {seq} of mission type {kind}")
        items.append([it.command, it.param1, it.x, it.y])
    return items


out["fence"] = download(mavutil.mavlink.MAV_MISSION_TYPE_FENCE)
out["rally"] = download(mavutil.mavlink.MAV_MISSION_TYPE_RALLY)
# About 1 km north of home.
m.mav.command_int_send(sysid, 1, mavutil.mavlink.MAV_FRAME_GLOBAL, mavutil.mavlink.MAV_CMD_DO_REPOSITION, 0, 0,
                       -1, 0, 0, 0, home.latitude + 90000, home.longitude, 0)
t = time.time()
while "outside_ack" not in out and time.time() - t < 5:
    msg = recv("COMMAND_ACK", 1.0)
    if msg is not None and msg.get_srcSystem() == sysid and msg.command == mavutil.mavlink.MAV_CMD_DO_REPOSITION:
        out["outside_ack"] = msg.result

# 3. Mission upload to one vehicle, then AUTO, then each item reached.
pos = recv("GLOBAL_POSITION_INT", 5.0)
while pos is not None and pos.get_srcSystem() != sysid:
    pos = recv("GLOBAL_POSITION_INT", 5.0)
if pos is None:
    fail("no position from the mission vehicle")
lat0, lon0 = pos.lat, pos.lon
# Home first (ArduPilot's item 0, not flown), then three points a few metres around it
# (1e-7 deg of latitude is about 1.1 cm).
items = [(lat0, lon0), (lat0 + 300, lon0), (lat0 + 300, lon0 + 500), (lat0, lon0 + 500)]
t0 = time.time()
m.mav.mission_count_send(sysid, 1, len(items))
sent = 0
while True:
    msg = recv(["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], 5.0)
    if msg is None:
        fail(f"mission upload stalled after {sent} items")
    if msg.get_srcSystem() != sysid:
        continue
    if msg.get_type() == "MISSION_ACK":
        out["mission"]["ack"] = msg.type
        break
    lat, lon = items[msg.seq]
    m.mav.mission_item_int_send(sysid, 1, msg.seq, mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                mavutil.mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, lat, lon, 0)
    sent += 1
out["mission"]["items_sent"] = sent
out["mission"]["upload_ms"] = (time.time() - t0) * 1e3
if out["mission"]["ack"] != mavutil.mavlink.MAV_MISSION_ACCEPTED:
    fail(f"mission refused: {out['mission']['ack']}")
m.mav.command_long_send(sysid, 1, mavutil.mavlink.MAV_CMD_DO_SET_MODE, 0,
                        mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, args.auto_mode, 0, 0, 0, 0, 0)
reached = []
deadline = time.time() + 20
while time.time() < deadline and len(reached) < len(items) - 1:
    msg = recv(["MISSION_ITEM_REACHED", "COMMAND_ACK"], 1.0)
    if msg is None or msg.get_srcSystem() != sysid:
        continue
    if msg.get_type() == "COMMAND_ACK":
        out["mission"]["mode_ack"] = msg.result
    elif msg.seq not in reached:
        reached.append(msg.seq)
out["mission"]["reached"] = reached

# 4. Operator hold on another vehicle.
hold = args.hold_sysid
m.mav.set_mode_send(hold, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, args.hold_mode)
deadline = time.time() + 10
while time.time() < deadline:
    hb = recv("HEARTBEAT", 1.0)
    if hb is not None and hb.get_srcSystem() == hold and hb.get_srcComponent() == 1 and hb.custom_mode == args.hold_mode:
        out["hold"] = {"mode": hb.custom_mode, "at": time.time()}
        break
if not out["hold"]:
    fail("the held vehicle never showed HOLD")

# 5. Heartbeats timed over a window from discovery, however soon the steps above ended.
while time.monotonic() - discovered < args.heartbeat_s:
    recv("HEARTBEAT", 0.5)
out["heartbeat_timing"] = {
    s: {"count": len(t), "span_s": t[-1] - t[0], "max_gap_s": max((b - a for a, b in zip(t, t[1:])), default=0.0)}
    for s, t in heard.items()
}
print(json.dumps(out))
