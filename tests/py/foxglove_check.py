"""A recording's Foxglove channels decoded against Foxglove's published schemas.

Usage: foxglove_check.py RECORDING ESTIMATE_NC LAT0 LON0 SIZE_E SIZE_N

Every channel under /foxglove is decoded: protobuf ones with the classes of the
`foxglove-schemas-protobuf` package (Foxglove's own), chosen by the schema's name, JSON ones
validated against the JSON schema the channel carries. Each vehicle's LocationFix is checked
against the telemetry it was made from (the position, placed on the Earth here on its own:
spherical Earth of the WGS-84 equatorial radius, flat over the site, the site's physical
extent over the grid's). Each Grid is checked against estimate.nc at the step of the model it
came from (the /foxglove/model message recorded with it). Prints "ok" and counts.
"""
import json
import math
import sys

import cbor2
import jsonschema
import numpy as np
import xarray as xr
from foxglove_schemas_protobuf.GeoJSON_pb2 import GeoJSON
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from mcap.reader import make_reader

PUBLISHED = {"foxglove.LocationFix": LocationFix, "foxglove.Grid": Grid, "foxglove.GeoJSON": GeoJSON}
R = 6378137.0


def main(rec, nc, lat0, lon0, size_e, size_n):
    ds = xr.open_dataset(nc)
    telemetry, fixes, grids, models, counts = {}, {}, {}, [], {}
    with open(rec, "rb") as f:
        reader = make_reader(f)
        # The model grid (grid metres) from the recording's header: the file's axes are physical.
        header = {m.name: m.metadata for m in reader.iter_metadata()}["hetfleet"]
        rows, cols, cell = int(header["rows"]), int(header["cols"]), float(header["cell_m"])
        assert (rows, cols) == (ds.sizes["y"], ds.sizes["x"])
        scale = (size_e / (cols * cell), size_n / (rows * cell))
        for schema, channel, message in reader.iter_messages():
            topic = channel.topic
            if topic.endswith("/telemetry"):
                t = cbor2.loads(message.data)
                if (t.get("autopilot") or {}).get("link") != "connecting":
                    telemetry.setdefault(t["vehicle"], []).append(t)
            if not topic.startswith("/foxglove"):
                continue
            counts[topic.split("/")[2]] = counts.get(topic.split("/")[2], 0) + 1
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema", (topic, schema.encoding)
                value = json.loads(message.data)
                jsonschema.validate(value, json.loads(schema.data))
                if topic == "/foxglove/model":
                    models.append(value)
                continue
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf", topic
            msg = PUBLISHED[schema.name]()
            msg.ParseFromString(message.data)
            if schema.name == "foxglove.LocationFix":
                fixes.setdefault(topic.rsplit("/", 1)[1], []).append(msg)
            elif schema.name == "foxglove.Grid":
                grids.setdefault(topic.rsplit("/", 1)[1], []).append(msg)
            else:
                doc = json.loads(msg.geojson)
                assert doc["type"] == "FeatureCollection" and doc["features"], topic
    assert fixes and set(fixes) == set(telemetry), (sorted(fixes), sorted(telemetry))
    for v, fs in fixes.items():
        assert len(fs) == len(telemetry[v]), (v, len(fs), len(telemetry[v]))
        for fix, t in zip(fs, telemetry[v]):
            north, east = t["position"][1] * scale[1], t["position"][0] * scale[0]
            lat = lat0 + math.degrees(north / R)
            lon = lon0 + math.degrees(east / (R * math.cos(math.radians(lat0))))
            assert abs(fix.latitude - lat) < 1e-9 and abs(fix.longitude - lon) < 1e-9, (v, fix, lat, lon)
            assert fix.timestamp.seconds > 1.7e9
    steps = list(ds["step"].values)
    for name, var in [("estimate", "estimate"), ("std", "variance"), ("truth", "truth")]:
        gs = grids[name]
        assert len(gs) == len(models), (name, len(gs), len(models))
        for g, m in zip(gs, models):
            assert g.column_count == cols and g.cell_stride == 4 and g.row_stride == 4 * cols, g
            assert g.fields[0].name == name and g.fields[0].type == 7, g.fields  # FLOAT32
            assert abs(g.cell_size.x - cell) < 1e-12 and g.frame_id == "site"
            got = np.frombuffer(g.data, dtype="<f4").reshape(rows, cols)
            want = ds[var].values[steps.index(m["step"])]
            if name == "std":
                want = np.sqrt(want)
            both = np.isfinite(want)
            assert np.array_equal(np.isfinite(got), both), name
            # The grid is f32: within its rounding of the file's f64.
            err = np.max(np.abs(got[both] - want[both]) / np.maximum(np.abs(want[both]), 1e-30))
            assert err < 1e-6, (name, m["step"], err)
    print("ok", json.dumps(counts, sort_keys=True))


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], *map(float, a[2:6]))
