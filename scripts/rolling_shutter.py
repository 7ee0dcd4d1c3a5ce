#!/usr/bin/env python3
"""The rolling-shutter readout of the Kinect v1 presets: a sweep on the two real sequences.

For each readout (seconds from the first row to the last), `rgbid odometry` and `rgbid slam`
run on fr1/rpy 0-199 and redkitchen 0-299 with a camera file that is the sequence's usual
camera (`tum_fr1` for fr1/rpy, redkitchen's `calib.txt` intrinsics) plus that readout; both
are scored by `rgbid eval` against the ground truth. OpenCV's RGB_DEPTH odometry
(`../shared/eval/peer_odometry.py --methods cv_rgbd`) runs once per sequence in the same
script run and its trajectory is scored by the same evaluator. The row to choose is the one
with the best mean of (odometry ATE / OpenCV's ATE) over the two sequences, the rule by which
the odometry's defaults are chosen. Writes docs/results/rolling_shutter.json (rendered by
scripts/results.py).

Usage: python3 scripts/rolling_shutter.py --python /work/.venv-peers/bin/python
       [--bin target/release/rgbid] [--readouts 0 0.005 0.01 ...]
Standard library only (the peer needs a Python with OpenCV).
"""
import argparse
import json
import pathlib
import subprocess
import sys
import tempfile

from layouts import ROOT, meta

DATA = ROOT.parent / "shared" / "data" / "rgbd"
# name, the camera file's lines before the readout.
SEQUENCES = [
    ("tum_fr1_rpy_0_199", "preset = tum_fr1\n"),
    ("redkitchen_0_299", "fx = 585\nfy = 585\ncx = 320\ncy = 240\ndepth_factor = 5000\n"),
]


def run(cmd):
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(map(str, cmd))} failed ({r.returncode}):\n{r.stdout}{r.stderr}")
    return r.stdout


def score(binary, seq, traj):
    d = json.loads(run([binary, "eval", seq / "groundtruth.txt", traj, "--json"]))
    return d["ate"]["translation"]["rmse"], d["rpe"]["translation_m_per_s"]["rmse"]


def opencv(python, binary, seq, out):
    script = ROOT.parent / "shared" / "eval" / "peer_odometry.py"
    run([python, script, seq, out, "--methods", "cv_rgbd"])
    trajs = sorted(pathlib.Path(out).glob("*cv_rgbd*.txt"))
    if not trajs:
        sys.exit(f"OpenCV wrote no trajectory in {out}")
    return score(binary, seq, trajs[0])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bin", default=str(ROOT / "target/release/rgbid"))
    p.add_argument("--python", required=True, help="a Python with OpenCV for the peer")
    p.add_argument("--readouts", type=float, nargs="+",
                   default=[0.0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03, 0.04])
    p.add_argument("--json", default=str(ROOT / "docs/results/rolling_shutter.json"))
    a = p.parse_args()
    rows, peers = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        for name, camera in SEQUENCES:
            seq = DATA / name
            peers[name] = opencv(a.python, a.bin, seq, tmp / f"{name}-cv")
            print(f"{name}: OpenCV ATE {peers[name][0]:.4f} m, RPE {peers[name][1]:.4f} m/s", flush=True)
            for readout in a.readouts:
                cam = tmp / f"{name}-{readout}.cfg"
                cam.write_text(camera + f"readout = {readout}\n")
                traj = tmp / f"{name}-{readout}-odometry.txt"
                run([a.bin, "--log", "error", "odometry", seq, "--camera", cam, "--backend", "cpu",
                     "--out", traj])
                ate, rpe = score(a.bin, seq, traj)
                out = tmp / f"{name}-{readout}-slam"
                run([a.bin, "--log", "error", "slam", seq, "--camera", cam, "--backend", "cpu",
                     "--no-model", "--out", out])
                s = json.loads((out / "summary.json").read_text())
                slam_ate, _ = score(a.bin, seq, out / "trajectory.txt")
                rows.append({
                    "sequence": name, "readout_s": readout, "ate_m": ate, "rpe_m_per_s": rpe,
                    "ate_over_opencv": ate / peers[name][0], "slam_ate_m": slam_ate,
                    "slam_keyframes": s["keyframes"], "slam_loops": s.get("loops_accepted"),
                })
                print(f"{name} readout {readout * 1e3:.1f} ms: odometry ATE {ate:.4f} m "
                      f"({ate / peers[name][0]:.3f} of OpenCV), RPE {rpe:.4f} m/s; SLAM ATE "
                      f"{slam_ate:.4f} m, {s['keyframes']} keyframes, {s.get('loops_accepted')} loops",
                      flush=True)
    doc = {"benchmark": "rolling-shutter", "meta": meta("rolling_shutter.py", a.bin), "rows": rows,
           "opencv": {k: {"ate_m": v[0], "rpe_m_per_s": v[1]} for k, v in peers.items()}}
    pathlib.Path(a.json).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
