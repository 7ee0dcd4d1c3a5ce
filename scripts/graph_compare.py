#!/usr/bin/env python3
"""Runs `rgbid graph bench --json` and GTSAM (../shared/eval/peer_posegraph.py) on the same
pose-graph files in one session and prints a ratio table: F / f*, chi2, seconds and the time
ratio rgbid / best GTSAM run. Usage:
  scripts/graph_compare.py [--rgbid target/debug/rgbid] [--data ../shared/data/posegraph] [FILTER...]
GTSAM must be importable by the Python running peer_posegraph.py (default /work/.venv-peers)."""
import argparse, json, os, subprocess, sys

ap = argparse.ArgumentParser()
ap.add_argument("--rgbid", default="target/debug/rgbid")
ap.add_argument("--data", default="../shared/data/posegraph")
ap.add_argument("--python", default="/work/.venv-peers/bin/python")
ap.add_argument("--peer", default="../shared/eval/peer_posegraph.py")
ap.add_argument("filters", nargs="*", default=["se-sync/"])
a = ap.parse_args()

cmd = [a.rgbid, "--log", "warn", "graph", "bench", "--data", a.data, "--json"] + sum((["--only", f] for f in a.filters), [])
ours = {}
for line in subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.splitlines() + \
        subprocess.run(cmd, capture_output=True, text=True).stderr.splitlines():
    line = line.strip()
    if line.startswith("{"):
        o = json.loads(line); ours[o["file"]] = o
rows = []
for key, o in sorted(ours.items()):
    if not key.endswith(".g2o"):
        continue
    path = os.path.join(a.data, key)
    peer = subprocess.run([a.python, a.peer, path], capture_output=True, text=True)
    runs = [json.loads(l) for l in peer.stdout.splitlines() if l.startswith("{")]
    ok = [r for r in runs if "s" in r]
    best = min(ok, key=lambda r: r["F"]) if ok else None
    lm = next((r for r in ok if r["method"] == "gtsam_lm"), None)
    rows.append((key, o, best, lm))
print(f"{'file':30} {'F rgbid':>11} {'F/f*':>7} {'chi2 rgbid':>11} {'s rgbid':>8} | {'GTSAM best':>16} {'F':>11} {'chi2':>11} {'s':>7} | {'chi2 ratio':>10} {'time ratio':>10}")
for key, o, best, lm in rows:
    fr = f"{o['F']/o['fstar']:.4f}" if o.get("fstar") else "-"
    if best:
        print(f"{key:30} {o['F']:11.5g} {fr:>7} {o['chi2']:11.5g} {o['s']:8.3f} | {best['method']:>16} {best['F']:11.5g} {best['chi2']:11.5g} {best['s']:7.3f} | {o['chi2']/best['chi2']:10.4f} {o['s']/best['s']:10.3f}")
    else:
        print(f"{key:30} {o['F']:11.5g} {fr:>7} {o['chi2']:11.5g} {o['s']:8.3f} | {'(no GTSAM run)':>16}")
