#!/usr/bin/env bash
# Changed-scene relocalisation (issue 7): a map of session 0 of a generated scene, then
# sessions 1..5 (objects moved, removed, added; other sensor noise) start lost in that map.
# A case succeeds when the session relocalises within its first 10 frames.
# Usage: [SCENES="home:2 ..."] scripts/relocalisation_experiment.sh [RGBID_BINARY] [OUT_DIR]
set -euo pipefail
BIN=${1:-target/release/rgbid}
OUT=${2:-reloc-exp}
mkdir -p "$OUT"
common="--width 192 --backend cpu --no-model"
for spec in ${SCENES:-office:5 kitchen:3}; do
  scene=${spec%%:*}; seed=${spec##*:}
  # One lap = 300 frames; the map covers the first 120 frames (laps = 120/300).
  "$BIN" --log warn slam --synth "$scene:loop" --frames 120 --laps 0.4 --seed "$seed" $common \
    --out "$OUT/$scene-map" --map-out "$OUT/$scene.rgbmap" > "$OUT/$scene-map.log"
  for s in 1 2 3 4 5; do
    for masks in on off; do
      flag=""; [ "$masks" = off ] && flag="--no-masks"
      dir="$OUT/$scene-s$s-$masks"
      "$BIN" --log warn slam --synth "$scene:loop" --frames 40 --laps 0.13333333 --seed "$seed" \
        --session "$s" $common $flag --map-in "$OUT/$scene.rgbmap" --out "$dir" > "$dir.log" 2>&1 || true
      first=$(awk -F, 'NR>1 && $3=="Relocalised" {print $1; exit}' "$dir/timing.csv" 2>/dev/null || true)
      ok=no; [ -n "$first" ] && [ "$first" -lt 10 ] && ok=yes
      echo "$scene session $s masks $masks: first relocalised frame ${first:-none} -> $ok"
    done
  done
done | tee "$OUT/results.txt"
for m in on off; do
  echo "masks $m: $(grep -c "masks $m: .* yes" "$OUT/results.txt") of $(grep -c "masks $m:" "$OUT/results.txt") relocalised within 10 frames"
done | tee -a "$OUT/results.txt"
