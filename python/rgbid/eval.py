"""Trajectory evaluation (TUM definitions): absolute trajectory error and relative pose error.

Both take ``float64[N, 8]`` arrays (``t tx ty tz qx qy qz qw``, ``world_from_camera``), match
poses by time stamp (within ``max_diff`` seconds) and return dicts of metres / degrees with
``rmse``, ``mean``, ``median``, ``std``, ``min``, ``max`` and ``matched`` (pose pairs used).
"""

from __future__ import annotations

from typing import Any, Dict

import numpy as np

from ._rgbid import evaluate

__all__ = ["ate", "rpe", "evaluate"]


def _stats(s: Dict[str, Any]) -> Dict[str, Any]:
    out = {k: s[k] for k in ("rmse", "mean", "median", "std", "min", "max")}
    out["matched"] = s["count"]
    return out


def ate(gt: np.ndarray, est: np.ndarray, max_diff: float = 0.02, scale: bool = False) -> Dict[str, Any]:
    """Absolute trajectory error of the translations, metres, after aligning ``est`` to ``gt``
    (rigid, or a similarity with ``scale=True`` for monocular trajectories).

    Returns ``rmse``, ``mean``, ``median``, ``std``, ``min``, ``max`` (metres), ``matched``
    and ``scale`` (the alignment's scale, 1 for a rigid one).
    """
    m = evaluate(gt, est, 1.0, max_diff, scale)
    out = _stats(m["ate"]["translation"])
    out["scale"] = m["ate"]["alignment"]["scale"]
    return out


def rpe(gt: np.ndarray, est: np.ndarray, delta: float = 1.0, max_diff: float = 0.02) -> Dict[str, Any]:
    """Relative pose error over ``delta`` seconds: ``rmse``, ``mean``, ``median``, ``std``,
    ``min``, ``max`` of the translation drift (metres), ``matched`` (pose pairs), and
    ``rotation_deg`` (the same statistics of the rotation drift, degrees).

    Raises ``ValueError`` when no pair of poses spans ``delta``.
    """
    m = evaluate(gt, est, delta, max_diff, False)
    r = m.get("rpe")
    if r is None:
        raise ValueError(f"no pose pairs span delta = {delta} s")
    out = _stats(r["translation_m"])
    out["rotation_deg"] = _stats(r["rotation_deg"])
    return out
