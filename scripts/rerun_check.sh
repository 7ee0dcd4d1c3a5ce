#!/usr/bin/env bash
# Checks the `rerun` feature by hand (CI does not build its large dependency tree): builds
# rgbid with it, runs `rgbid slam` on a generated closed loop and `rgbid odometry` on a
# generated TUM folder, both with `--rerun save:...`, and reads the recordings back with the
# rerun Python SDK (scripts/rerun_check.py), checking entities and counts against the runs'
# own files.
#
#   scripts/rerun_check.sh [WORK_DIR]     (default /tmp/rgbid-rerun-check)
#
# Environment: CARGO_TARGET_DIR as for any build; RERUN_VENV, a venv with rerun-sdk 0.36
# (created under WORK_DIR when it does not exist: needs pip access to PyPI).
set -euo pipefail
cd "$(dirname "$0")/.."
work=${1:-/tmp/rgbid-rerun-check}
venv=${RERUN_VENV:-$work/venv}
mkdir -p "$work"

if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet 'rerun-sdk==0.36.*'
fi

cargo build --release --features rerun --bin rgbid
target=${CARGO_TARGET_DIR:-target}
rgbid="$target/release/rgbid"

echo "== rgbid slam --synth office:loop (150 frames, 1.3 laps, 160 px wide), CPU backend"
rm -rf "$work/slam" "$work/slam.rrd"
"$rgbid" slam --synth office:loop --frames 150 --laps 1.3 --width 160 --backend cpu \
  --out "$work/slam" --no-model --rerun "save:$work/slam.rrd"
ls -l "$work/slam.rrd"
"$venv/bin/python" scripts/rerun_check.py slam "$work/slam.rrd" "$work/slam"

echo "== rgbid odometry on a generated TUM folder (60 frames, 160 px wide), CPU backend"
rm -rf "$work/seq" "$work/odo.rrd" "$work/odo.txt" "$work/odo.csv" \
  "$work/seq"
"$rgbid" synth --scene office --trajectory handheld --frames 60 --width 160 --out "$work/seq"
"$rgbid" odometry "$work/seq" --backend cpu --out "$work/odo.txt" --csv "$work/odo.csv" \
  --rerun "save:$work/odo.rrd"
ls -l "$work/odo.rrd"
"$venv/bin/python" scripts/rerun_check.py odometry "$work/odo.rrd" "$work/odo.txt" "$work/odo.csv" \
  "$work/seq"
