#!/usr/bin/env python3
"""Camera rate on real data: `rgbid slam` and `rgbid odometry` wall time against camera time.

For each real sequence, `rgbid slam SEQ --backend cpu --out DIR` runs `--runs` times; the wall
time is the whole process (start-up, loading and decoding, the back-end, the final
optimisation and the output files), measured around it; camera time is the sequence's first
to last time stamp plus one frame period (30 Hz). Per-frame front-end times (median, 95th
percentile, maximum) come from the run folder's `timing.csv`. `rgbid odometry` runs the same
way (process wall time per frame, decoding included), and OpenCV's RGB_DEPTH odometry
(`../shared/eval/peer_odometry.py --methods cv_rgbd`) once per sequence in the same script run
when `--python` names a Python with OpenCV; its figure is its per-frame compute median.
Medians over the runs; the 1-minute load average before each run is recorded, and before
and after each sequence's runs the cores the machine delivers: a single-threaded Python loop timed alone, then
two copies at once (`cores = t_alone / t_1 + t_alone / t_2`: 2.0 on two free cores; a load
average does not show a neighbour sharing the host's cores).
Writes docs/results/camera_rate.json (rendered by scripts/results.py).

Usage: python3 scripts/camera_rate.py [--bin target/release/rgbid] [--runs 5]
       [--python /work/.venv-peers/bin/python] [--json docs/results/camera_rate.json]
Standard library only.
"""
import argparse
import csv
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

from layouts import ROOT, meta

DATA = ROOT.parent / "shared" / "data" / "rgbd"
SEQUENCES = [("tum_fr1_rpy_0_199", ["--camera", "tum_fr1"]), ("redkitchen_0_299", [])]


def quantile(values, q):
    v = sorted(values)
    return v[min(len(v) - 1, int(q * len(v)))] if v else None


def timed(cmd):
    load = os.getloadavg()[0]
    t = time.monotonic()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.monotonic() - t
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stdout}{r.stderr}")
    return wall, load


SPIN = "import time\nt = time.perf_counter()\nx = 0\nfor i in range(6_000_000):\n    x += i\nprint(time.perf_counter() - t)"


def cores_delivered():
    """Cores the machine gives two single-threaded processes at once (median of 3 probes)."""
    def spin(n):
        procs = [subprocess.Popen([sys.executable, "-c", SPIN], stdout=subprocess.PIPE, text=True)
                 for _ in range(n)]
        return [float(p.communicate()[0]) for p in procs]
    probes = []
    for _ in range(3):
        alone = spin(1)[0]
        probes.append(sum(alone / t for t in spin(2)))
    return statistics.median(probes)


def peer(python, seq, out):
    script = ROOT.parent / "shared" / "eval" / "peer_odometry.py"
    r = subprocess.run([python, str(script), str(seq), str(out), "--methods", "cv_rgbd"],
                       capture_output=True, text=True)
    for line in r.stdout.splitlines():
        if line.startswith("{"):
            d = json.loads(line)
            if d.get("method") == "cv_rgbd":
                return d
    print(f"OpenCV did not run on {seq.name}:\n{r.stdout[-2000:]}{r.stderr[-2000:]}", file=sys.stderr)
    return None


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bin", default=str(ROOT / "target/release/rgbid"))
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--python", default=None, help="a Python with OpenCV for the peer row")
    p.add_argument("--json", default=str(ROOT / "docs/results/camera_rate.json"))
    a = p.parse_args()
    if a.python:
        # Checked before the first run: the peer row comes after minutes of rgbid runs.
        try:
            r = subprocess.run([a.python, "-c", "import cv2"], capture_output=True, text=True)
        except OSError as e:
            p.error(f"--python {a.python}: {e}; set up the peers as ../shared/eval/README.md says")
        if r.returncode != 0:
            last = (r.stderr.strip().splitlines() or [""])[-1]
            p.error(f"--python {a.python} cannot import cv2 (OpenCV): {last}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, extra in SEQUENCES:
            seq = DATA / name
            slam_walls, odo_walls, loads, fe = [], [], [], {"p50": [], "p95": [], "max": []}
            summary = None
            cores = cores_delivered()
            for i in range(a.runs):
                out = pathlib.Path(tmp) / f"{name}-{i}"
                wall, load = timed([a.bin, "slam", str(seq), "--backend", "cpu", "--out", str(out), *extra])
                slam_walls.append(wall)
                loads.append(load)
                with open(out / "timing.csv", newline="") as f:
                    frames = list(csv.DictReader(f))
                ms = [float(r["frontend_ms"]) for r in frames]
                for k, q in (("p50", 0.5), ("p95", 0.95), ("max", 1.0)):
                    fe[k].append(quantile(ms, q))
                stamps = [float(r["timestamp"]) for r in frames]
                summary = json.loads((out / "summary.json").read_text())
                traj = pathlib.Path(tmp) / f"{name}-odo-{i}.txt"
                wall, load = timed([a.bin, "odometry", str(seq), "--backend", "cpu", "--out", str(traj), *extra])
                odo_walls.append(wall)
                loads.append(load)
            cores = [cores, cores_delivered()]
            camera_s = stamps[-1] - stamps[0] + 1.0 / 30.0
            n = len(stamps)
            cv = peer(a.python, seq, pathlib.Path(tmp) / f"{name}-cv") if a.python else None
            odo_ms = statistics.median(odo_walls) / n * 1e3
            row = {
                "sequence": name,
                "frames": n,
                "camera_s": camera_s,
                "slam_wall_s_median": statistics.median(slam_walls),
                "slam_wall_s": slam_walls,
                "slam_keyframes": summary["keyframes"],
                "slam_loops": summary.get("loops_accepted"),
                "slam_ate_m": summary.get("slam_ate_rmse"),
                "frontend_ms_p50": statistics.median(fe["p50"]),
                "frontend_ms_p95": statistics.median(fe["p95"]),
                "frontend_ms_max": statistics.median(fe["max"]),
                "odometry_wall_ms_per_frame": odo_ms,
                "opencv_ms_per_frame": cv.get("ms_median") if cv else None,
                "load_1min": loads,
                "cores_delivered": cores,
            }
            if row["opencv_ms_per_frame"]:
                row["opencv_over_rgbid"] = row["opencv_ms_per_frame"] / odo_ms
            rows.append(row)
            print(f"{name}: slam {row['slam_wall_s_median']:.2f} s for {camera_s:.2f} s of camera; "
                  f"front-end p95 {row['frontend_ms_p95']:.1f} ms; odometry {odo_ms:.1f} ms/frame"
                  + (f", OpenCV {row['opencv_ms_per_frame']:.1f}" if cv else "")
                  + f"; cores delivered of 2 before / after: {cores[0]:.2f} / {cores[1]:.2f}")
    doc = {"benchmark": "camera-rate", "meta": meta("camera_rate.py", a.bin), "runs": a.runs,
           "backend": "cpu", "rows": rows}
    pathlib.Path(a.json).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
