#!/usr/bin/env bash
# Analogues of the thesis' tables 4.1-4.3 and 6.1 on the two real sequences: odometry
# variants through `rgbid bench odometry` (OpenCV RGB_DEPTH in the first run of each
# sequence), then `rgbid slam` for table 6.1. Usage: scripts/thesis_tables.sh [OUT_DIR]
# (RGBID_BIN, RGBID_DATA, RGBID_PYTHON override the binary, data folder and peer Python);
# then `python3 scripts/thesis_tables.py OUT_DIR` writes docs/results/thesis_tables.json.
# Each variant sets only what it varies; everything else is the default configuration.
set -u
B=${RGBID_BIN:-target/release/rgbid}
PY=${RGBID_PYTHON:-python3}
D=${RGBID_DATA:-../shared/data/rgbd}
O=${1:-/tmp/thesis-tables}
mkdir -p "$O"
uptime > "$O/load_start.txt"
# name|options. Table 4.1: estimator x parametrisation x scale; 4.2: terms; 4.3: performance.
variants() {
  for est in student huber tukey leastsquares; do
    for geo in inversedepth depth; do
      for sc in ml mad mscale; do
        # The M-scale differs from ML for Huber and Tukey only.
        case $est-$sc in student-mscale | leastsquares-mscale) continue ;; esac
        echo "t41-$est-$geo-$sc|--set estimator=$est --set geometric=$geo --set scale=$sc"
      done
    done
  done
  for t in photometric geometric; do echo "t42-$t|--set terms=$t"; done
  echo "t43-levels3|--set levels=3"
  echo "t43-full-resolution|--set max_width=0"
  echo "t43-stop-level2|--set stop_level=2"
  echo "t43-samples4800|--set max_samples=4800"
  echo "t43-iterations-halved|--set iterations=[3,4,5]"
  echo "t43-frame-to-frame|--set reference_switch=null"
  echo "t43-no-constant-velocity|--set constant_velocity=false"
}
for seq in tum_fr1_rpy_0_199 redkitchen_0_299; do
  cam=""
  [ "$seq" = tum_fr1_rpy_0_199 ] && cam="--camera tum_fr1"
  # The default configuration, with the peer.
  # shellcheck disable=SC2086
  "$B" bench odometry "$D/$seq" $cam --backends cpu --peers cv_rgbd --python "$PY" \
    --out "$O/$seq-default" --json "$O/$seq-default.json" > "$O/$seq-default.log" 2>&1
  variants | while IFS='|' read -r name opts; do
    # shellcheck disable=SC2086
    "$B" bench odometry "$D/$seq" $cam --backends cpu --peers "" $opts \
      --out "$O/$seq-$name" --json "$O/$seq-$name.json" > "$O/$seq-$name.log" 2>&1 \
      || echo "$seq $name failed (see $O/$seq-$name.log)"
  done
  # shellcheck disable=SC2086
  /usr/bin/time -f "%e s wall" "$B" slam "$D/$seq" $cam --backend cpu --out "$O/slam-$seq" \
    > "$O/slam-$seq.log" 2>&1
  for t in trajectory odometry; do
    "$B" eval "$D/$seq/groundtruth.txt" "$O/slam-$seq/$t.txt" --json > "$O/slam-$seq-$t.eval.json" 2>&1
  done
done
uptime > "$O/load_end.txt"
