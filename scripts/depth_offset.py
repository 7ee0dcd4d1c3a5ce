#!/usr/bin/env python3
"""How much the depth-to-colour time offset of a TUM sequence costs `rgbid slam`.

The Kinect's colour and depth streams are not synchronised: in a TUM folder every depth map
has its own time stamp, up to half a frame period from the colour image it is paired with.
`rgbid` takes the pair as one instant. This diagnostic writes copies of a TUM sequence whose
depth maps are moved to their colour image's time stamp, and runs `rgbid slam` on each:

- `none`: the depth maps re-written through the same warp with no motion (a control: it must
  give the original figures);
- `gt:F`: the camera motion over F times the stamped offset, from the ground truth;
- `cv:F`: the same motion predicted causally at constant velocity from the two previous frames
  of the `none` run's odometry (what a tracker could do online).

Each depth pixel is back-projected with the pinhole intrinsics (lens distortion is left out:
it moves a pixel by far less than the motion does), moved by the rigid motion from the depth
time to the colour time, and splatted to the nearest pixel (nearest surface kept).

Only for TUM fr1 folders (the fr1 intrinsics are built in).

Usage: /path/to/python scripts/depth_offset.py [--seq ../shared/data/rgbd/tum_fr1_rpy_0_199]
       [--variants none gt:0.5 gt:1 cv:1] [--bin target/release/rgbid]
Needs numpy, scipy and OpenCV (the peers' Python).
"""
import argparse
import json
import os
import pathlib
import subprocess
import tempfile

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

ROOT = pathlib.Path(__file__).resolve().parent.parent
# TUM fr1 colour intrinsics (pixels), the `tum_fr1` camera preset.
FX, FY, CX, CY = 517.3, 516.5, 318.6, 255.3


def listing(path):
    return [line.split() for line in open(path) if line.strip() and not line.startswith("#")]


def matrix(rotation, translation):
    m = np.eye(4)
    m[:3, :3] = rotation.as_matrix()
    m[:3, 3] = translation
    return m


def interpolator(rows):
    """world_from_camera at time t (linear position, slerped rotation)."""
    rows = np.asarray(rows, dtype=float)

    def at(t):
        j = int(np.clip(np.searchsorted(rows[:, 0], t), 1, len(rows) - 1))
        a, b = rows[j - 1], rows[j]
        u = (t - a[0]) / (b[0] - a[0])
        rot = Slerp([0, 1], Rotation.from_quat([a[4:8], b[4:8]]))([u])[0]
        return matrix(rot, a[1:4] * (1 - u) + b[1:4] * u)

    return at


def constant_velocity(rows):
    """cam(t) from cam(t + dt) predicted from the two frames before the colour time t."""
    rows = np.asarray(rows, dtype=float)

    def motion(t, dt):
        k = int(np.argmin(abs(rows[:, 0] - t)))
        if k < 2:
            return np.eye(4)
        a, b = (matrix(Rotation.from_quat(r[4:8]), r[1:4]) for r in rows[k - 2 : k])
        rel = np.linalg.inv(a) @ b
        f = dt / (rows[k - 1, 0] - rows[k - 2, 0])
        rot = Rotation.from_rotvec(Rotation.from_matrix(rel[:3, :3]).as_rotvec() * f)
        return matrix(rot, rel[:3, 3] * f)

    return motion


def warp(depth_m, colour_from_depth):
    h, w = depth_m.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    m = depth_m > 0
    z = depth_m[m]
    pts = np.stack([(u[m] - CX) / FX * z, (v[m] - CY) / FY * z, z])
    pts = colour_from_depth[:3, :3] @ pts + colour_from_depth[:3, 3:4]
    pu = np.round(pts[0] / pts[2] * FX + CX).astype(int)
    pv = np.round(pts[1] / pts[2] * FY + CY).astype(int)
    ok = (pu >= 0) & (pu < w) & (pv >= 0) & (pv < h) & (pts[2] > 0)
    out = np.zeros((h, w))
    order = np.argsort(-pts[2][ok])  # far first, so the nearest surface is written last
    out[pv[ok][order], pu[ok][order]] = pts[2][ok][order]
    return out


def write_copy(seq, dest, motion):
    """A copy of `seq` in `dest` with every depth map moved to its colour time stamp."""
    dest.mkdir(parents=True)
    (dest / "depth").mkdir()
    for name in ("rgb", "rgb.txt", "depth.txt", "groundtruth.txt"):
        os.symlink(seq / name, dest / name)
    colour_times = np.array([float(r[0]) for r in listing(seq / "rgb.txt")])
    offsets = []
    for stamp, name in listing(seq / "depth.txt"):
        td = float(stamp)
        tc = float(colour_times[np.argmin(abs(colour_times - td))])
        offsets.append(td - tc)
        raw = cv2.imread(str(seq / name), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise SystemExit(f"{seq / name}: not a readable depth image")
        out = warp(raw.astype(np.float64) / 5000.0, motion(tc, td - tc))
        cv2.imwrite(str(dest / name), np.round(out * 5000.0).astype(np.uint16))
    return np.array(offsets)


def run_slam(binary, seq, out):
    cmd = [str(binary), "--log", "error", "slam", str(seq), "--camera", "tum_fr1",
           "--out", str(out), "--no-model"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.load(open(out / "summary.json"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", type=pathlib.Path,
                    default=ROOT.parent / "shared/data/rgbd/tum_fr1_rpy_0_199",
                    help="a TUM fr1 folder: the warp and `rgbid slam --camera tum_fr1` take "
                         "fr1's intrinsics")
    ap.add_argument("--variants", nargs="+", default=["none", "gt:0.5", "gt:1", "cv:1"])
    ap.add_argument("--bin", type=pathlib.Path, default=ROOT / "target/release/rgbid")
    args = ap.parse_args()
    seq = args.seq.resolve()
    gt = interpolator([list(map(float, r)) for r in listing(seq / "groundtruth.txt")])
    odometry = None
    print("| variant | SLAM ATE m | odometry ATE m | odometry RPE m/s | keyframes | loops |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        for variant in args.variants:
            kind, _, factor = variant.partition(":")
            f = float(factor or 0.0)
            if kind == "none":
                motion = lambda t, dt: np.eye(4)  # noqa: E731
            elif kind == "gt":
                motion = lambda t, dt, f=f: np.linalg.inv(gt(t)) @ gt(t + f * dt)  # noqa: E731
            elif kind == "cv":
                if odometry is None:
                    raise SystemExit("cv:F needs the `none` variant first (its odometry)")
                cv = constant_velocity(odometry)
                motion = lambda t, dt, f=f, cv=cv: cv(t, f * dt)  # noqa: E731
            else:
                raise SystemExit(f"unknown variant {variant!r} (none, gt:F, cv:F)")
            copy = tmp / variant.replace(":", "_")
            offsets = write_copy(seq, copy, motion)
            s = run_slam(args.bin, copy, tmp / (copy.name + "_out"))
            if kind == "none":
                odometry = [list(map(float, r)) for r in listing(tmp / "none_out/odometry.txt")]
                print(f"<!-- depth minus colour time: median {np.median(offsets) * 1e3:.2f} ms, "
                      f"range {offsets.min() * 1e3:.2f} to {offsets.max() * 1e3:.2f} ms -->")
            print(f"| {variant} | {s['slam_ate_rmse']:.5f} | {s['odometry_ate_rmse']:.5f} | "
                  f"{s['odometry_rpe_rmse']:.5f} | {s['keyframes']} | {s['loops_accepted']} |")


if __name__ == "__main__":
    main()
