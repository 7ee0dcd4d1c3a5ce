#!/usr/bin/env bash
# Runs the GPU tests and every GPU benchmark from a bundle made by scripts/gpu-bundle.sh and
# writes one JSON (gpu-check.json) that scripts/results.py renders into docs/results.md.
#
#   bash .gpu-check/gpu-check.sh OUTDIR
# On the device machine (see the `device` notes): unpack the loader first, e.g.
#   for f in .gpu-check/deb/*.deb; do dpkg -x $f /; done; ldconfig; bash .gpu-check/gpu-check.sh $OUT
set -uo pipefail
B="$(cd "$(dirname "$0")" && pwd)"
OUT="${1:?usage: gpu-check.sh OUTDIR}"
mkdir -p "$OUT"
export RGBID_REQUIRE_GPU=1
if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
fi
start=$(date +%s)
# The binaries travel gzipped; unpack them beside the outputs.
BIN="$OUT/.bin"
mkdir -p "$BIN"
for f in "$B"/bin/*.gz; do
    gzip -dc "$f" >"$BIN/$(basename "$f" .gz)"
done
chmod +x "$BIN"/*
"$BIN/rgbid" adapters >"$OUT/adapters.txt" 2>&1

# GPU tests: every test executable, `gpu_*` ignored tests only.
: >"$OUT/tests.tsv"
for t in "$BIN"/test-*; do
    name=$(basename "$t")
    log="$OUT/$name.log"
    t0=$(date +%s.%N)
    "$t" --ignored gpu_ --test-threads 1 >"$log" 2>&1
    rc=$?
    t1=$(date +%s.%N)
    # From libtest's summary lines (test lines can be interleaved with driver messages).
    passed=$(grep -o '[0-9]\+ passed' "$log" | awk '{s += $1} END {print s + 0}')
    failed=$(grep -o '[0-9]\+ failed' "$log" | awk '{s += $1} END {print s + 0}')
    printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$rc" "$passed" "$failed" \
        "$(awk "BEGIN{printf \"%.1f\", $t1 - $t0}")" >>"$OUT/tests.tsv"
    echo "$name: exit $rc, $passed passed, $failed failed"
done

# Benchmarks: odometry per stage, keyframe fusion and ray casting, per backend and size.
"$BIN/rgbid" --log warn bench kernels --backends cpu,gpu --sizes 640x480,320x240 \
    --repeat 15 --json "$OUT/kernels.json" | tee "$OUT/kernels.txt"
# TSDF integration and ray casting per backend on the generated room (no peer here).
"$BIN/rgbid" --log warn bench tsdf --backends cpu,gpu --python "" \
    --json "$OUT/tsdf.json" | tee "$OUT/tsdf.txt"
end=$(date +%s)

# One report: the kernels report (meta: date, commit, machine, adapters) with the tests.
python3 - "$OUT" "$((end - start))" <<'PY'
import json, sys
out, seconds = sys.argv[1], int(sys.argv[2])
try:
    doc = json.load(open(f"{out}/kernels.json"))
except (OSError, ValueError) as e:
    doc = {"meta": {}, "error": f"bench kernels wrote no report: {e}"}
doc["benchmark"] = "gpu-check"
doc["check_seconds"] = seconds
doc["adapters"] = open(f"{out}/adapters.txt").read()
try:
    doc["tsdf"] = json.load(open(f"{out}/tsdf.json"))
except (OSError, ValueError) as e:
    doc["tsdf"] = {"error": f"bench tsdf wrote no report: {e}"}
doc["tests"] = [
    dict(zip(["executable", "exit", "passed", "failed", "seconds"], line.rstrip("\n").split("\t")))
    for line in open(f"{out}/tests.tsv") if line.strip()
]
json.dump(doc, open(f"{out}/gpu-check.json", "w"), indent=1)
print(f"wrote {out}/gpu-check.json ({seconds} s)")
PY
rm -rf "$BIN"
