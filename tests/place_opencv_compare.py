#!/usr/bin/env python3
"""Compare rgbid's ORB with OpenCV's on a real TUM pair: repeatability under the true motion,
descriptor-matching precision, and speed per image, measured in the same run.

CASE_DIR holds img_prev.png, img_curr.png, dep_prev.png (16-bit), pose_prev.txt and
pose_curr.txt (`tx ty tz qx qy qz qw`, camera-to-world), and optionally calib.txt
(`fx fy cx cy depth_factor`; default: the TUM Kinect intrinsics, depth factor 5000).

usage: /work/.venv-peers/bin/python tests/place_opencv_compare.py [RGBID_BIN] [CASE_DIR]
(default: target/debug/rgbid, ../shared/data/rgbd/tum_pairs/case_1)
"""
import os
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np

here = os.path.dirname(os.path.abspath(__file__))
root = os.path.dirname(here)
binary = sys.argv[1] if len(sys.argv) > 1 else os.path.join(root, "target/debug/rgbid")
case = sys.argv[2] if len(sys.argv) > 2 else os.path.join(root, "../shared/data/rgbd/tum_pairs/case_1")
# Intrinsics and depth factor: CASE_DIR/calib.txt (`fx fy cx cy depth_factor`) if present, else
# the TUM Kinect defaults of tum_pairs.
fx = fy = 525.0
cx, cy = 319.5, 239.5
depth_factor = 5000.0
if os.path.exists(os.path.join(case, "calib.txt")):
    fx, fy, cx, cy, depth_factor = [float(x) for x in open(os.path.join(case, "calib.txt")).read().split()[:5]]


def quat_to_mat(qx, qy, qz, qw):
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])


def pose(path):
    v = [float(x) for x in open(path).read().split()]
    t = np.eye(4)
    t[:3, :3] = quat_to_mat(*v[3:7])
    t[:3, 3] = v[:3]
    return t


world_from_prev = pose(os.path.join(case, "pose_prev.txt"))
world_from_curr = pose(os.path.join(case, "pose_curr.txt"))
curr_from_prev = np.linalg.inv(world_from_curr) @ world_from_prev
depth_prev = cv2.imread(os.path.join(case, "dep_prev.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / depth_factor
img_prev = os.path.join(case, "img_prev.png")
img_curr = os.path.join(case, "img_curr.png")
h, w = depth_prev.shape


def project_prev_to_curr(pts):
    """Maps prev pixels to curr pixels with depth and the true motion; NaN where no depth."""
    out = np.full_like(pts, np.nan)
    for i, (u, v) in enumerate(pts):
        ui, vi = int(round(u)), int(round(v))
        if not (0 <= ui < w and 0 <= vi < h):
            continue
        z = depth_prev[vi, ui]
        if z <= 0:
            continue
        p = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z, 1.0])
        q = curr_from_prev @ p
        if q[2] > 0:
            out[i] = [fx * q[0] / q[2] + cx, fy * q[1] / q[2] + cy]
    return out


def evaluate(name, kp_prev, d_prev, kp_curr, d_curr, ms):
    proj = project_prev_to_curr(kp_prev)
    valid = ~np.isnan(proj[:, 0]) & (proj[:, 0] >= 0) & (proj[:, 0] < w) & (proj[:, 1] >= 0) & (proj[:, 1] < h)
    dist = np.linalg.norm(proj[valid][:, None, :] - kp_curr[None, :, :], axis=2)
    rep = float(np.mean(dist.min(axis=1) < 2.5)) if valid.any() else float("nan")
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    knn = bf.knnMatch(d_prev, d_curr, k=2)
    back = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(d_curr, d_prev, k=1)}
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance and m[0].distance <= 64
            and back.get(m[0].trainIdx) == m[0].queryIdx]
    correct = 0
    checked = 0
    for m in good:
        p = proj[m.queryIdx]
        if np.isnan(p[0]):
            continue
        checked += 1
        if np.linalg.norm(p - kp_curr[m.trainIdx]) < 3.0:
            correct += 1
    print(f"{name:7s} keypoints {len(kp_prev):4d}/{len(kp_curr):4d}  repeatability(2.5px) {rep:.3f}  "
          f"matches {len(good):4d}  correct(3px) {correct}/{checked} = {correct / max(checked, 1):.3f}  "
          f"median ms/image {ms:.2f}")


# OpenCV ORB, same settings (1000 features, 8 levels, 1.2, FAST 20).
orb = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8, fastThreshold=20)
gp = cv2.cvtColor(cv2.imread(img_prev), cv2.COLOR_BGR2GRAY)
gc = cv2.cvtColor(cv2.imread(img_curr), cv2.COLOR_BGR2GRAY)
times = []
for _ in range(21):
    t0 = time.perf_counter()
    kp1, d1 = orb.detectAndCompute(gp, None)
    times.append((time.perf_counter() - t0) * 1e3)
kp2, d2 = orb.detectAndCompute(gc, None)
cv_ms = float(np.median(times[1:]))

with tempfile.TemporaryDirectory() as tmp:
    res = {}
    for tag, img in [("prev", img_prev), ("curr", img_curr)]:
        dump = os.path.join(tmp, tag + ".txt")
        out = subprocess.run([binary, "place", "bench", img, "--repeat", "20", "--dump", dump],
                             check=True, capture_output=True, text=True).stdout
        rows = [l.split() for l in open(dump)]
        kp = np.array([[float(r[0]), float(r[1])] for r in rows])
        d = np.array([list(bytes.fromhex(r[5])) for r in rows], dtype=np.uint8)
        ms = float(out.split("median ORB ")[1].split(" ms")[0])
        res[tag] = (kp, d, ms, out.strip())
print(f"pair {case}; true motion |t| = {np.linalg.norm(curr_from_prev[:3, 3]) * 1e3:.1f} mm; "
      f"OpenCV {cv2.__version__} on {cv2.getNumThreads()} threads")
evaluate("opencv", np.array([k.pt for k in kp1]), d1, np.array([k.pt for k in kp2]), d2, cv_ms)
evaluate("rgbid", res["prev"][0], res["prev"][1], res["curr"][0], res["curr"][1], res["prev"][2])
print("rgbid bench:", res["prev"][3])
