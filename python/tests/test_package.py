"""The Python package against ground truth and against the `rgbid` program."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import rgbid
from conftest import FRAMES, SCENE, SEED, TRAJECTORY, WIDTH, run_cli


def relative_to_first(traj: np.ndarray) -> np.ndarray:
    """Poses as 4x4 matrices relative to the first one: first^-1 @ pose_i."""
    mats = np.stack([to_matrix(r) for r in traj])
    inv = np.linalg.inv(mats[0])
    return np.einsum("ij,njk->nik", inv, mats)


def to_matrix(row: np.ndarray) -> np.ndarray:
    x, y, z, w = row[4:8] / np.linalg.norm(row[4:8])
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = row[1:4]
    return m


def track_all(seq, backend="cpu", model=None, initial=None):
    odo = rgbid.Odometry(seq.camera, backend=backend, model=model)
    if initial is not None:
        odo.set_initial_pose(initial)
    rows = []
    for t, image, depth, factor in seq:
        r = odo.track(image, depth, factor, t)
        assert r["status"] == "ok", r
        assert (r["model_ms"] is None) == (model is None), r
        m = r["world_from_camera"]
        assert m.shape == (4, 4) and m.dtype == np.float64
        rows.append(pose_row(t, m))
    return np.array(rows)


def pose_row(t: float, m: np.ndarray) -> list:
    r = m[:3, :3]
    # Quaternion from a rotation matrix (Shepperd), enough for comparisons of the rows.
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return [t, *m[:3, 3], x, y, z, w]


def test_tracks_a_generated_sequence():
    # At 320x240: at 160x120 the sensor noise dominates the error of this short sequence.
    seq = rgbid.synth.render(SCENE, TRAJECTORY, FRAMES, SEED, width=320)
    assert len(seq) == FRAMES and seq.path is None
    est = track_all(seq)
    gt = seq.groundtruth
    assert gt.shape == (FRAMES, 8)
    ate = rgbid.eval.ate(gt, est)
    assert ate["matched"] == FRAMES
    # Within a centimetre over half a metre of handheld motion; a tracker that loses the
    # motion (wrong sign, wrong units, frames mixed up) is off by decimetres.
    assert ate["rmse"] < 0.01, ate
    path_length = np.linalg.norm(np.diff(gt[:, 1:4], axis=0), axis=1).sum()
    assert path_length > 0.05, "the sequence must move for the check to mean anything"


def test_odometry_matches_the_cli(tum_dir: Path, tmp_path: Path):
    out = tmp_path / "cli.txt"
    run_cli("odometry", str(tum_dir), "--out", str(out), "--backend", "cpu")
    cli = rgbid.read_trajectory(out)
    py = track_all(rgbid.read_sequence(tum_dir))
    assert cli.shape == py.shape == (FRAMES, 8)
    np.testing.assert_allclose(cli[:, 0], py[:, 0], atol=1e-6)
    a, b = relative_to_first(cli), relative_to_first(py)
    # Translations within 1e-6 m; the file's 7 decimals bound the rounding.
    assert np.abs(a[:, :3, 3] - b[:, :3, 3]).max() < 1e-6
    assert np.abs(a[:, :3, :3] - b[:, :3, :3]).max() < 1e-6


def test_frame_to_model_odometry_matches_the_cli(tum_dir: Path, tmp_path: Path):
    out = tmp_path / "cli.txt"
    run_cli(
        "odometry", str(tum_dir), "--out", str(out), "--backend", "cpu",
        "--reference", "model", "--voxel", "0.03",
    )
    cli = rgbid.read_trajectory(out)
    seq = rgbid.read_sequence(tum_dir)
    # The program starts at the ground truth's first pose, and a TSDF's voxels are fixed in
    # the world frame, so the same start is needed for the same model.
    gt = seq.groundtruth
    first = seq[0][0]
    initial = to_matrix(gt[np.argmin(np.abs(gt[:, 0] - first))])
    py = track_all(seq, model={"voxel": 0.03}, initial=initial)
    assert cli.shape == py.shape == (FRAMES, 8)
    a, b = relative_to_first(cli), relative_to_first(py)
    assert np.abs(a[:, :3, 3] - b[:, :3, 3]).max() < 1e-6
    assert np.abs(a[:, :3, :3] - b[:, :3, :3]).max() < 1e-6
    # Not the frame-to-reference trajectory under another name.
    frame = relative_to_first(track_all(seq))
    assert np.abs(frame[:, :3, 3] - b[:, :3, 3]).max() > 1e-6
    with pytest.raises(ValueError, match="unknown key"):
        rgbid.Odometry(seq.camera, backend="cpu", model={"voxels": 0.03})
    with pytest.raises(ValueError, match="voxel"):
        rgbid.Odometry(seq.camera, backend="cpu", model={"voxel": -1.0})


def test_slam_matches_the_cli(tum_dir: Path, tmp_path: Path):
    out = tmp_path / "run"
    run_cli("slam", str(tum_dir), "--out", str(out), "--backend", "cpu")
    cli = rgbid.read_trajectory(out / "trajectory.txt")
    seq = rgbid.read_sequence(tum_dir)
    slam = rgbid.Slam(seq.camera, backend="cpu")
    events = slam.events()
    statuses = []
    for t, image, depth, factor in seq:
        r = slam.process(image, depth, factor, t)
        statuses.append(r["status"])
    result = slam.finish()
    assert result.trajectory.shape == cli.shape == (FRAMES, 8)
    a, b = relative_to_first(cli), relative_to_first(result.trajectory)
    assert np.abs(a[:, :3, 3] - b[:, :3, 3]).max() < 1e-6
    assert np.abs(a[:, :3, :3] - b[:, :3, :3]).max() < 1e-6
    assert result.statuses == statuses
    kinds = [e["kind"] for e in events]
    assert kinds.count("keyframe_created") == result.keyframes.shape[0] >= 1
    assert result.points.shape[1] == 3 and result.points.shape[0] > 100
    assert result.colors.shape == (result.points.shape[0], 3) and result.colors.dtype == np.uint8
    # The run folder the CLI wrote reads back with the same trajectory.
    run = rgbid.read_run(out)
    assert run["complete"]
    np.testing.assert_array_equal(run["trajectory"], cli)
    assert run["summary"]["frames"] == FRAMES
    # The map saves and a new Slam loads it.
    result.save_map(tmp_path / "map.bin")
    again = rgbid.Slam(seq.camera, backend="cpu", map_path=tmp_path / "map.bin")
    assert again.frames == 0


def slam_colors(seq, config=None) -> np.ndarray:
    slam = rgbid.Slam(seq.camera, config=config, backend="cpu")
    for t, image, depth, factor in seq:
        slam.process(image, depth, factor, t)
    colors = slam.finish().colors
    assert colors.dtype == np.uint8 and colors.ndim == 2 and colors.shape[1] == 3
    assert colors.shape[0] > 100
    return colors


def test_slam_colors_are_the_keyframes_rgb():
    # The generated scene is coloured: keyframes keep their reference frame's RGB, so most
    # model points differ between channels; with keyframe_colour off every point is grey.
    seq = rgbid.synth.render(SCENE, TRAJECTORY, FRAMES, SEED, width=WIDTH)
    colors = slam_colors(seq).astype(int)
    non_grey = (colors[:, 0] != colors[:, 1]) | (colors[:, 1] != colors[:, 2])
    assert non_grey.mean() > 0.1, non_grey.mean()
    grey = slam_colors(seq, config={"keyframe_colour": False})
    assert (grey[:, 0] == grey[:, 1]).all() and (grey[:, 1] == grey[:, 2]).all()
    assert rgbid.default_config("slam")["keyframe_colour"] is True


def test_read_sequence_gives_the_stored_frames(tum_dir: Path):
    seq = rgbid.read_sequence(tum_dir)
    mem = rgbid.synth.render(SCENE, TRAJECTORY, FRAMES, SEED, width=WIDTH)
    assert len(seq) == len(mem) == FRAMES
    cam = seq.camera
    assert (cam.width, cam.height) == (WIDTH, WIDTH * 3 // 4)
    assert seq.depth_factor == 5000.0
    np.testing.assert_allclose(seq.timestamps, mem.timestamps, atol=1e-6)
    for i in (0, FRAMES // 2, -1):
        t, image, depth, factor = seq[i]
        t2, image2, depth2, _ = mem[i]
        assert image.dtype == np.uint8 and image.shape == (cam.height, cam.width, 3)
        assert depth.dtype == np.uint16 and depth.shape == (cam.height, cam.width)
        assert factor == 5000.0 and abs(t - t2) < 1e-6
        # PNG is lossless: the folder holds exactly what was rendered.
        np.testing.assert_array_equal(image, image2)
        np.testing.assert_array_equal(depth, depth2)
    with pytest.raises(IndexError):
        seq[FRAMES]
    # The ground truth of the folder is the renderer's (the file keeps 7 decimals).
    np.testing.assert_allclose(seq.groundtruth, mem.groundtruth, atol=1e-6)


def test_eval_matches_the_cli(tum_dir: Path, tmp_path: Path):
    seq = rgbid.read_sequence(tum_dir)
    est = track_all(seq)
    # Perturb so that the errors are not tiny.
    est[:, 1:4] += 0.01 * np.sin(np.arange(len(est)))[:, None]
    est_path = tmp_path / "est.txt"
    rgbid.write_trajectory(est_path, est)
    cli = json.loads(run_cli("eval", str(tum_dir / "groundtruth.txt"), str(est_path), "--json", "--delta", "0.5"))
    gt = rgbid.read_trajectory(tum_dir / "groundtruth.txt")
    est_back = rgbid.read_trajectory(est_path)
    ate = rgbid.eval.ate(gt, est_back)
    rpe = rgbid.eval.rpe(gt, est_back, delta=0.5)
    for k in ("rmse", "mean", "median", "max"):
        assert ate[k] == pytest.approx(cli["ate"]["translation"][k], rel=1e-12, abs=1e-15)
        assert rpe[k] == pytest.approx(cli["rpe"]["translation_m"][k], rel=1e-12, abs=1e-15)
    assert ate["matched"] == cli["ate"]["translation"]["count"] == FRAMES
    assert rpe["matched"] == cli["rpe"]["translation_m"]["count"]
    assert ate["rmse"] > 0.003


def test_config_as_a_dict():
    cam = rgbid.Camera.preset("tum_fr1")
    assert (cam.width, cam.height) == (640, 480) and cam.depth_factor == 5000.0
    assert cam.readout > 0 and rgbid.Camera.preset("tum_fr3").readout == 0.0
    assert rgbid.Camera(500, 500, 320, 240, 640, 480, readout=0.02).readout == 0.02
    with pytest.raises(ValueError, match="readout"):
        rgbid.Camera(500, 500, 320, 240, 640, 480, readout=-1.0)
    defaults = rgbid.default_config("odometry")
    assert defaults["estimator"] == "student"
    rgbid.Odometry(cam, config={"estimator": "huber", "levels": 3}, backend="cpu")
    with pytest.raises(ValueError, match="estimatr"):
        rgbid.Odometry(cam, config={"estimatr": "huber"}, backend="cpu")
    with pytest.raises(ValueError, match="backend"):
        rgbid.Odometry(cam, backend="tpu")
    slam_defaults = rgbid.default_config("slam")
    assert "odometry" in slam_defaults
    with pytest.raises(ValueError, match="odometry.levls"):
        rgbid.Slam(cam, config={"odometry": {"levls": 3}}, backend="cpu")


def test_pose_round_trip(tmp_path: Path):
    seq = rgbid.synth.render(SCENE, TRAJECTORY, 5, SEED, width=WIDTH)
    gt = seq.groundtruth
    p = tmp_path / "gt.txt"
    rgbid.write_trajectory(p, gt)
    np.testing.assert_allclose(rgbid.read_trajectory(p), gt, atol=1e-6)
    odo = rgbid.Odometry(seq.camera, backend="cpu")
    start = to_matrix(gt[0])
    odo.set_initial_pose(start)
    t, image, depth, factor = seq[0]
    r = odo.track(image, depth, factor, t)
    np.testing.assert_allclose(r["world_from_camera"], start, atol=1e-12)
    with pytest.raises(ValueError, match="rigid"):
        odo.set_initial_pose(2 * start)
