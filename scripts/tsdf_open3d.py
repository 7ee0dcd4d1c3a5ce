#!/usr/bin/env python3
"""Open3D's tensor VoxelBlockGrid on a TUM-layout folder: the peer of `rgbid bench tsdf`.

Integrates every frame of SEQ (associations.txt, groundtruth.txt as world_from_camera, the
camera of calib.txt or rgbid's default) with the ground-truth pose, on the CPU, then extracts
a triangle mesh. Writes the mesh (PLY) and a JSON file with the integration time of every
frame (milliseconds, integration only: frames are decoded before the clock starts).

Usage: tsdf_open3d.py SEQ --voxel 0.02 --depth-max 4.0 --mesh OUT.ply --json OUT.json

Exits with status 3 when Open3D cannot be imported.
"""
import argparse
import json
import sys
import time

import numpy as np

# Exit status when Open3D cannot be imported (e.g. a machine without the wheel or its shared
# libraries): the caller reports the peer as skipped rather than failed.
NO_OPEN3D = 3

try:
    import open3d as o3d
    import open3d.core as o3c
except ImportError as e:
    print(f"open3d not importable: {e}", file=sys.stderr)
    sys.exit(NO_OPEN3D)


def read_pairs(seq):
    pairs = []
    with open(f"{seq}/associations.txt") as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            t_rgb, rgb, t_depth, depth = line.split()[:4]
            pairs.append((float(t_rgb), f"{seq}/{rgb}", f"{seq}/{depth}"))
    return pairs


def read_poses(seq):
    poses = []
    with open(f"{seq}/groundtruth.txt") as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            v = [float(x) for x in line.split()]
            poses.append((v[0], v[1:4], v[4:8]))
    return poses


def matrix(t, q):
    x, y, z, w = q
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def read_camera(seq, width, height):
    try:
        with open(f"{seq}/calib.txt") as f:
            fx, fy, cx, cy = [float(x) for x in f.read().split()[:4]]
    except OSError:
        fx, fy, cx, cy = 525.0, 525.0, 319.5, 239.5
    return o3c.Tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], o3c.Dtype.Float64)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("seq")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--depth-max", type=float, default=4.0)
    ap.add_argument("--depth-scale", type=float, default=5000.0)
    ap.add_argument("--mesh", required=True)
    ap.add_argument("--json", required=True)
    a = ap.parse_args()
    device = o3c.Device("CPU:0")
    poses = read_poses(a.seq)
    times = [p[0] for p in poses]
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=a.voxel,
        block_resolution=8,
        block_count=100000,
        device=device,
    )
    intrinsic = None
    ms = []
    for t, rgb_path, depth_path in read_pairs(a.seq):
        k = int(np.argmin([abs(t - s) for s in times]))
        if abs(times[k] - t) > 0.02:
            continue
        depth = o3d.t.io.read_image(depth_path).to(device)
        color = o3d.t.io.read_image(rgb_path).to(device)
        if intrinsic is None:
            intrinsic = read_camera(a.seq, depth.columns, depth.rows)
        world_from_camera = matrix(poses[k][1], poses[k][2])
        extrinsic = o3c.Tensor(np.linalg.inv(world_from_camera), o3c.Dtype.Float64)
        start = time.perf_counter()
        coords = vbg.compute_unique_block_coordinates(
            depth, intrinsic, extrinsic, a.depth_scale, a.depth_max)
        vbg.integrate(coords, depth, color, intrinsic, extrinsic, a.depth_scale, a.depth_max)
        ms.append(1000.0 * (time.perf_counter() - start))
    start = time.perf_counter()
    mesh = vbg.extract_triangle_mesh().to_legacy()
    extract_s = time.perf_counter() - start
    o3d.io.write_triangle_mesh(a.mesh, mesh)
    with open(a.json, "w") as f:
        json.dump({"integrate_ms": ms, "extract_s": extract_s, "open3d": o3d.__version__}, f)


if __name__ == "__main__":
    main()
