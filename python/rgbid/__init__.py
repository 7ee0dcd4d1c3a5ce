"""rgbid: dense RGB-D odometry with inverse depth and RGB-ID SLAM, numpy in and out.

The systems of the thesis *Real-time Metric Localisation with Wearable Vision Systems*
(Gutierrez-Gomez, 2016), implemented in Rust with WGSL compute kernels (any GPU through wgpu,
or the CPU).

Conventions: transforms are named ``a_from_b`` (``p_a = a_from_b @ p_b``), as ``float64[4, 4]``
homogeneous matrices; metres, radians, seconds; camera frame x right, y down, z forward;
integer pixel coordinates are pixel centres. Trajectories are ``float64[N, 8]`` arrays with
the TUM columns ``t tx ty tz qx qy qz qw`` (``world_from_camera``).

Images are RGB (``uint8[H, W, 3]``) or grey (``uint8[H, W]``): a BGR image from OpenCV must
be converted by the caller (``cv2.cvtColor(img, cv2.COLOR_BGR2RGB)``). Depth is
``uint16[H, W]`` with a depth factor (units per metre: TUM 5000, millimetre sensors 1000;
0 = no measurement) or ``float32[H, W]`` in metres. Arrays must be C-contiguous; they are
read in place (the only copy of a frame is the one the library keeps), and the interpreter
lock is released while rgbid works, so several systems can run in threads.

Bad input raises ``ValueError``; failures inside rgbid raise :class:`RgbidError`.

Submodules: :mod:`rgbid.eval` (ATE / RPE), :mod:`rgbid.graph` (pose-graph optimisation),
:mod:`rgbid.synth` (generated sequences with exact ground truth).
"""

from __future__ import annotations

from ._rgbid import (
    Camera,
    EventStream,
    Odometry,
    RgbidError,
    Sequence,
    Slam,
    SlamResult,
    TsdfVolume,
    __version__,
    default_config,
    read_run,
    read_sequence,
    read_trajectory,
    write_trajectory,
)
from . import eval, graph, synth  # noqa: E402  (submodules need the names above)

__all__ = [
    "Camera",
    "EventStream",
    "Odometry",
    "RgbidError",
    "Sequence",
    "Slam",
    "SlamResult",
    "TsdfVolume",
    "__version__",
    "default_config",
    "eval",
    "graph",
    "read_run",
    "read_sequence",
    "read_trajectory",
    "synth",
    "write_trajectory",
]
