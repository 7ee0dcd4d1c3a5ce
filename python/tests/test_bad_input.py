"""Bad frames raise ValueError with a message that says what is wrong."""

from __future__ import annotations

import numpy as np
import pytest

import rgbid

H, W = 60, 80


@pytest.fixture(scope="module")
def odo():
    cam = rgbid.Camera(70.0, 70.0, 39.5, 29.5, W, H)
    return rgbid.Odometry(cam, config={"levels": 2}, backend="cpu")


def frame():
    rng = np.random.default_rng(1)
    return rng.integers(0, 255, (H, W, 3), dtype=np.uint8), np.full((H, W), 5000, np.uint16)


def test_a_good_frame_tracks(odo):
    image, depth = frame()
    assert odo.track(image, depth, 5000.0, 0.0)["status"] == "ok"
    assert odo.track(image[:, :, 0].copy(), depth, 5000.0, 0.1)["status"] == "ok"
    assert odo.track(image, depth.astype(np.float32) / 5000, None, 0.2)["status"] == "ok"


def test_wrong_dtype(odo):
    image, depth = frame()
    with pytest.raises(ValueError, match="image must be uint8.*float64"):
        odo.track(image.astype(np.float64), depth, 5000.0, 0.0)
    with pytest.raises(ValueError, match="depth must be uint16.*int32"):
        odo.track(image, depth.astype(np.int32), 5000.0, 0.0)
    with pytest.raises(ValueError, match="numpy array"):
        odo.track(image.tolist(), depth, 5000.0, 0.0)


def test_shape_mismatch(odo):
    image, depth = frame()
    with pytest.raises(ValueError, match="depth has shape"):
        odo.track(image, depth[:-1].copy(), 5000.0, 0.0)
    with pytest.raises(ValueError, match=r"uint8\[H, W, 3\]"):
        odo.track(np.zeros((H, W, 4), np.uint8), depth, 5000.0, 0.0)
    with pytest.raises(ValueError, match="frame is"):
        odo.track(np.zeros((H + 2, W, 3), np.uint8), np.zeros((H + 2, W), np.uint16), 5000.0, 0.0)


def test_non_contiguous(odo):
    image, depth = frame()
    with pytest.raises(ValueError, match="C-contiguous"):
        odo.track(image[:, ::-1], depth, 5000.0, 0.0)
    with pytest.raises(ValueError, match="C-contiguous"):
        odo.track(image, np.asfortranarray(depth), 5000.0, 0.0)


def test_bad_depth_factor(odo):
    image, depth = frame()
    for bad in (float("nan"), 0.0, -5000.0, float("inf")):
        with pytest.raises(ValueError, match="depth factor"):
            odo.track(image, depth, bad, 0.0)
    with pytest.raises(ValueError, match="needs depth_factor"):
        odo.track(image, depth, None, 0.0)
    with pytest.raises(ValueError, match="metres"):
        odo.track(image, depth.astype(np.float32), 5000.0, 0.0)


def test_bad_timestamp_and_camera(odo):
    image, depth = frame()
    with pytest.raises(ValueError, match="time"):
        odo.track(image, depth, 5000.0, float("nan"))
    with pytest.raises(ValueError):
        rgbid.Camera(-1.0, 70.0, 39.5, 29.5, W, H)
    with pytest.raises(ValueError):
        rgbid.Camera.preset("no_such_camera")


def test_errors_of_files_name_them(tmp_path):
    with pytest.raises(rgbid.RgbidError, match="nothing_here"):
        rgbid.read_sequence(tmp_path / "nothing_here")
    bad = tmp_path / "t.txt"
    bad.write_text("0 1 2 3\n")
    with pytest.raises(rgbid.RgbidError):
        rgbid.read_trajectory(bad)
    with pytest.raises(ValueError, match=r"float64\[N, 8\]"):
        rgbid.eval.ate(np.zeros((3, 7)), np.zeros((3, 8)))
