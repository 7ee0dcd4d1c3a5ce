"""Odometry or SLAM over many sequences as Ray tasks, one table of ATE / RPE / time.

    python ray_batch.py                              # 4 generated sequences, local Ray
    python ray_batch.py --sequences 16 --system slam
    python ray_batch.py --folders /data/tum/*/       # TUM folders (same paths on every node)

Each sequence is one Ray task; Ray places the tasks on the CPUs it knows about. On one machine
`ray.init()` starts a local Ray. On a cluster, start Ray on the nodes first (`ray start --head`
on one, `ray start --address=HEAD_IP:6379` on the others, each with `pip install ./python
ray`), then run this script on a node with `--address auto`: the tasks spread over every node.
TUM folders must then be readable at the same path on every node (a shared file system);
generated sequences need no data.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Dict, List, Optional

import numpy as np


def run_sequence(spec: Dict) -> Dict:
    """One sequence: opens or generates it, runs the system, evaluates against ground truth."""
    import rgbid  # imported in the worker

    if spec["folder"]:
        seq = rgbid.read_sequence(spec["folder"])
        name = spec["folder"]
    else:
        seq = rgbid.synth.render(spec["scene"], spec["trajectory"], spec["frames"], spec["seed"], width=spec["width"])
        name = f"{spec['scene']}:{spec['trajectory']} seed {spec['seed']}"
    t0 = time.perf_counter()
    rows = []
    if spec["system"] == "slam":
        slam = rgbid.Slam(seq.camera, backend=spec["backend"])
        for t, image, depth, factor in seq:
            slam.process(image, depth, factor, t)
        est = slam.finish().trajectory
    else:
        odo = rgbid.Odometry(seq.camera, backend=spec["backend"])
        for t, image, depth, factor in seq:
            r = odo.track(image, depth, factor, t)
            m = r["world_from_camera"]
            if m is not None:
                rows.append(_tum_row(t, m))
        est = np.array(rows)
    seconds = time.perf_counter() - t0
    out = {"sequence": name, "frames": len(seq), "seconds": seconds, "fps": len(seq) / seconds}
    gt = seq.groundtruth
    if gt is not None and len(est) >= 2:
        ate = rgbid.eval.ate(gt, est)
        out["ate_rmse_m"] = ate["rmse"]
        try:
            out["rpe_rmse_m"] = rgbid.eval.rpe(gt, est, delta=min(1.0, 0.5 * (gt[-1, 0] - gt[0, 0])))["rmse"]
        except ValueError:
            out["rpe_rmse_m"] = float("nan")
    return out


def _tum_row(t: float, m: np.ndarray) -> List[float]:
    r = m[:3, :3]
    w = np.sqrt(max(0.0, 1 + np.trace(r))) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return [t, *m[:3, 3], x, y, z, w]


def format_table(rows: List[Dict]) -> str:
    head = f"{'sequence':<34} {'frames':>6} {'seconds':>8} {'fps':>6} {'ATE m':>9} {'RPE m':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['sequence']:<34} {r['frames']:>6} {r['seconds']:>8.2f} {r['fps']:>6.1f} "
            f"{r.get('ate_rmse_m', float('nan')):>9.4f} {r.get('rpe_rmse_m', float('nan')):>9.4f}"
        )
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> List[Dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--system", choices=["odometry", "slam"], default="odometry")
    p.add_argument("--folders", nargs="*", default=[], help="TUM folders (instead of generated sequences)")
    p.add_argument("--sequences", type=int, default=4, help="generated sequences (seeds 1..N)")
    p.add_argument("--scene", default="office")
    p.add_argument("--trajectory", default="handheld")
    p.add_argument("--frames", type=int, default=60, help="frames per generated sequence (30 per second)")
    p.add_argument("--width", type=int, default=160, help="width of generated frames, pixels")
    p.add_argument("--backend", default="cpu", choices=["auto", "gpu", "cpu"])
    p.add_argument("--address", default=None, help="Ray cluster address ('auto' on a cluster node); default: local")
    p.add_argument("--num-cpus", type=int, default=None, help="CPUs of a local Ray (default: all)")
    a = p.parse_args(argv)

    import ray

    if a.address:
        ray.init(address=a.address)
    else:
        ray.init(num_cpus=a.num_cpus)
    try:
        base = dict(system=a.system, backend=a.backend, scene=a.scene, trajectory=a.trajectory, frames=a.frames, width=a.width)
        if a.folders:
            specs = [dict(base, folder=f, seed=0) for f in a.folders]
        else:
            specs = [dict(base, folder=None, seed=s) for s in range(1, a.sequences + 1)]
        task = ray.remote(num_cpus=1)(run_sequence)
        t0 = time.perf_counter()
        rows = ray.get([task.remote(s) for s in specs])
        wall = time.perf_counter() - t0
    finally:
        ray.shutdown()
    print(format_table(rows))
    print(f"{len(rows)} sequences in {wall:.1f} s wall ({sum(r['seconds'] for r in rows):.1f} s of tasks)")
    return rows


if __name__ == "__main__":
    main()
    sys.exit(0)
