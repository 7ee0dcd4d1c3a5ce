"""Shared fixtures: a small generated TUM folder and the `rgbid` program to compare with.

The CLI comparisons need the `rgbid` binary built from the same checkout: `RGBID_BIN`, else
`target/debug/rgbid` or `target/release/rgbid` under the repository (or `CARGO_TARGET_DIR`).
Without one those tests fail (they are part of the contract), they never skip.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

import rgbid

ROOT = Path(__file__).resolve().parents[2]

# A short handheld sequence: 40 frames (1.3 s) at 160x120, fast on two cores.
SCENE, TRAJECTORY, FRAMES, SEED, WIDTH = "office", "handheld", 40, 3, 160


def rgbid_bin() -> Path:
    if os.environ.get("RGBID_BIN"):
        return Path(os.environ["RGBID_BIN"])
    targets = [Path(os.environ["CARGO_TARGET_DIR"])] if os.environ.get("CARGO_TARGET_DIR") else []
    targets.append(ROOT / "target")
    for t in targets:
        for profile in ("debug", "release"):
            p = t / profile / "rgbid"
            if p.exists():
                return p
    pytest.fail("no rgbid binary: build it (cargo build) or set RGBID_BIN")


def run_cli(*args: str) -> str:
    r = subprocess.run([str(rgbid_bin()), *args], capture_output=True, text=True)
    assert r.returncode == 0, f"rgbid {' '.join(args)} failed:\n{r.stdout}\n{r.stderr}"
    return r.stdout


@pytest.fixture(scope="session")
def tum_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("seq") / "office"
    rgbid.synth.render(SCENE, TRAJECTORY, FRAMES, SEED, width=WIDTH, out=str(out))
    return out
