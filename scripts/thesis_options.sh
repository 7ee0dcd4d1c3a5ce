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
odo_variant() {
  local cur="--set linearisation=current"
  case $1 in
    base) echo "--set covisibility_test=depth --set geometric_sampling=nearest $cur" ;;
    covis) echo "--set covisibility_test=consistent --set geometric_sampling=nearest $cur" ;;
    coarse) echo "--set covisibility_test=depth --set geometric_sampling=coarselinear $cur" ;;
    reflin) echo "--set covisibility_test=consistent --set geometric_sampling=nearest --set linearisation=reference" ;;
  esac
}
slam_variant() {
  local fixed="--set fusion.tol_sigmas=0 --set fusion.occlusion=false --set fusion.both_directions=false"
  local thesis="--set fusion.tol_sigmas=3 --set fusion.occlusion=true --set fusion.both_directions=true"
  local cur="--set odometry.linearisation=current"
  case $1 in
    default) echo "--set odometry.covisibility_test=depth $fixed $cur" ;;
    fusion) echo "--set odometry.covisibility_test=depth $thesis $cur" ;;
    covis) echo "--set odometry.covisibility_test=consistent $fixed $cur" ;;
    both) echo "--set odometry.covisibility_test=consistent $thesis $cur" ;;
    nocap) echo "--set odometry.covisibility_test=consistent $thesis --set fusion.max_weight=1e9 $cur" ;;
    reflin) echo "--set odometry.covisibility_test=consistent $fixed --set odometry.linearisation=reference" ;;
  esac
}
for seq in tum_fr1_rpy_0_199 redkitchen_0_299; do
  cam=""
  [ "$seq" = tum_fr1_rpy_0_199 ] && cam="--camera tum_fr1"
  peers=cv_rgbd # OpenCV once per sequence, in the base run
  for v in base covis coarse reflin; do
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
  for v in default fusion covis both nocap reflin; do
    # shellcheck disable=SC2046,SC2086
    /usr/bin/time -f "%e s wall" "$B" slam "$D/$seq" $cam --backend cpu \
      --out "$O/slam-$seq-$v" $(slam_variant $v) > "$O/slam-$seq-$v.log" 2>&1
    "$B" eval "$D/$seq/groundtruth.txt" "$O/slam-$seq-$v/trajectory.txt" --json \
      > "$O/slam-$seq-$v.eval.json" 2>&1
  done
done
uptime > "$O/load_end.txt"
