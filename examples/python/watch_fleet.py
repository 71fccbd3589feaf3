"""A client of a live mission in Python: it joins the mission's Zenoh network (eclipse-zenoh,
the same 1.x line as the fleet), and prints each model the server publishes and each
vehicle's telemetry, decoded from CBOR. It changes nothing.

    python3 watch_fleet.py <mission-id> <endpoint> [models]

`endpoint` is the server's Zenoh endpoint (`tcp/127.0.0.1:7447`); it exits 0 after `models`
models (default 3), 1 if none came within a minute. Needs `pip install eclipse-zenoh cbor2
numpy`. The messages' fields are in docs/reference/protocol.md: per-cell arrays are packed
little-endian float32 bytes, eigenvalues and amplitudes lists of [re, im].
"""
import json
import queue
import sys

import cbor2
import numpy as np
import zenoh


def main():
    mission, endpoint = sys.argv[1], sys.argv[2]
    wanted = int(sys.argv[3]) if len(sys.argv) > 3 else 3
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # Keep trying until the server is up (a client gives up at once otherwise).
    conf.insert_json5("connect/timeout_ms", "-1")
    conf.insert_json5("connect/exit_on_failure", "false")
    events = queue.Queue()
    with zenoh.open(conf) as session:
        session.declare_subscriber(f"fleet/{mission}/model/latest", lambda s: events.put(s))
        session.declare_subscriber(f"fleet/{mission}/vehicle/*/telemetry", lambda s: events.put(s))
        seen = 0
        while seen < wanted:
            try:
                sample = events.get(timeout=60)
            except queue.Empty:
                print("no model within a minute", file=sys.stderr)
                return 1
            m = cbor2.loads(sample.payload.to_bytes())
            if m["type"] == "model":
                variance = np.frombuffer(m["variance"], "<f4")
                print(f"model v{m['version']} epoch {m['epoch']} step {m['step']}: rank {len(m['eigenvalues'])}, "
                      f"mean reported variance {variance.mean():.3e}")
                seen += 1
            elif m["type"] == "telemetry":
                x, y = m["position"]
                print(f"telemetry {m['vehicle']} step {m['step']}: at ({x:.1f}, {y:.1f}) m, outbox {m['outbox_depth']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
