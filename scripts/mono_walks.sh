#!/usr/bin/env bash
# Metric monocular SLAM on generated catadioptric walks (thesis ch. 2-3): `rgbid mono
# --synthetic omni --walker-height --loops` per walk (the EKF, the scale estimation beside it,
# loops from the images and optimSim3 with the section scales), each report into a scratch
# folder, then collected into docs/results/mono_walks.json (rendered by scripts/results.py).
#
# Usage: scripts/mono_walks.sh [RGBID_BINARY] [SCRATCH_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:-./target/release/rgbid}
runs=${2:-/tmp/rgbid-mono-walks}
mkdir -p "$runs"
# scene:trajectory:frames at 30 Hz (the default pace schedule walks, stops and walks on).
# The office's walking loop is about 8 m, the corridor's about 30 m: every 60 s walk laps its
# loop. The 25 s corridor walk stays within its first lap, so no place is seen twice in the
# same direction and the loops can only be false ones. The hall and the stairwell are walked
# along an open route (about 64 m in 60 s) that never comes back, so they have no true loop;
# the stairwell's `stairs` walk climbs its 12 risers of 0.17 m, one step per tread.
walks=(corridor:walk-head:1800 corridor:walk-chest:1800 office:walk-head:1800 office:walk-chest:1800
  corridor:walk-head:3600 corridor:walk-head:750 hall:walk-head:1800 stairwell:stairs:1800)
for w in "${walks[@]}"; do
  IFS=: read -r scene traj frames <<<"$w"
  name="${scene}_${traj}_${frames}"
  "$bin" --log warn mono --synthetic omni --scene "$scene" --trajectory "$traj" --frames "$frames" \
    --walker-height 1.75 --loops --out "$runs/$name.txt" --json "$runs/$name.json" \
    || echo "$name: exit $?"
done
python3 - "$runs" docs/results/mono_walks.json "${walks[@]}" <<'PY'
import json, pathlib, sys
runs, out, walks = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), sys.argv[3:]
rows, meta = [], None
for w in walks:
    scene, traj, frames = w.split(":")
    p = runs / f"{scene}_{traj}_{frames}.json"
    if not p.is_file():
        rows.append({"sequence": f"{scene} / {traj}", "missing": True})
        continue
    doc = json.loads(p.read_text())
    meta = meta or doc["meta"]
    rows.append({k: v for k, v in doc.items() if k not in ("meta", "benchmark")})
meta = dict(meta or {})
meta["command"] = "scripts/mono_walks.sh (rgbid mono --synthetic omni --walker-height 1.75 --loops --json per walk)"
out.write_text(json.dumps({"meta": meta, "benchmark": "mono-walks", "rows": rows}, indent=1) + "\n")
print(f"wrote {out}")
PY
