"""Per-frame cost of calling rgbid from Python, against the Rust call on the same frames.

For every frame, the wall time of `Odometry.track` / `Slam.process` as Python sees it is set
against `rust_ms`, the time the binding measured inside the library for that call (building
the frame from the numpy buffers with `RgbdFrame::from_buffers`, then tracking it: what a
Rust program embedding rgbid does per frame). The difference is what Python adds: argument
checks, releasing and taking back the interpreter lock, building the result dict and arrays.
Frames are rendered before timing, so decoding is not in either figure.

    python benchmarks/overhead.py                       # odometry and SLAM, 320x240, CPU
    python benchmarks/overhead.py --json ../docs/results/python_overhead.json

Prints medians over the frames (the first frames, which allocate, are skipped as warm-up).
Goal: overhead under 5 % of the Rust call.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

import rgbid


def measure(system: str, frames, camera, backend: str, warmup: int):
    if system == "odometry":
        obj = rgbid.Odometry(camera, backend=backend)
        call = obj.track
    else:
        obj = rgbid.Slam(camera, backend=backend)
        call = obj.process
    wall, rust = [], []
    for i, (t, image, depth, factor) in enumerate(frames):
        t0 = time.perf_counter()
        r = call(image, depth, factor, t)
        dt = (time.perf_counter() - t0) * 1e3
        if i >= warmup:
            wall.append(dt)
            rust.append(r["rust_ms"])
    if system == "slam":
        obj.finish()
    over = [w - r for w, r in zip(wall, rust)]
    med_rust = statistics.median(rust)
    med_over = statistics.median(over)
    return {
        "system": system,
        "backend": obj.backend,
        "frames": len(wall),
        "python_ms": statistics.median(wall),
        "rust_ms": med_rust,
        "overhead_ms": med_over,
        "overhead_pct": 100.0 * med_over / med_rust,
    }


def machine():
    cpu = "?"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    os_name = platform.platform()
    try:
        for line in open("/etc/os-release"):
            if line.startswith("PRETTY_NAME="):
                os_name = line.split("=", 1)[1].strip().strip('"') + ", Linux " + platform.release()
    except OSError:
        pass
    return {"cpu": cpu, "logical_cores": os.cpu_count(), "os": os_name, "gpu_adapters": []}


def git(*args):
    try:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=120, help="frames of the generated sequence (30 per second)")
    p.add_argument("--width", type=int, default=320, help="frame width in pixels (height 3/4 of it)")
    p.add_argument("--warmup", type=int, default=5, help="frames left out of the medians")
    p.add_argument("--backend", default="cpu", choices=["auto", "gpu", "cpu"])
    p.add_argument("--systems", nargs="+", default=["odometry", "slam"], choices=["odometry", "slam"])
    p.add_argument("--json", default=None, help="write the report here (for scripts/results.py)")
    a = p.parse_args(argv)

    seq = rgbid.synth.render("office", "handheld", a.frames, 7, width=a.width)
    frames = list(seq)  # rendered before any timing
    h, w = frames[0][2].shape
    print(f"{len(frames)} generated frames {w}x{h}, backend {a.backend}, medians over frames {a.warmup}..")
    print(f"{'system':<9} {'python ms':>10} {'rust ms':>9} {'overhead ms':>12} {'overhead %':>11}")
    rows = []
    for system in a.systems:
        r = measure(system, frames, seq.camera, a.backend, a.warmup)
        r.update(width=w, height=h)
        rows.append(r)
        print(f"{system:<9} {r['python_ms']:>10.3f} {r['rust_ms']:>9.3f} {r['overhead_ms']:>12.4f} {r['overhead_pct']:>10.2f}%")
    if a.json:
        doc = {
            "benchmark": "python-overhead",
            "meta": {
                "command": "python " + " ".join(["python/benchmarks/overhead.py", *(argv or __import__("sys").argv[1:])]),
                "commit": git("rev-parse", "--short", "HEAD"),
                "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
                "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "load_average": [round(x, 2) for x in os.getloadavg()],
                "machine": machine(),
                "rgbid_version": rgbid.__version__,
                "python": platform.python_version(),
            },
            "sequence": f"office:handheld, {len(frames)} frames {w}x{h}, seed 7",
            "warmup": a.warmup,
            "rows": rows,
        }
        Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {a.json}")
    return rows


if __name__ == "__main__":
    main()
