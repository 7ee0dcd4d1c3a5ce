"""Pose-graph optimisation of g2o and iSAM files (thesis ch. 7)."""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np

from ._rgbid import graph_optimize

__all__ = ["optimize"]


def optimize(path: str, cost: str = "geodesic", max_iterations: Optional[int] = None) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Optimises the pose graph in ``path`` (``.g2o``, else iSAM text) as ``rgbid graph
    optimize`` does by default.

    ``cost``: ``"geodesic"`` (error whitened by the full information matrix, g2o's chi2) or
    ``"sesync"`` (chordal). Returns ``(poses, summary)``: ``poses`` is ``float64[N, 3]``
    (``x y theta``, metres and radians) for 2D graphs or ``float64[N, 7]`` (``tx ty tz qx qy
    qz qw``) for 3D ones, in the file's vertex order; ``summary`` has ``initial_cost``,
    ``final_cost``, ``iterations``, ``time_s`` (solver seconds), ``init_time_s``,
    ``termination`` and ``chi2``.
    """
    return graph_optimize(str(path), cost, max_iterations)
