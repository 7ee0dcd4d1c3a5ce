"""A sequence in, a trajectory and a point cloud out, and a plot against the ground truth.

    python quickstart.py                      # a generated office sequence (handheld)
    python quickstart.py /data/rgbd_dataset_freiburg1_xyz --camera tum_fr1

Writes trajectory.txt (TUM format), points.ply (the SLAM model) and quickstart.png (top view
of the trajectory against the ground truth; needs matplotlib, skipped without it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import rgbid


def quat_to_matrix(row: np.ndarray) -> np.ndarray:
    x, y, z, w = row[4:8] / np.linalg.norm(row[4:8])
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = row[1:4]
    return m


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write("ply\nformat ascii 1.0\n")
        f.write(f"element vertex {len(points)}\n")
        f.write("property float x\nproperty float y\nproperty float z\n")
        f.write("property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
        for p, c in zip(points, colors):
            f.write(f"{p[0]:.5f} {p[1]:.5f} {p[2]:.5f} {c[0]} {c[1]} {c[2]}\n")


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", nargs="?", help="TUM folder (default: a generated handheld office sequence)")
    p.add_argument("--camera", default=None, help="camera preset or file for a TUM folder")
    p.add_argument("--frames", type=int, default=150, help="frames of the generated sequence")
    p.add_argument("--backend", default="auto", choices=["auto", "gpu", "cpu"])
    p.add_argument("--out", default=".", help="output folder")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    if a.sequence:
        seq = rgbid.read_sequence(a.sequence, camera=a.camera)
    else:
        seq = rgbid.synth.render("office", "handheld", a.frames, 7, width=320)
    slam = rgbid.Slam(seq.camera, backend=a.backend)
    for t, image, depth, factor in seq:
        slam.process(image, depth, factor, t)
    result = slam.finish()
    rgbid.write_trajectory(out / "trajectory.txt", result.trajectory)
    write_ply(out / "points.ply", result.points, result.colors)
    summary = {"poses": len(result.trajectory), "points": len(result.points), "keyframes": len(result.keyframes)}
    print(f"{summary['poses']} poses, {summary['keyframes']} keyframes, {summary['points']} points -> {out}")

    gt = seq.groundtruth
    est = result.trajectory
    if gt is not None and len(est) >= 2:
        ate = rgbid.eval.ate(gt, est)
        summary["ate_rmse_m"] = ate["rmse"]
        print(f"ATE rmse {ate['rmse']:.4f} m over {ate['matched']} poses")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot (pip install matplotlib)")
        return summary
    fig, ax = plt.subplots(figsize=(6, 6))
    if gt is not None:
        ax.plot(gt[:, 1], gt[:, 2], "k-", label="ground truth")
        # The estimate starts at the identity: put its first pose on the ground truth's.
        i0 = int(np.argmin(np.abs(gt[:, 0] - est[0, 0])))
        world_from_est = quat_to_matrix(gt[i0]) @ np.linalg.inv(quat_to_matrix(est[0]))
        xyz = np.array([(world_from_est @ quat_to_matrix(r))[:3, 3] for r in est])
    else:
        xyz = est[:, 1:4]
    ax.plot(xyz[:, 0], xyz[:, 1], "r-", label="rgbid SLAM")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend()
    ax.set_title("trajectory, top view")
    fig.savefig(out / "quickstart.png", dpi=100)
    summary["plot"] = str(out / "quickstart.png")
    print(f"plot in {out / 'quickstart.png'}")
    return summary


if __name__ == "__main__":
    main()
