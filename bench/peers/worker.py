#!/usr/bin/env python3
"""The peers' side of `fleet bench peers`: one timed run at a time, on the data hetfleet wrote.

hetfleet starts this once, with the BLAS pinned to one thread, and alternates its own runs
with requests here, so both sides are timed on the same data in the same minutes. One JSON
request per line on stdin, one JSON answer per line on stdout:

  {"op": "hello"}
      -> {"versions": {...}, "blas": [...]}
  {"op": "table1", "data": "z.npy", "init": 100, "tau": 10, "peer": "general_r10", "eig": true}
      -> {"seconds": s, "eigs": [[re, im], ...]}   (the final operator's eigenvalues)
  {"op": "qr", "basis": "basis.npy", "k": 10}
      -> {"seconds": s, "pivots": [...]}           (pysensors QR().fit, its first k sensors)

The Table 1 runners are paper_table.py's (numpy references in dmd_ref.py, PyDMD, odmd), so
what is timed here is what that script times. A missing package exits 3 with its name on
stderr, before any request is read.
"""
import gc
import json
import os
import sys
import time

try:
    import numpy as np
    import pysensors as ps
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import paper_table as pt
except ImportError as exc:  # the caller says how to install the peers
    print(f"missing: {exc.name}", file=sys.stderr)
    sys.exit(3)

RUNNERS = {
    "batch_svd": lambda Z, T, i, tau, e: pt.run_batch(lambda: pt.BatchSVD(), Z, T, i, tau, e),
    "pydmd_full": lambda Z, T, i, tau, e: pt.run_pydmd(-1, Z, T, i, tau, e),
    "general": lambda Z, T, i, tau, e: pt.run_general(None, "direct", Z, T, i, tau, e),
    "general_r10": lambda Z, T, i, tau, e: pt.run_general(10, "direct", Z, T, i, tau, e),
    "longterm": lambda Z, T, i, tau, e: pt.run_longterm(1.0, Z, T, i, tau, e),
    "odmd": lambda Z, T, i, tau, e: pt.run_odmd(1.0, Z, T, i, tau, e),
}

_loaded = {}


def load(path):
    if path not in _loaded:
        _loaded[path] = np.asfortranarray(np.load(path))
    return _loaded[path]


def eigenvalues(obj):
    """The final operator's eigenvalues, whichever peer made it."""
    if hasattr(obj, "eigs"):  # PyDMD
        lam = obj.eigs
    elif hasattr(obj, "atilde_or_a"):  # dmd_ref
        lam = np.linalg.eigvals(obj.atilde_or_a())
    else:  # odmd
        lam = np.linalg.eigvals(obj.A)
    return [[float(z.real), float(z.imag)] for z in lam]


def table1(req):
    Z = load(req["data"])
    T = Z.shape[1] - 1
    gc.collect()
    seconds, _, obj = RUNNERS[req["peer"]](Z, T, req["init"], req["tau"], req["eig"])
    return {"seconds": seconds, "eigs": eigenvalues(obj)}


def qr(req):
    basis = load(req["basis"])
    gc.collect()
    t0 = time.perf_counter()
    model = ps.optimizers.QR().fit(basis)
    seconds = time.perf_counter() - t0
    return {"seconds": seconds, "pivots": [int(p) for p in model.get_sensors()[: req["k"]]]}


def hello(_):
    return {"versions": pt.versions(), "blas": pt.blas_info()}


OPS = {"hello": hello, "table1": table1, "qr": qr}


def main():
    for line in sys.stdin:
        req = json.loads(line)
        try:
            answer = OPS[req["op"]](req)
        except Exception as exc:  # one answer per request, whatever happens
            answer = {"error": f"{type(exc).__name__}: {exc}"}
        print(json.dumps(answer), flush=True)


if __name__ == "__main__":
    main()
