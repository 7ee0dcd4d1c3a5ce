#!/usr/bin/env bash
# The monocular EKF with each patch mode on generated catadioptric walks (thesis 2.5.2-2.5.3 and
# the modes beside it): `rgbid mono --synthetic omni --walker-height 1.75 --patch MODE --json`
# per walk and mode, each report into a scratch folder (a report already there is reused, so an
# interrupted sweep resumes), then collected into docs/results/mono_patch_modes.json (rendered
# by scripts/results.py).
#
# Usage: scripts/mono_patch_modes.sh [RGBID_BINARY] [SCRATCH_DIR] [MODE...]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:-./target/release/rgbid}
runs=${2:-/tmp/rgbid-mono-patch-modes}
shift $(($# < 2 ? $# : 2))
modes=("$@")
[ ${#modes[@]} -gt 0 ] || modes=(plain warped thesis anisotropic projective)
mkdir -p "$runs"
# The 60 s head-worn walks of scripts/mono_walks.sh, seed 7, 400x400 at 30 Hz.
walks=(corridor:walk-head:1800 office:walk-head:1800)
for mode in "${modes[@]}"; do
  for w in "${walks[@]}"; do
    IFS=: read -r scene traj frames <<<"$w"
    name="${mode}_${scene}_${traj}_${frames}"
    [ -f "$runs/$name.json" ] && continue
    "$bin" --log warn mono --synthetic omni --scene "$scene" --trajectory "$traj" --frames "$frames" \
      --walker-height 1.75 --patch "$mode" --out "$runs/$name.txt" --json "$runs/$name.json" \
      || echo "$name: exit $?"
  done
done
python3 - "$runs" docs/results/mono_patch_modes.json "${walks[*]}" "${modes[@]}" <<'PY'
import json, pathlib, sys
runs, out, walks, modes = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), sys.argv[3].split(), sys.argv[4:]
rows, metas = [], []
for mode in modes:
    for w in walks:
        scene, traj, frames = w.split(":")
        p = runs / f"{mode}_{scene}_{traj}_{frames}.json"
        if not p.is_file():
            rows.append({"mode": mode, "sequence": f"{scene} / {traj}", "missing": True})
            continue
        doc = json.loads(p.read_text())
        metas.append(doc["meta"])
        row = {"mode": mode}
        row.update({k: v for k, v in doc.items() if k not in ("meta", "benchmark")})
        rows.append(row)
meta = dict(metas[-1] if metas else {})
meta["command"] = ("scripts/mono_patch_modes.sh (rgbid mono --synthetic omni --walker-height 1.75 "
                   "--patch MODE --json per walk and mode)")
meta["commits"] = sorted({m.get("commit", "?") for m in metas})
out.write_text(json.dumps({"meta": meta, "benchmark": "mono-patch-modes", "rows": rows}, indent=1) + "\n")
print(f"wrote {out}")
PY
