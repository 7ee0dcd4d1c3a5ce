"""rgbid.graph.optimize against `rgbid graph optimize` on a small noisy SE(2) loop."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

import rgbid
from conftest import run_cli


def write_square(path: Path) -> np.ndarray:
    """A 2 m square walked twice (8 poses, odometry with a 0.05 rad error on one edge, and loop
    edges between the laps). Returns the true poses (x, y, theta)."""
    truth = []
    for k in range(8):
        side = k % 4
        x, y = [(0, 0), (2, 0), (2, 2), (0, 2)][side]
        truth.append((x, y, side * math.pi / 2))
    truth = np.array(truth, float)
    info = "100 0 0 100 0 1000"
    lines = []
    for i, (x, y, t) in enumerate(truth):
        lines.append(f"VERTEX_SE2 {i} {x + 0.1 * i} {y} {t}")

    def rel(i, j, noise=0.0):
        xi, yi, ti = truth[i]
        xj, yj, tj = truth[j]
        c, s = math.cos(ti), math.sin(ti)
        dx, dy = xj - xi, yj - yi
        dt = (tj - ti + math.pi) % (2 * math.pi) - math.pi + noise
        return f"EDGE_SE2 {i} {j} {c * dx + s * dy} {-s * dx + c * dy} {dt} {info}"

    for i in range(7):
        lines.append(rel(i, i + 1, 0.05 if i == 2 else 0.0))
    for i in range(4):
        lines.append(rel(i, i + 4))
    path.write_text("\n".join(lines) + "\n")
    return truth


def read_vertices(path: Path) -> np.ndarray:
    rows = [l.split() for l in path.read_text().splitlines() if l.startswith("VERTEX_SE2")]
    return np.array([[float(v) for v in r[2:5]] for r in rows])


def test_optimize_matches_the_cli(tmp_path: Path):
    g = tmp_path / "square.g2o"
    truth = write_square(g)
    poses, summary = rgbid.graph.optimize(g)
    assert poses.shape == (8, 3)
    for k in ("initial_cost", "final_cost", "iterations", "time_s", "termination", "chi2"):
        assert k in summary
    assert summary["final_cost"] <= summary["initial_cost"]
    # The optimum spreads the one bad edge over the loop: close to the truth, not equal.
    err = np.abs(poses[:, :2] - truth[:, :2]).max()
    assert err < 0.2, err
    out = tmp_path / "out.g2o"
    stdout = run_cli("graph", "optimize", str(g), "--out", str(out))
    cli = read_vertices(out)
    np.testing.assert_allclose(poses, cli, atol=1e-5)
    chi2 = float(re.search(r"chi2 (\S+)", stdout.split("final:")[1]).group(1))
    assert summary["chi2"] == pytest.approx(chi2, rel=1e-5)
    with pytest.raises(ValueError, match="cost"):
        rgbid.graph.optimize(g, cost="l1")
