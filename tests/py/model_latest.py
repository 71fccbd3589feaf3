"""A Python eclipse-zenoh client reads the fleet's model: it asks `fleet/<mission>/model/latest`
(the server answers with the newest model), decodes the CBOR, and checks the shapes and the
eigenvalues against the server's summary.json. Exit 0 when every check holds.

usage: model_latest.py <endpoint> <mission> <summary.json>
"""
import json
import os
import sys

import cbor2
import numpy as np
import zenoh


def main():
    endpoint, mission, summary_path = sys.argv[1:4]
    summary = json.load(open(summary_path))
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        replies = list(session.get(f"fleet/{mission}/model/latest", timeout=10.0))
    ok = [r.ok for r in replies if r.ok is not None]
    assert ok, f"no model reply ({len(replies)} replies)"
    sample = ok[0]
    assert str(sample.encoding).startswith("application/cbor"), sample.encoding
    m = cbor2.loads(sample.payload.to_bytes())
    assert m["v"] == 4 and m["type"] == "model", (m["v"], m["type"])
    # The model's per-cell arrays are packed little-endian f32 bytes (schema 4;
    # mission/src/protocol/floats.rs); eigenvalues and amplitudes are f64 lists.
    f4 = lambda k: np.frombuffer(m[k], "<f4")
    rows, cols = m["grid"]["rows"], m["grid"]["cols"]
    lam = np.array(m["eigenvalues"], dtype=float)
    r = lam.shape[0]
    modes = f4("modes_re").reshape(rows * cols, r) + 1j * f4("modes_im").reshape(rows * cols, r)
    assert r == summary["rank"], (r, summary["rank"])
    assert len(m["amplitudes"]) == r and len(f4("variance")) == rows * cols
    # The estimate's reported variance and the forecast's to the next boat step, per cell.
    var, fvar = f4("variance"), f4("forecast_variance")
    assert fvar.shape == var.shape and m["forecast_steps"] > 0, (fvar.shape, m["forecast_steps"])
    assert np.all(var >= 0) and np.all(fvar >= 0) and np.all(np.isfinite(fvar)), "variances finite and >= 0"
    assert m["version"] == summary["model_version"], (m["version"], summary["model_version"])
    # The fused estimate and its variance at the model's step: the server's own f64 arrays of
    # that step (estimate.npy / variance.npy beside summary.json) rounded to f32, bit for bit.
    run = os.path.dirname(summary_path)
    step = m["step"]
    for key in ("estimate", "variance"):
        kept = np.load(os.path.join(run, f"{key}.npy"))
        sent = f4(key)
        assert sent.shape == (rows * cols,), (key, sent.shape)
        assert np.array_equal(kept[step].reshape(-1).astype(np.float32), sent), f"{key} on the wire differs from the server's {key}.npy at step {step}"

    expected = np.array(summary["eigenvalues"], dtype=float)
    assert np.allclose(lam, expected, rtol=0, atol=1e-12), (lam, expected)
    # The forecast a client would make: Phi diag(lambda)^t alpha, finite and real-valued.
    alpha = np.array(m["amplitudes"], dtype=float) @ np.array([1, 1j])
    x1 = modes @ ((lam @ np.array([1, 1j])) * alpha)
    assert np.all(np.isfinite(x1)) and np.abs(x1.imag).max() < 1e-6 * max(1.0, np.abs(x1.real).max())
    # The modes hold the field's anomalies about its mean level: level + Phi alpha is the field at
    # the model's step (the amplitudes are fitted to it), far closer to the estimate there than
    # the anomaly alone.
    level = m["level"]
    assert np.isfinite(level) and level != 0.0, level
    wet = np.ones(rows * cols, bool)
    wet[np.array(m.get("land", []), dtype=int)] = False
    x0 = (modes @ alpha).real
    est = f4("estimate").astype(float)
    with_level = np.abs(level + x0 - est)[wet].mean()
    without = np.abs(x0 - est)[wet].mean()
    assert with_level < 0.5 * without, (with_level, without, level)
    print(f"python eclipse-zenoh {zenoh.__name__}: model v{m['version']} rank {r} on {rows}x{cols}, eigenvalues match")


if __name__ == "__main__":
    main()
