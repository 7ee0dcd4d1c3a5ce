#!/usr/bin/env bash
# Monocular loop detection from images (thesis 3.3.2) on generated catadioptric walks that lap
# their loop: `rgbid mono --synthetic omni --loops` per walk (precision and recall against the
# ground truth, a sweep of the bag-of-words score, inlier and inlier-ratio thresholds), each
# report into a scratch folder, then collected into docs/results/mono_loops.json (rendered by
# scripts/results.py).
#
# Usage: scripts/mono_loops.sh [RGBID_BINARY] [SCRATCH_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:-./target/release/rgbid}
runs=${2:-/tmp/rgbid-mono-loops}
mkdir -p "$runs"
# scene:trajectory:frames at 30 Hz (the default pace schedule walks, stops and walks on).
walks=(office:walk-head:1800 corridor:walk-head:1800 corridor:walk-chest:1800)
for w in "${walks[@]}"; do
  IFS=: read -r scene traj frames <<<"$w"
  name="${scene}_${traj}_${frames}"
  "$bin" --log warn mono --synthetic omni --scene "$scene" --trajectory "$traj" --frames "$frames" \
    --loops --loops-json "$runs/$name.json" | tail -n 60 || echo "$name: exit $?"
done
python3 - "$runs" docs/results/mono_loops.json "${walks[@]}" <<'PY'
import json, pathlib, sys
runs, out, walks = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), sys.argv[3:]
rows, meta = [], None
for w in walks:
    scene, traj, frames = w.split(":")
    p = runs / f"{scene}_{traj}_{frames}.json"
    if not p.is_file():
        rows.append({"sequence": f"{scene} / {traj} ({frames} frames)", "missing": True})
        continue
    doc = json.loads(p.read_text())
    meta = meta or doc["meta"]
    row = {k: v for k, v in doc.items() if k not in ("meta", "benchmark")}
    # The per-keyframe candidate lists stay in the scratch reports.
    row["evaluation"].pop("queries", None)
    rows.append(row)
meta = dict(meta or {})
meta["command"] = "scripts/mono_loops.sh (rgbid mono --synthetic omni --loops --loops-json per walk)"
out.write_text(json.dumps({"meta": meta, "benchmark": "mono-loops", "rows": rows}, indent=1) + "\n")
print(f"wrote {out}")
PY
