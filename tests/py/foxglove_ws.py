"""A Foxglove WebSocket client (subprotocol foxglove.websocket.v1) on a live mission.

Usage: foxglove_ws.py URL VEHICLES [refused|connect]

Connects, subscribes to every /foxglove channel as it is advertised, and decodes what arrives
with Foxglove's published schemas (foxglove-schemas-protobuf) until it has a LocationFix from
each of VEHICLES (comma-separated) and an estimate Grid; prints "ok" and what it got. With
"refused", expects the server to refuse the connection (HTTP 401) and prints "refused"; with
"connect", only checks the handshake and prints "connected".

The Foxglove SDK's server can answer a subscription that follows an advertisement too quickly with
"Unknown channel ID" (it sends the advertisement before it records it); the client then subscribes
to that channel again, as a client that must not miss a vehicle would, and says how often it did.
"""
import asyncio
import json
import struct
import sys

import websockets
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix


async def main(url, vehicles, mode):
    refused = mode == "refused"
    for _ in range(300):  # the view comes up with the mission's nodes
        try:
            ws = await websockets.connect(url, subprotocols=["foxglove.websocket.v1"], max_size=None, open_timeout=10)
            break
        except ConnectionRefusedError:
            await asyncio.sleep(0.1)
        except websockets.exceptions.InvalidStatus as e:
            assert refused and e.response.status_code == 401, e
            print("refused", e.response.status_code)
            return
    else:
        raise AssertionError(f"nothing listens at {url}")
    assert not refused, "connected without the credential"
    assert ws.subprotocol == "foxglove.websocket.v1", ws.subprotocol
    if mode == "connect":
        await ws.close()
        print("connected")
        return
    channels, subs, fixes, grids, again = {}, {}, {}, 0, 0
    async with ws:
        while not (set(vehicles) <= set(fixes) and grids):
            msg = await asyncio.wait_for(ws.recv(), 60)
            if isinstance(msg, str):
                m = json.loads(msg)
                unknown = m["op"] == "status" and m.get("message", "").startswith("Unknown channel ID: ")
                if unknown:
                    cid = int(m["message"].rsplit(" ", 1)[1])
                    sid = next(s for s, c in subs.items() if c["id"] == cid)
                    await asyncio.sleep(0.05)
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": sid, "channelId": cid}]}))
                    again += 1
                if m["op"] != "advertise":
                    continue
                new = []
                for c in m["channels"]:
                    if c["topic"].startswith("/foxglove") and c["id"] not in channels:
                        channels[c["id"]] = c
                        sid = len(subs) + 1
                        subs[sid] = c
                        new.append({"id": sid, "channelId": c["id"]})
                if new:
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            assert msg[0] == 0x01, msg[0]  # messageData
            sid, _log_ns = struct.unpack_from("<IQ", msg, 1)
            c, payload = subs[sid], msg[13:]
            if c["schemaName"] == "foxglove.LocationFix":
                fix = LocationFix()
                fix.ParseFromString(payload)
                assert -90 <= fix.latitude <= 90 and fix.frame_id == c["topic"].rsplit("/", 1)[1], fix
                fixes[fix.frame_id] = (fix.latitude, fix.longitude)
            elif c["topic"] == "/foxglove/estimate":
                g = Grid()
                g.ParseFromString(payload)
                assert g.column_count > 0 and len(g.data) == g.row_stride * (len(g.data) // g.row_stride), g
                grids += 1
    topics = sorted(c["topic"] for c in channels.values())
    print("ok", json.dumps({"fixes": sorted(fixes), "grids": grids, "channels": topics, "resubscribed": again}))


if __name__ == "__main__":
    a = sys.argv[1:]
    asyncio.run(main(a[0], a[1].split(","), a[2] if len(a) > 2 else "data"))
