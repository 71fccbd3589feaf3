"""MAVLink message rates per vehicle, as a ground station sees them on the fleet's gateway.

    python3 scripts/mavlink_rates.py [--port 14550] [--seconds 5]

Run it while `fleet up` runs (the default mission's gateway sends to udp 127.0.0.1:14550).
"""

import argparse
import collections
import os
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--port", type=int, default=14550)
ap.add_argument("--seconds", type=float, default=5.0)
args = ap.parse_args()
m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{args.port}", source_system=255)
first = m.recv_match(blocking=True, timeout=30)
if first is None:
    raise SystemExit(f"nothing on udp port {args.port} in 30 s: is the fleet up with a gateway?")
counts = collections.Counter()
t0 = time.time()
while time.time() - t0 < args.seconds:
    msg = m.recv_match(blocking=True, timeout=0.5)
    if msg is not None and msg.get_type() != "BAD_DATA":
        counts[(msg.get_srcSystem(), msg.get_srcComponent(), msg.get_type())] += 1
dt = time.time() - t0
systems = sorted({s for s, _, _ in counts})
print(f"{'sys':>4} {'comp':>4} {'message':<28} {'Hz':>6}")
for s in systems:
    total = 0
    for (sy, c, t), n in sorted(counts.items()):
        if sy == s:
            print(f"{sy:>4} {c:>4} {t:<28} {n / dt:6.1f}")
            total += n
    print(f"{s:>4} {'':>4} {'all':<28} {total / dt:6.1f}")
