#!/usr/bin/env python3
"""The live view's cost (issue 20): the model server's epoch latency on the default mission
without the view, and with `fleet up --web` and three pages open (server-sent event clients),
plus the bytes pushed to each page per epoch. Paced (`step_ms`) so the pages are connected
for the whole mission. Usage: python3 bench/web_cost.py [--step-ms 50] [--runs 2]
Run from the workspace root after `cargo build --release --workspace`."""
import argparse, http.client, json, os, re, shutil, subprocess, tempfile, threading, time

def page(port, stats, stop):
    """One page: reads /api/events until the watch goes away, counting bytes and events."""
    while not stop.is_set():
        try:
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            c.request("GET", "/api/events")
            r = c.getresponse()
            while True:
                line = r.fp.readline()
                if not line:
                    return
                stats["bytes"] += len(line)
                if line.startswith(b"event: "):
                    kind = line[7:].strip().decode()
                    stats[kind] = stats.get(kind, 0) + 1
        except OSError:
            if stats["bytes"]:
                return
            time.sleep(0.05)

def run(mission, out, web_port=None, pages=0):
    args = ["target/release/fleet", "up", mission, "--out", out]
    if web_port:
        args += ["--web", f"127.0.0.1:{web_port}", "--web-linger-s", "0"]
    stop, stats, threads = threading.Event(), [{"bytes": 0} for _ in range(pages)], []
    p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for s in stats:
        t = threading.Thread(target=page, args=(web_port, s, stop), daemon=True)
        t.start()
        threads.append(t)
    rc = p.wait()
    stop.set()
    for t in threads:
        t.join(timeout=5)
    assert rc == 0, f"fleet up failed ({rc})"
    summary = json.load(open(os.path.join(out, "summary.json")))
    return summary["latency_ms"], stats

def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--step-ms", type=int, default=50)
    ap.add_argument("--runs", type=int, default=2)
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="hetfleet-webcost-")
    text = open("config/mission.toml").read()
    text = re.sub(r"step_ms = \d+", f"step_ms = {a.step_ms}", text)
    mission = os.path.join(tmp, "mission.toml")
    open(mission, "w").write(text)
    rows = []
    for i in range(a.runs):
        for label, port, pages in (("no view", None, 0), ("view + 3 pages", 8800 + i, 3)):
            lat, stats = run(mission, os.path.join(tmp, f"run-{i}-{pages}"), port, pages)
            rows.append((label, lat, stats))
            pushed = ""
            if stats:
                epochs = lat["count"]
                per_page = sum(s["bytes"] for s in stats) / len(stats)
                pushed = f"; per page {per_page / 1e3:.0f} kB in all, {per_page / epochs / 1e3:.1f} kB per epoch ({stats[0].get('fields', 0)} field pushes, {stats[0].get('state', 0)} state pushes)"
            print(f"run {i + 1} {label:15s}: epoch latency p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms over {lat['count']} epochs{pushed}", flush=True)
    shutil.rmtree(tmp, ignore_errors=True)

if __name__ == "__main__":
    main()
