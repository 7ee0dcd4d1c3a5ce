"""rgbid.TsdfVolume: integration against the frames' own depth, save / load round trips,
the CLI reading a volume saved from Python, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

import rgbid
from conftest import run_cli

FRAMES = 8


def to_matrix(row: np.ndarray) -> np.ndarray:
    x, y, z, w = row[4:8] / np.linalg.norm(row[4:8])
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = row[1:4]
    return m


@pytest.fixture(scope="module")
def seq():
    # Without sensor noise: at 160 pixels wide a Kinect's disparity noise is centimetres of
    # depth, and the ray cast is compared with single frames below.
    s = rgbid.synth.render("office", "handheld", FRAMES, 5, width=160, noise=False)
    frames = [s[i] for i in range(len(s))]
    poses = [to_matrix(r) for r in s.groundtruth]
    return s.camera, frames, poses


def integrate(vol, frames, poses):
    for (_, image, depth, factor), pose in zip(frames, poses):
        assert vol.integrate(depth, factor, pose, image=image) > 0


def test_ray_cast_sees_the_integrated_depth(seq):
    camera, frames, poses = seq
    vol = rgbid.TsdfVolume(camera, voxel=0.02, backend="cpu")
    integrate(vol, frames, poses)
    assert vol.frames == FRAMES and vol.block_count > 100
    assert vol.params["voxel_size"] == 0.02
    # The CPU backend keeps every block in its (host) storage: nothing is paged.
    assert vol.paging["resident_blocks"] == vol.block_count
    assert vol.paging["host_blocks"] == 0 and vol.paging["page_outs"] == 0
    _, _, depth, factor = frames[3]
    r = vol.ray_cast(poses[3])
    assert r["depth"].shape == depth.shape and r["depth"].dtype == np.float32
    assert r["normals"].shape == depth.shape + (3,)
    assert r["colour"].shape == depth.shape + (3,) and r["colour"].dtype == np.uint8
    measured = depth.astype(np.float64) / factor
    both = (measured > 0) & (r["depth"] > 0)
    assert both.mean() > 0.7, both.mean()
    # The fused surface lies within a fraction of a voxel of each frame's depth.
    err = np.abs(r["depth"][both] - measured[both])
    assert np.median(err) < 0.01, np.median(err)
    # Unit normals, or zero where a neighbour of the surface voxel is unobserved.
    n = np.linalg.norm(r["normals"][both], axis=1)
    unit = np.abs(n - 1.0) < 1e-3
    assert (unit | (n == 0)).all() and unit.mean() > 0.9, unit.mean()
    assert r["colour"][both].mean() > 10

    vertices, triangles, normals, colours = vol.extract_mesh()
    assert vertices.dtype == np.float32 and vertices.shape[1] == 3
    assert triangles.dtype == np.uint32 and triangles.shape[1] == 3
    assert normals.shape == vertices.shape and colours.shape == vertices.shape
    assert colours.dtype == np.uint8
    assert len(triangles) > 1000 and triangles.max() < len(vertices)
    assert np.isfinite(vertices).all()


def test_save_load_continues_exactly(seq, tmp_path):
    camera, frames, poses = seq
    saved = rgbid.TsdfVolume(camera, voxel=0.02, backend="cpu")
    integrate(saved, frames[:4], poses[:4])
    path = tmp_path / "v.tsdf"
    saved.save(path)
    loaded = rgbid.TsdfVolume.load(str(path), backend="cpu")
    assert loaded.frames == 4 and loaded.block_count == saved.block_count
    for a, b in zip(saved.extract_mesh(), loaded.extract_mesh()):
        np.testing.assert_array_equal(a, b)
    ra, rb = saved.ray_cast(poses[5]), loaded.ray_cast(poses[5])
    for k in ("depth", "normals", "colour"):
        np.testing.assert_array_equal(ra[k], rb[k])
    integrate(saved, frames[4:], poses[4:])
    integrate(loaded, frames[4:], poses[4:])
    for a, b in zip(saved.extract_mesh(), loaded.extract_mesh()):
        np.testing.assert_array_equal(a, b)

    # The CLI reads the volume saved from Python and extracts the same mesh.
    loaded.save(path)
    out = run_cli("mesh", "--volume", str(path), "--backend", "cpu", "--out", str(tmp_path / "m.ply"))
    n_vertices = len(loaded.extract_mesh()[0])
    assert f"{n_vertices} vertices" in out, out


def test_depth_only_and_metres(seq):
    camera, frames, poses = seq
    a = rgbid.TsdfVolume(camera, voxel=0.04, backend="cpu")
    b = rgbid.TsdfVolume(camera, voxel=0.04, backend="cpu")
    for (_, _, depth, factor), pose in zip(frames[:3], poses[:3]):
        a.integrate(depth, factor, pose)
        b.integrate(depth.astype(np.float32) / np.float32(factor), None, pose)
    va, _, _, ca = a.extract_mesh()
    vb, _, _, _ = b.extract_mesh()
    assert len(va) > 100
    # Depth only: no colour was integrated.
    assert ca.max() == 0
    assert abs(len(va) - len(vb)) < 0.01 * len(va)


def test_bad_input(seq, tmp_path):
    camera, frames, poses = seq
    _, image, depth, factor = frames[0]
    with pytest.raises(ValueError, match="voxel_size"):
        rgbid.TsdfVolume(camera, voxel=-0.01, backend="cpu")
    with pytest.raises(ValueError, match="min_depth"):
        rgbid.TsdfVolume(camera, min_depth=5.0, max_depth=4.0, backend="cpu")
    with pytest.raises(ValueError, match="backend"):
        rgbid.TsdfVolume(camera, backend="tpu")
    with pytest.raises(ValueError, match="device_blocks"):
        rgbid.TsdfVolume(camera, backend="cpu", device_blocks=0)
    vol = rgbid.TsdfVolume(camera, voxel=0.04, backend="cpu")
    with pytest.raises(ValueError, match="dtype"):
        vol.integrate(depth.astype(np.int32), factor, poses[0])
    with pytest.raises(ValueError, match="camera"):
        vol.integrate(depth[:, :80].copy(), factor, poses[0])
    with pytest.raises(ValueError, match="rigid"):
        vol.integrate(depth, factor, 2 * poses[0])
    with pytest.raises(ValueError, match="shape"):
        vol.integrate(depth, factor, poses[0], image=image[:60].copy())
    with pytest.raises(ValueError, match="float64"):
        vol.ray_cast(np.eye(3))
    missing = tmp_path / "missing.tsdf"
    with pytest.raises(rgbid.RgbidError, match="missing.tsdf"):
        rgbid.TsdfVolume.load(missing, backend="cpu")
    bad = tmp_path / "bad.tsdf"
    bad.write_bytes(b"RGBIDTSD" + b"\x07\x00\x00\x00" + bytes(200))
    with pytest.raises(rgbid.RgbidError, match="bad.tsdf.*version 7"):
        rgbid.TsdfVolume.load(bad, backend="cpu")
