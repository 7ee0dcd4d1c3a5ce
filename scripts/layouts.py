#!/usr/bin/env python3
"""`rgbid slam` on one generated sequence written in every dataset layout.

`rgbid synth --layout L` writes the same frames (same scene, trajectory, seed and sensor noise)
as a TUM, ETH3D, 7-Scenes, ScanNet and Replica (NICE-SLAM) folder; `rgbid slam DIR` runs on
each with the layout detected from the folder (no --format), and its `summary.json` gives the
ATE against the ground truth the layout itself carries. 7-Scenes and Replica folders hold no
camera of the rendered size, so they run with the DROID-SLAM `calib.txt` the writer leaves
(`--camera DIR/calib.txt --calib-format droid`). Writes docs/results/layouts.json (rendered by
scripts/results.py).

Usage: python3 scripts/layouts.py [--bin target/release/rgbid] [--frames 300] [--width 320]
       [--out /tmp/rgbid-layouts] [--json docs/results/layouts.json]
Standard library only.
"""
import argparse
import datetime
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
LAYOUTS = ["tum", "eth3d", "7scenes", "scannet", "replica"]


def machine():
    cpu = "?"
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    osname = platform.platform()
    try:
        rel = dict(
            line.split("=", 1) for line in pathlib.Path("/etc/os-release").read_text().splitlines() if "=" in line
        )
        osname = f"{rel.get('PRETTY_NAME', '?').strip(chr(34))}, Linux {platform.release()}"
    except OSError:
        pass
    return {"cpu": cpu, "logical_cores": os.cpu_count(), "os": osname, "gpu_adapters": []}


def git(*args):
    r = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else None


def meta(script, binary, load=None):
    """The report's provenance: the command line of `scripts/SCRIPT`, commit, date, load
    average (`load`, else now), machine and the version of the rgbid binary `binary`."""
    return {
        "command": f"python3 scripts/{script} " + " ".join(sys.argv[1:]),
        "commit": git("rev-parse", "--short", "HEAD") or "unknown",
        # Benchmark outputs (docs/results) are not source changes.
        "dirty": bool(git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)docs/results")),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "load_average": [round(x, 2) for x in (load or os.getloadavg())],
        "machine": machine(),
        "rgbid_version": (subprocess.run([binary, "--version"], capture_output=True, text=True)
                          .stdout.split() or ["?"])[-1],
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bin", default=str(ROOT / "target/release/rgbid"))
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--out", default="/tmp/rgbid-layouts")
    p.add_argument("--json", default=str(ROOT / "docs/results/layouts.json"))
    a = p.parse_args()
    out = pathlib.Path(a.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    load_start = os.getloadavg()
    rows = []
    for layout in LAYOUTS:
        d = out / layout
        synth = [a.bin, "synth", "--scene", "office", "--trajectory", "handheld", "--frames",
                 str(a.frames), "--width", str(a.width), "--seed", str(a.seed), "--backend", "cpu",
                 "--layout", layout, "--out", str(d)]
        subprocess.run(synth, check=True, capture_output=True)
        run = out / f"run-{layout}"
        slam = [a.bin, "slam", str(d), "--out", str(run), "--backend", "cpu"]
        if layout in ("7scenes", "replica"):
            slam += ["--camera", str(d / "calib.txt"), "--calib-format", "droid"]
        r = subprocess.run(slam, capture_output=True, text=True, env={**os.environ, "RUST_LOG": "info"})
        if r.returncode != 0:
            sys.exit(f"{layout}: rgbid slam failed:\n{r.stdout}{r.stderr}")
        detected = f"{layout} layout, camera from" in r.stderr
        s = json.loads((run / "summary.json").read_text())
        rows.append({
            "layout": layout,
            "detected": detected,
            "frames": s["frames"],
            "keyframes": s["keyframes"],
            "loops": s.get("loops_accepted"),
            "ate_m": s.get("slam_ate_rmse"),
            "odometry_ate_m": s.get("odometry_ate_rmse"),
            "wall_s": s["wall_s"],
            "fps": s["frames"] / s["wall_s"] if s["wall_s"] > 0 else None,
        })
        print(f"{layout:8} detected {detected} frames {s['frames']} keyframes {s['keyframes']} "
              f"ATE {s.get('slam_ate_rmse')} m, {rows[-1]['fps']:.1f} fps")
    doc = {"benchmark": "layouts", "meta": meta("layouts.py", a.bin, load_start),
           "scene": "office", "trajectory": "handheld", "frames": a.frames, "width": a.width,
           "height": a.width * 3 // 4, "seed": a.seed, "backend": "cpu", "rows": rows}
    pathlib.Path(a.json).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
