"""An instrument driver that feeds a boat: the program a field team writes for its own sonde.

It hears where the boat is from the fleet's ground-station stream (the autopilot's
GLOBAL_POSITION_INT, as QGroundControl hears it; a driver on the boat's companion computer
could read the GPS instead), reads its instrument once a period, and sends each reading to the
boat's vehicle node as one line of JSON over UDP, the interface `[sensors] boat-1 =
"udp:ADDR:PORT"` opens (docs/guide/survey.md, "Instruments"):

    {"t": 1795597230.25, "lat": 55.67612, "lon": 12.56841, "value": 0.42, "sigma": 0.01}

`t` is UTC seconds, `lat`/`lon` WGS 84 degrees, `value` in the field's units, `sigma` its noise.

    python3 sonde_driver.py --gcs 127.0.0.1:14550 --sysid 3 --to 127.0.0.1:15601 [--period 0.5] [--seconds 30]

`--gcs` is where the mission's `[mavlink] gcs` sends the fleet's stream (`udpout:` to this
address), `--sysid` the boat's MAVLink system id (its place in the mission's vehicle list),
`--to` the boat's sensor port. Needs `pip install pymavlink`. `read_instrument` is the part to
replace: here a stand-in that reads a constant with Gaussian noise.
"""
import argparse
import json
import random
import socket
import sys
import time

from pymavlink import mavutil


def read_instrument(rng):
    """The instrument's value and its noise standard deviation (replace with the real read)."""
    sigma = 0.01
    return 0.3 + rng.gauss(0.0, sigma), sigma


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--gcs", required=True, help="host:port the fleet's ground-station stream comes to")
    p.add_argument("--sysid", type=int, required=True, help="the boat's MAVLink system id")
    p.add_argument("--to", required=True, help="host:port of the boat's sensor (udp:) interface")
    p.add_argument("--period", type=float, default=1.0, help="seconds between readings")
    p.add_argument("--seconds", type=float, default=60.0, help="stop after this long")
    a = p.parse_args()
    host, port = a.to.rsplit(":", 1)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stream = mavutil.mavlink_connection(f"udpin:{a.gcs}", source_system=255)
    rng = random.Random(1)
    fix, sent, next_at, end = None, 0, 0.0, time.time() + a.seconds
    while time.time() < end:
        msg = stream.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=0.2)
        if msg is not None and msg.get_srcSystem() == a.sysid:
            fix = (msg.lat / 1e7, msg.lon / 1e7)
        if fix is None or time.time() < next_at:
            continue
        value, sigma = read_instrument(rng)
        line = {"t": time.time(), "lat": fix[0], "lon": fix[1], "value": value, "sigma": sigma}
        out.sendto((json.dumps(line) + "\n").encode(), (host, int(port)))
        sent += 1
        next_at = time.time() + a.period
    print(f"sent {sent} readings", file=sys.stderr)
    return 0 if sent else 1


if __name__ == "__main__":
    sys.exit(main())
