#!/usr/bin/env python3
"""OpenCV's RGB-D odometry on the two TUM pairs of ../shared/data/rgbd/tum_pairs, each term
alone and both together, against the ground truth: the peer side of the per-term table in docs/notes.md
(rgbid's side: `cargo run --release --example tum_pairs -- CONFIG.json` with
`{"terms": "photometric"}`, `{"terms": "geometric"}` and `{}`).

Usage: python3 scripts/tum_pairs_opencv.py [DATA_DIR]   (needs opencv-python >= 4.7, scipy)

Prints, per method and pair, the translation (mm) and rotation (deg) of the error
`truth^-1 * estimate` of prev_from_curr and its rotation vector (deg, camera axes).
"""
import sys

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

DATA = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/rgbd/tum_pairs"
K = np.array([[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]], np.float32)


def pose(path):
    v = [float(x) for x in open(path).read().split()]
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(v[3:7]).as_matrix()
    t[:3, 3] = v[:3]
    return t


def main():
    methods = [
        ("RGB_DEPTH (both)", cv2.OdometryType_RGB_DEPTH),
        ("RGB (photometric)", cv2.OdometryType_RGB),
        ("DEPTH (ICP)", cv2.OdometryType_DEPTH),
    ]
    for name, kind in methods:
        for case in ["case_1", "case_2"]:
            d = f"{DATA}/{case}/"
            gray = lambda n: cv2.cvtColor(cv2.imread(d + n), cv2.COLOR_BGR2GRAY)
            depth = lambda n: cv2.imread(d + n, cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000
            settings = cv2.OdometrySettings()
            settings.setCameraMatrix(K)
            odo = cv2.Odometry(kind, settings, cv2.OdometryAlgoType_COMMON)
            if kind == cv2.OdometryType_DEPTH:
                ok, rt = odo.compute(depth("dep_curr.png"), depth("dep_prev.png"))
            else:
                ok, rt = odo.compute(depth("dep_curr.png"), gray("img_curr.png"),
                                     depth("dep_prev.png"), gray("img_prev.png"))
            truth = np.linalg.inv(pose(d + "pose_prev.txt")) @ pose(d + "pose_curr.txt")
            err = np.linalg.inv(truth) @ rt
            rv = np.degrees(Rotation.from_matrix(err[:3, :3]).as_rotvec())
            print(f"{name:18} {case}: ok={ok} {1e3 * np.linalg.norm(err[:3, 3]):.2f} mm "
                  f"{np.linalg.norm(rv):.3f} deg (error rotation vector, deg: "
                  f"{rv[0]:+.3f} {rv[1]:+.3f} {rv[2]:+.3f})")


if __name__ == "__main__":
    main()
