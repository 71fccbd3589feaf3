"""A pymavlink ground station with MAVLink 2 signing, against a signed hetfleet gateway
(tests/tests/mavlink_signing.rs).

It listens where the gateway sends (udpin), signs with the mission's key (the SHA-256 of the
passphrase, as MAVProxy's `signing key <passphrase>` does), and:
  1. sees the vehicle's HEARTBEATs, each signed and passing pymavlink's own check;
  2. asks for HOME_POSITION signed: acked (through the gateway, the vehicle's bridge re-signing
     with its autopilot key, and the simulated autopilot's check);
  3. asks unsigned, and signed with a wrong key: no answer to either;
  4. sends one signed request twice, byte for byte: answered once (the copy is a replay).
Prints one JSON object of what it sent and what came back; the Rust test checks the gateway's
refusal counters against it.
"""

import argparse
import hashlib
import json
import os
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--port", type=int, required=True)
ap.add_argument("--passphrase-file", required=True)
ap.add_argument("--sysid", type=int, required=True)
args = ap.parse_args()

passphrase = open(args.passphrase_file).read().strip()
key = hashlib.sha256(passphrase.encode()).digest()
m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{args.port}", source_system=255, source_component=190)
out = {"sent": {"unsigned": 0, "bad_signature": 0, "replay": 0}}


def fail(why):
    out["error"] = why
    print(json.dumps(out))
    sys.exit(1)


def sign_with(k):
    # Incoming frames are checked against the same key: unsigned or foreign ones are dropped.
    m.setup_signing(k, sign_outgoing=True)


def home_request():
    return m.mav.command_long_encode(args.sysid, 1, mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 0, 0, 0, 0)


def acks_within(seconds):
    """COMMAND_ACKs of REQUEST_MESSAGE from the vehicle within `seconds` (pymavlink drops what
    fails its signing check)."""
    n, deadline = 0, time.time() + seconds
    while time.time() < deadline:
        a = m.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
        if a is not None and a.get_srcSystem() == args.sysid and a.command == mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE:
            n += 1
    return n


# 1. Signed heartbeats from the vehicle.
sign_with(key)
deadline, signed = time.time() + 30, 0
while time.time() < deadline and signed < 3:
    hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
    if hb is not None and hb.get_srcSystem() == args.sysid and hb.get_srcComponent() == 1:
        signed += int(bool(getattr(hb, "_signed", False)))
out["signed_heartbeats"] = signed
if signed < 3:
    fail("no signed HEARTBEAT from the vehicle")

# 2. A signed request: answered (tried a few times: the first may race the vehicle's set-up).
answered = 0
for _ in range(5):
    m.mav.send(home_request())
    answered = acks_within(1.5)
    if answered:
        break
out["signed_acks"] = answered

# 3. Unsigned, then signed with a key that is not the mission's.
m.mav.signing.sign_outgoing = False
for _ in range(3):
    m.mav.send(home_request())
    out["sent"]["unsigned"] += 1
m.mav.signing.sign_outgoing = True
out["unsigned_acks"] = acks_within(2.0)
sign_with(hashlib.sha256(b"a stranger's guess").digest())
for _ in range(2):
    m.mav.send(home_request())
    out["sent"]["bad_signature"] += 1
sign_with(key)
out["wrong_key_acks"] = acks_within(2.0)

# 4. One signed frame sent twice, byte for byte.
frame = home_request().pack(m.mav)
m.write(frame)
first = acks_within(2.0)
m.write(frame)
out["sent"]["replay"] += 1
out["replay_acks"] = (first, acks_within(2.0))
print(json.dumps(out))
