"""MAVSDK (the `mavsdk` Python package, the native binding of MAVSDK v4) against a running
`sim-autopilot` (tests/tests/mavlink.rs): connect, telemetry (position, home, battery),
parameters, arm, a geofence upload and download, a mission upload, start and run to the end.
Prints one JSON object of what it saw; the Rust test checks it against the simulator's site.
"""

import json
import sys
import time

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action import Action
from mavsdk.plugins.geofence import FenceType, Geofence, GeofenceData, Point, Polygon
from mavsdk.plugins.mission import Mission, MissionItem, MissionPlan
from mavsdk.plugins.param import Param
from mavsdk.plugins.telemetry import Telemetry

port = int(sys.argv[1])
out = {}


def step(name, f):
    """Run one call; its result or its error goes in the output."""
    try:
        r = f()
        out[name] = r if isinstance(r, (int, float, str, bool, list, dict, type(None))) else str(r)
    except Exception as e:  # noqa: BLE001 - the test reads what failed
        out[name] = f"error: {e}"


m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
out["connect"] = str(m.add_any_connection(f"udpout://127.0.0.1:{port}"))
system = m.first_autopilot(10.0)
if system is None:
    out["error"] = "no autopilot discovered"
    print(json.dumps(out))
    sys.exit(1)
t, a, g, mi, par = Telemetry(system), Action(system), Geofence(system), Mission(system), Param(system)
# Position and home once the first GLOBAL_POSITION_INT and HOME_POSITION are in (NaN before).
deadline = time.time() + 10
while time.time() < deadline and not (t.position().latitude_deg == t.position().latitude_deg and t.home().latitude_deg == t.home().latitude_deg):
    time.sleep(0.1)
while time.time() < deadline and t.battery().remaining_percent != t.battery().remaining_percent:
    time.sleep(0.1)
p = t.position()
out["position"] = [p.latitude_deg, p.longitude_deg]
step("home", lambda: [t.home().latitude_deg, t.home().longitude_deg])
step("battery", lambda: t.battery().remaining_percent)
step("cruise_speed", lambda: par.get_param_float("CRUISE_SPEED"))
step("arm", lambda: int(a.arm()))
time.sleep(0.5)
out["armed"] = t.armed()

# A square fence 0.002 deg across around the vehicle, read back.
d = 0.001
square = [Point(p.latitude_deg + dy, p.longitude_deg + dx) for dy, dx in ((-d, -d), (-d, d), (d, d), (d, -d))]
step("fence_upload", lambda: int(g.upload_geofence(GeofenceData([Polygon(square, FenceType.INCLUSION)], []))))
step("fence_download", lambda: [[[q.latitude_deg, q.longitude_deg] for q in poly.points] for poly in g.download_geofence().polygons])

# Three waypoints about 11 m apart, run to the end.
wps = [(p.latitude_deg + 1e-4 * k, p.longitude_deg + 1e-4 * (k % 2)) for k in (1, 2, 3)]
items = [MissionItem(lat, lon, 0.0, None, True) for lat, lon in wps]
step("mission_upload", lambda: int(mi.upload_mission(MissionPlan(items))))
step("mission_start", lambda: int(mi.start_mission()))
deadline = time.time() + 30
while time.time() < deadline and not mi.is_mission_finished():
    time.sleep(0.2)
pr = mi.mission_progress()
out["progress"] = [pr.current, pr.total]
out["finished"] = mi.is_mission_finished()
# It holds at the end; read its position after the next few position messages (10 Hz), not the
# one cached when the last item was reached (at 100x speed that one may be metres behind).
time.sleep(0.5)
q = t.position()
out["end"] = [q.latitude_deg, q.longitude_deg]
out["waypoints"] = [list(w) for w in wps]
print(json.dumps(out))
