#!/usr/bin/env python3
"""How the TUM pairs' ranking depends on the timing of their ground truth.

The ground-truth poses of ../shared/data/rgbd/tum_pairs are the nearest 100 Hz motion-capture
samples to the colour frames (case_1: 4.7 ms after the earlier frame, 0.5 ms after the later
one), so the true motion between the colour frames is the ground-truth motion scaled by the
ratio of the intervals if the velocity is constant. This prints the error (translation mm,
rotation deg) of rgbid's and OpenCV RGB_DEPTH's `prev_from_curr` against the ground-truth
motion scaled by s (`expm(s * logm(T))`), for s around 1.

Usage: cargo run --release --example tum_pairs -- CONFIG.json | \\
         python3 scripts/tum_pairs_gt_scale.py [DATA_DIR]
(needs opencv-python >= 4.7 with the 5.x Odometry API, scipy)
"""
import re
import sys

import cv2
import numpy as np
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from tum_pairs_opencv import K, pose

DATA = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/rgbd/tum_pairs"
SCALES = [0.95, 0.97, 1.0, 1.03, 1.0703, 1.09]


def rgbid_estimates(text):
    """prev_from_cur of each case from the `tum_pairs` example's output."""
    out, case = {}, None
    for line in text.splitlines():
        m = re.search(r"(case_\d+):", line)
        if m:
            case = m.group(1)
        m = re.search(r"estimate prev_from_cur: t (\S+) (\S+) (\S+) mm, rotation vector (\S+) (\S+) (\S+) deg", line)
        if m and case:
            v = [float(x) for x in m.groups()]
            t = np.eye(4)
            t[:3, :3] = Rotation.from_rotvec(np.radians(v[3:])).as_matrix()
            t[:3, 3] = np.array(v[:3]) * 1e-3
            out[case] = t
    return out


def main():
    ours = rgbid_estimates(sys.stdin.read())
    for case in ["case_1", "case_2"]:
        d = f"{DATA}/{case}/"
        gray = lambda n: cv2.cvtColor(cv2.imread(d + n), cv2.COLOR_BGR2GRAY)
        depth = lambda n: cv2.imread(d + n, cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000
        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(K)
        odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
        _, cv_est = odo.compute(depth("dep_curr.png"), gray("img_curr.png"),
                                depth("dep_prev.png"), gray("img_prev.png"))
        truth = np.linalg.inv(pose(d + "pose_prev.txt")) @ pose(d + "pose_curr.txt")
        log_truth = np.real(logm(truth))
        print(case)
        for s in SCALES:
            scaled = expm(s * log_truth)
            row = []
            for name, est in [("rgbid", ours.get(case)), ("OpenCV RGB_DEPTH", cv_est)]:
                if est is None:
                    continue
                e = np.linalg.inv(scaled) @ est
                ang = np.degrees(np.linalg.norm(Rotation.from_matrix(e[:3, :3]).as_rotvec()))
                row.append(f"{name} {1e3 * np.linalg.norm(e[:3, 3]):5.2f} mm {ang:.3f} deg")
            print(f"  ground-truth motion x {s:.4f}: " + " | ".join(row))


if __name__ == "__main__":
    main()
