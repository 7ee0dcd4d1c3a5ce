"""Reads an `rgbid --rerun save:FILE.rrd` recording back with the rerun Python SDK (0.36) and
checks its entities and row counts against the run's own output files.

    python rerun_check.py slam RECORDING.rrd RUN_FOLDER
    python rerun_check.py odometry RECORDING.rrd TRAJECTORY.txt FRAMES.csv [SEQUENCE]

With SEQUENCE (the TUM folder odometry ran on), also compares the pinhole with its calib.txt
and frame 0's logged images with its PNG files.

Prints every entity path with its rows and component columns, then each check; exits 1 when
a check fails. Needs only `rerun-sdk==0.36.*` (pyarrow and pillow come with it).
"""

from __future__ import annotations

import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from rerun.experimental import RrdReader

failures: list[str] = []


def check(ok: bool, what: str) -> None:
    print(f"  [{'ok' if ok else 'FAIL'}] {what}")
    if not ok:
        failures.append(what)


def read(path: str):
    """Per entity: temporal rows, static rows, component columns, and its chunks' batches."""
    chunks = RrdReader(path).stream().to_chunks()
    entities: dict[str, dict] = defaultdict(
        lambda: {"rows": 0, "static": 0, "columns": set(), "batches": []}
    )
    for c in chunks:
        if c.is_empty:
            continue
        e = entities[c.entity_path]
        e["static" if c.is_static else "rows"] += c.num_rows
        batch = c.to_record_batch()
        e["columns"].update(n for n in batch.schema.names if ":" in n and not n.startswith("rerun."))
        e["batches"].append(batch)
    print(f"{path}: {len(chunks)} chunks, {len(entities)} entities")
    for name in sorted(entities):
        e = entities[name]
        cols = ", ".join(sorted(e["columns"]))
        print(f"  {name:40s} rows {e['rows']:5d} static {e['static']}  [{cols}]")
    return entities


def rows_with(entities, entity: str, column_suffix: str) -> int:
    """Temporal rows of `entity` holding a non-null value in the column ending with the suffix."""
    n = 0
    for b in entities.get(entity, {}).get("batches", []):
        for i, name in enumerate(b.schema.names):
            if name.endswith(column_suffix):
                n += len(b.column(i)) - b.column(i).null_count
    return n


def column_by_frame(entities, entity: str, column_suffix: str) -> dict[int, object]:
    """Values of a component column by the `frame` timeline (the last one logged at a frame)."""
    out: dict[int, object] = {}
    for b in entities.get(entity, {}).get("batches", []):
        names = b.schema.names
        if "frame" not in names:
            continue
        frames = b.column(names.index("frame")).to_pylist()
        for i, name in enumerate(names):
            if name.endswith(column_suffix):
                for f, v in zip(frames, b.column(i).to_pylist()):
                    if v is not None:
                        out[f] = v
    return out


def flat(v):
    """A logged single-instance value (a list of one) as a flat numpy array."""
    return np.asarray(v, dtype=float).reshape(-1)


def tum(path: Path) -> np.ndarray:
    rows = [l.split() for l in path.read_text().splitlines() if l.strip() and not l.startswith("#")]
    return np.array(rows, dtype=float).reshape(-1, 8)


def common(entities, frames: int) -> None:
    check(
        entities.get("/world/camera", {}).get("static", 0) >= 1
        and "Pinhole:image_from_camera" in entities["/world/camera"]["columns"],
        "/world/camera has a static pinhole",
    )
    for entity, col in [("/world/camera/image", "Image:buffer"), ("/world/camera/depth", "DepthImage:buffer")]:
        n = rows_with(entities, entity, col)
        check(n == frames, f"{entity}: {n} images for {frames} frames")
    meters = column_by_frame(entities, "/world/camera/depth", "DepthImage:meter")
    check(
        len(meters) == frames and all(abs(flat(m)[0] - 1.0) < 1e-9 for m in meters.values()),
        "depth images in metres (meter = 1) on every frame",
    )


def slam(rrd: str, run: Path) -> None:
    entities = read(rrd)
    timing = list(csv.DictReader((run / "timing.csv").open()))
    frames = len(timing)
    keyframes = len(tum(run / "keyframes.txt"))
    loops = [r for r in csv.DictReader((run / "loops.csv").open())]
    accepted = [
        r for r in loops if r["accepted"].lower() == "true" and r["relocalisation"].lower() == "false"
    ]
    posed = sum(1 for r in timing if r["status"] != "Lost")
    print(f"run folder: {frames} frames ({posed} posed), {keyframes} keyframes, {len(accepted)} accepted loops")
    common(entities, frames)
    n = rows_with(entities, "/world/camera", "Transform3D:translation")
    check(n == posed, f"/world/camera: {n} poses for {posed} posed frames")
    kf = sorted(e for e in entities if e.startswith("/world/keyframes/") and e.endswith("/points"))
    check(len(kf) == keyframes, f"{len(kf)} keyframe point clouds for {keyframes} keyframes")
    # A keyframe's points: those of its frame while the run goes on, its fused ones at the end.
    sizes = [rows_with(entities, e, "Points3D:positions") for e in kf]
    check(all(s >= 1 for s in sizes), "every keyframe has points logged")
    with_colour = all(rows_with(entities, e, "Points3D:colors") >= 1 for e in kf)
    check(with_colour, "keyframe points carry colours")
    for name in ["iterations", "covisibility", "frontend_ms", "sigma_photo"]:
        n = rows_with(entities, f"/frame/{name}", "Scalars:scalars")
        check(n == frames, f"/frame/{name}: {n} values for {frames} frames")
    iterations = column_by_frame(entities, "/frame/iterations", "Scalars:scalars")
    same = all(int(flat(iterations[int(r["index"])])[0]) == int(r["iterations"]) for r in timing)
    check(same, "/frame/iterations equals timing.csv's iterations on every frame")
    if accepted:
        strips = column_by_frame(entities, "/world/loops", "LineStrips3D:strips")
        last = strips[max(strips)] if strips else []
        check(len(last) == len(accepted), f"/world/loops: {len(last)} edges at the end for {len(accepted)} accepted loops")
    else:
        check("/world/loops" not in entities, "no accepted loop and no /world/loops")
    times = column_by_frame(entities, "/world/camera/image", "Image:buffer")
    check(sorted(times) == list(range(frames)), "images on frame indices 0..N-1")


def odometry(rrd: str, trajectory: Path, frames_csv: Path) -> None:
    entities = read(rrd)
    rows = list(csv.DictReader(frames_csv.open()))
    frames = len(rows)
    tracked = [r for r in rows if r["status"] == "ok"]
    print(f"odometry: {frames} frames, {len(tracked)} tracked")
    common(entities, frames)
    poses = column_by_frame(entities, "/world/camera", "Transform3D:translation")
    check(len(poses) == len(tracked), f"/world/camera: {len(poses)} poses for {len(tracked)} tracked frames")
    traj = tum(trajectory)
    logged = np.array([flat(poses[k]) for k in sorted(poses)])
    err = np.abs(logged - traj[: len(logged), 1:4]).max() if len(logged) == len(traj) else np.inf
    check(err < 1e-5, f"logged translations equal the trajectory file's (max difference {err:.2e} m)")
    iterations = column_by_frame(entities, "/frame/iterations", "Scalars:scalars")
    same = all(int(flat(iterations[int(r["index"])])[0]) == int(r["iterations"]) for r in tracked)
    check(same, "/frame/iterations equals the --csv iterations on every tracked frame")
    images_against_the_folder(entities, trajectory, frames_csv)


def images_against_the_folder(entities, trajectory: Path, frames_csv: Path) -> None:
    """The pinhole against calib.txt, frame 0's images against the folder's PNG files."""
    from PIL import Image

    seq = Path(sys.argv[5]) if len(sys.argv) > 5 else None
    if seq is None:
        return
    fx, fy, cx, cy, factor, w, h = (float(v) for v in (seq / "calib.txt").read_text().split()[:7])
    static = [b for b in entities["/world/camera"]["batches"] if "Pinhole:image_from_camera" in b.schema.names]
    k = flat(static[0].column(static[0].schema.names.index("Pinhole:image_from_camera")).to_pylist()[0])
    # Column-major 3x3; rerun's pixel centres are at +0.5 of ours.
    want = [fx, 0, 0, 0, fy, 0, cx + 0.5, cy + 0.5, 1]
    check(np.allclose(k, want, atol=1e-4), f"pinhole {k.round(3).tolist()} is calib.txt's (principal point + 0.5)")

    def listed(name: str) -> str:
        rows = [l.split() for l in (seq / name).read_text().splitlines() if l.strip() and not l.startswith("#")]
        return rows[0][1]

    depth_png = np.asarray(Image.open(seq / listed("depth.txt")), dtype=np.float64) / factor
    logged = column_by_frame(entities, "/world/camera/depth", "DepthImage:buffer")[0]
    depth = np.frombuffer(bytes(flat(logged).astype(np.uint8)), dtype=np.float32).reshape(int(h), int(w))
    valid = depth_png > 0
    err = np.abs(depth[valid] - depth_png[valid]).max()
    check(
        err < 1e-5 * depth_png.max() and (depth[~valid] == 0).all(),
        f"frame 0's depth is the PNG's in metres (max difference {err:.1e} m, {valid.sum()} valid pixels)",
    )
    rgb_png = np.asarray(Image.open(seq / listed("rgb.txt")).convert("RGB"))
    image = flat(column_by_frame(entities, "/world/camera/image", "Image:buffer")[0]).astype(np.uint8)
    check(image.size == rgb_png.size and (image == rgb_png.reshape(-1)).all(), "frame 0's image is the RGB PNG")


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "slam":
        slam(sys.argv[2], Path(sys.argv[3]))
    elif len(sys.argv) in (5, 6) and sys.argv[1] == "odometry":
        odometry(sys.argv[2], Path(sys.argv[3]), Path(sys.argv[4]))
    else:
        sys.exit(__doc__)
    if failures:
        print(f"{len(failures)} checks failed")
        sys.exit(1)
    print("all checks passed")
