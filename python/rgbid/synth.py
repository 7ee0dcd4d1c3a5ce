"""Generated RGB-D sequences with exact ground truth (procedural scenes, ray casting,
Kinect-like sensor noise)."""

from __future__ import annotations

from typing import Optional

from ._rgbid import Sequence, synth_render

__all__ = ["render"]


def render(
    scene: str,
    trajectory: str,
    frames: int,
    seed: int,
    width: int = 320,
    out: Optional[str] = None,
    noise: bool = True,
) -> Sequence:
    """Renders ``frames`` frames (30 per second) of ``scene`` (``office``, ...) along
    ``trajectory`` (``loop``, ``handheld``, ...) with ``seed``, ``width`` pixels wide (height
    3/4 of it; fx = 525 px at 640 wide).

    With ``out`` the frames go to a TUM folder there (``rgb/``, ``depth/``, ``rgb.txt``,
    ``depth.txt``, ``groundtruth.txt``, ``calib.txt``) which is read back; without it frames
    are rendered on demand. Either way a :class:`rgbid.Sequence` comes back, with
    ``groundtruth``.
    """
    return synth_render(scene, trajectory, frames, seed, width, None if out is None else str(out), noise)
