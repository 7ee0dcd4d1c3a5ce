#!/usr/bin/env python3
"""Software render of an rgbid PLY (a `model.ply` point cloud or a `mesh.ply` triangle mesh)
into a PNG, for the pictures in docs/. No GPU and no window: a pinhole camera, triangles
filled back to front (painter's order by mean depth), points splatted as small squares with a
depth buffer.

The view is chosen from the data: the camera looks along the mean viewing direction of the
run's trajectory (`--trajectory`, TUM `world_from_camera`; default: the one beside the PLY),
with the trajectory's mean "up", from far enough back that the model's central 98 % fits the
image. Vertex colours are drawn as stored; `--shade` multiplies mesh colours by
0.55 + 0.45 |n . view| (the vertex normals) so that the shape reads on flat-coloured areas.

Usage: render_ply.py IN.ply OUT.png [--trajectory TRAJ.txt] [--width 960] [--height 720]
       [--fov 60] [--back 1.0] [--shade] [--point-size 2]

Reads binary little-endian PLY with `float x y z`, optional `float nx ny nz`, `uchar red green
blue`, and an optional `face` element of `uchar`-counted `int`/`uint` index lists (what
rgbid writes).
"""
import argparse
import os
import sys

import cv2
import numpy as np

PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "uint8": "u1",
             "char": "i1", "int8": "i1", "short": "<i2", "ushort": "<u2", "int": "<i4",
             "int32": "<i4", "uint": "<u4", "uint32": "<u4"}


def read_ply(path):
    """Vertices (N x 3 float), colours (N x 3 uint8), normals (N x 3 or None), faces (M x 3)."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        sys.exit(f"{path}: only binary little-endian PLY is read")
    elements = []
    for line in header:
        w = line.split()
        if w[:1] == ["element"]:
            elements.append((w[1], int(w[2]), []))
        elif w[:1] == ["property"]:
            elements[-1][2].append(w[1:])
    pos = end
    verts = cols = normals = faces = None
    for name, count, props in elements:
        if name == "vertex":
            dtype = np.dtype([(p[1], PLY_TYPES[p[0]]) for p in props])
            v = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
            pos += dtype.itemsize * count
            verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
            if "red" in dtype.names:
                cols = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.uint8)
            else:
                cols = np.full((count, 3), 200, np.uint8)
            if "nx" in dtype.names:
                normals = np.stack([v["nx"], v["ny"], v["nz"]], 1).astype(np.float64)
        elif name == "face":
            (_, count_t, index_t, _), = props
            # rgbid writes triangles only: a count byte of 3 then three indices per face.
            dtype = np.dtype([("n", PLY_TYPES[count_t]), ("i", PLY_TYPES[index_t], (3,))])
            fa = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
            if count and not np.all(fa["n"] == 3):
                sys.exit(f"{path}: faces other than triangles")
            pos += dtype.itemsize * count
            faces = fa["i"].astype(np.int64)
        else:
            sys.exit(f"{path}: element '{name}' not read")
    return verts, cols, normals, faces


def read_trajectory(path):
    """Rows of (t, tx, ty, tz, qx, qy, qz, qw) as world_from_camera."""
    rows = [list(map(float, line.split())) for line in open(path)
            if line.strip() and not line.startswith("#")]
    return np.array(rows)


def rotation(q):
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def view(verts, traj, width, height, fov_deg, back):
    """world_from_view rotation R (columns x right, y down, z forward), centre c, focal f."""
    if traj is not None and len(traj):
        rots = [rotation(r[4:8]) for r in traj]
        forward = np.mean([r[:, 2] for r in rots], 0)
        down = np.mean([r[:, 1] for r in rots], 0)
    else:
        forward, down = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
    z = forward / np.linalg.norm(forward)
    y = down - z * (down @ z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    r = np.stack([x, y, z], 1)
    lo, hi = np.percentile(verts, 1, 0), np.percentile(verts, 99, 0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * np.linalg.norm(hi - lo)
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    half = np.radians(fov_deg) / 2 * min(1.0, height / width)
    dist = back * radius / np.sin(half)
    return r, centre - dist * z, f


def render(verts, cols, normals, faces, r, c, f, width, height, shade, point_size):
    p = (verts - c) @ r  # view frame: x right, y down, z forward
    img = np.full((height, width, 3), 255, np.uint8)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    zc = np.maximum(p[:, 2], 1e-6)
    u = f * p[:, 0] / zc + cx
    v = f * p[:, 1] / zc + cy
    colour = cols.astype(np.float64)
    if shade and normals is not None:
        ray = p / np.linalg.norm(p, axis=1, keepdims=True)
        lam = np.abs(np.sum((normals @ r) * ray, 1))
        colour *= (0.55 + 0.45 * lam)[:, None]
    colour = np.clip(colour + 0.5, 0, 255).astype(np.uint8)
    if faces is not None and len(faces):
        front = np.all(p[faces, 2] > 0.05, 1)
        tri = faces[front]
        order = np.argsort(-p[tri, 2].mean(1))
        tri = tri[order]
        pts = np.round(np.stack([u[tri], v[tri]], 2) * 16).astype(np.int32)
        tc = colour[tri].mean(1).astype(np.int64)
        for k in range(len(tri)):
            b, g, rr = int(tc[k, 2]), int(tc[k, 1]), int(tc[k, 0])
            cv2.fillConvexPoly(img, pts[k], (b, g, rr), lineType=cv2.LINE_8, shift=4)
        return img
    keep = (p[:, 2] > 0.05) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    order = np.argsort(-p[keep, 2])  # far first: nearer points overwrite
    ui = u[keep][order].astype(np.int64)
    vi = v[keep][order].astype(np.int64)
    col = colour[keep][order][:, ::-1]
    for dy in range(point_size):
        for dx in range(point_size):
            uu, vv = np.clip(ui + dx, 0, width - 1), np.clip(vi + dy, 0, height - 1)
            img[vv, uu] = col
    return img


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ply")
    ap.add_argument("png")
    ap.add_argument("--trajectory", help="TUM trajectory (default: trajectory.txt beside the PLY)")
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--fov", type=float, default=60.0, help="horizontal field of view, degrees")
    ap.add_argument("--back", type=float, default=1.0,
                    help="distance from the model's centre in bounding radii over the fit")
    ap.add_argument("--shade", action="store_true")
    ap.add_argument("--point-size", type=int, default=2)
    a = ap.parse_args()
    verts, cols, normals, faces = read_ply(a.ply)
    traj_path = a.trajectory or os.path.join(os.path.dirname(a.ply), "trajectory.txt")
    traj = read_trajectory(traj_path) if os.path.exists(traj_path) else None
    r, c, f = view(verts, traj, a.width, a.height, a.fov, a.back)
    img = render(verts, cols, normals, faces, r, c, f, a.width, a.height, a.shade, a.point_size)
    cv2.imwrite(a.png, img)
    print(f"{a.png}: {len(verts)} vertices, {0 if faces is None else len(faces)} triangles")


if __name__ == "__main__":
    main()
