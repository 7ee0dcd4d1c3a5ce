"""The examples run: quickstart (SLAM, PLY, plot) and the Ray batch on four sequences."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_quickstart(tmp_path: Path):
    summary = load("quickstart").main(["--frames", "45", "--backend", "cpu", "--out", str(tmp_path)])
    assert (tmp_path / "trajectory.txt").read_text().count("\n") == summary["poses"] == 45
    assert summary["points"] > 100
    assert (tmp_path / "points.ply").read_text().startswith("ply\n")
    assert summary["ate_rmse_m"] < 0.05
    if "plot" in summary:
        assert (tmp_path / "quickstart.png").stat().st_size > 1000


def test_ray_batch_on_four_sequences():
    try:
        import ray  # noqa: F401
    except Exception as e:  # ImportError, or a broken install
        pytest.skip(f"Ray cannot be imported here ({type(e).__name__}: {e}); pip install ray")
    rows = load("ray_batch").main(["--sequences", "4", "--frames", "30", "--width", "128", "--num-cpus", "2"])
    assert len(rows) == 4
    assert len({r["sequence"] for r in rows}) == 4
    for r in rows:
        assert r["frames"] == 30 and r["seconds"] > 0
        assert math.isfinite(r["ate_rmse_m"]) and r["ate_rmse_m"] < 0.05, r
