#!/usr/bin/env bash
# The thesis-formulation options of issue 33, each on both real sequences: odometry variants
# with OpenCV RGB_DEPTH in the same run (`rgbid bench odometry`), iterations per level
# (`rgbid odometry --csv`), then SLAM variants. Usage: scripts/thesis_options.sh [OUT_DIR]
# (RGBID_BIN, RGBID_DATA, RGBID_PYTHON override the binary, data folder and peer Python);
# then `python3 scripts/thesis_options.py OUT_DIR` writes docs/results/thesis_options.json.
# Every variant is spelled out with --set, so the figures do not depend on the defaults.
set -u
B=${RGBID_BIN:-target/release/rgbid}
PY=${RGBID_PYTHON:-python3}
D=${RGBID_DATA:-../shared/data/rgbd}
O=${1:-/tmp/thesis-runs}
mkdir -p "$O"
uptime > "$O/load_start.txt"
# Odometry: the defaults spelled out, then one departure (or thesis formulation) at a time.
DEFAULTS="--set covisibility_test=consistent --set geometric_sampling=nearest --set location=both --set linearisation=current"
odo_variant() {
  case $1 in
    base) echo "$DEFAULTS" ;;
    depthcovis) echo "$DEFAULTS --set covisibility_test=depth" ;;
    coarse) echo "$DEFAULTS --set geometric_sampling=coarselinear" ;;
    loczero) echo "$DEFAULTS --set location=zero" ;;
    locphoto) echo "$DEFAULTS --set location=photometric" ;;
    reflin) echo "$DEFAULTS --set linearisation=reference" ;;
  esac
}
slam_variant() {
  local odo="--set odometry.covisibility_test=consistent --set odometry.location=both --set odometry.linearisation=current"
  local thesis="--set fusion.tol_sigmas=3 --set fusion.occlusion=true --set fusion.both_directions=true"
  local fixed="--set fusion.tol_sigmas=0 --set fusion.occlusion=false --set fusion.both_directions=false"
  case $1 in
    default) echo "$odo $thesis" ;;
    fixedfusion) echo "$odo $fixed" ;;
    nocap) echo "$odo $thesis --set fusion.max_weight=1e9" ;;
    loczero) echo "$odo $thesis --set odometry.location=zero" ;;
    reflin) echo "$odo $thesis --set odometry.linearisation=reference" ;;
  esac
}
for seq in tum_fr1_rpy_0_199 redkitchen_0_299; do
  cam=""
  [ "$seq" = tum_fr1_rpy_0_199 ] && cam="--camera tum_fr1"
  peers=cv_rgbd # OpenCV once per sequence, in the base run
  for v in base depthcovis coarse loczero locphoto reflin; do
    # shellcheck disable=SC2046,SC2086
    "$B" bench odometry "$D/$seq" $cam --backends cpu --peers "$peers" --python "$PY" \
      $(odo_variant $v) --out "$O/$seq-$v" --json "$O/$seq-$v.json" > "$O/$seq-$v.log" 2>&1
    peers=""
  done
  for v in base coarse; do
    # shellcheck disable=SC2046,SC2086
    "$B" odometry "$D/$seq" $cam --backend cpu $(odo_variant $v) --csv "$O/$seq-$v.csv" \
      -o "$O/$seq-$v.txt" > "$O/$seq-$v-odo.log" 2>&1
  done
  for v in default fixedfusion nocap loczero reflin; do
    # shellcheck disable=SC2046,SC2086
    /usr/bin/time -f "%e s wall" "$B" slam "$D/$seq" $cam --backend cpu \
      --out "$O/slam-$seq-$v" $(slam_variant $v) > "$O/slam-$seq-$v.log" 2>&1
    "$B" eval "$D/$seq/groundtruth.txt" "$O/slam-$seq-$v/trajectory.txt" --json \
      > "$O/slam-$seq-$v.eval.json" 2>&1
  done
done
uptime > "$O/load_end.txt"
