#!/usr/bin/env bash
# Builds the bundle that scripts/gpu-check.sh runs on a machine with a real GPU: stripped
# release binaries (the CLI and the test executables that hold GPU tests) and the Vulkan
# loader package, in .gpu-check/ (ignored by git), under the 64 MiB a device run may carry.
#
#   bash scripts/gpu-bundle.sh            # build the bundle
#   bash .gpu-check/gpu-check.sh OUTDIR   # run it (here on lavapipe, or on the device)
set -euo pipefail
cd "$(dirname "$0")/.."
B=.gpu-check
rm -rf "$B"
mkdir -p "$B/bin" "$B/deb"

cargo build --release --bin rgbid
# Test executables with GPU tests: the library's unit tests (kernel parity) and the
# integration tests named in GPU_TESTS.
GPU_TESTS=(slam_fusion synth_gpu segment_gpu)
args=(--lib)
for t in "${GPU_TESTS[@]}"; do args+=(--test "$t"); done
cargo test --release --no-run --message-format=json "${args[@]}" >"$B/build.json"
python3 - "$B" <<'PY'
import json, shutil, sys
out = sys.argv[1]
for line in open(f"{out}/build.json"):
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("profile", {}).get("test") and m.get("executable"):
        name = m["target"]["name"] if m["target"]["kind"] != ["lib"] else "lib"
        shutil.copy(m["executable"], f"{out}/bin/test-{name}")
PY
rm "$B/build.json"
cp target/release/rgbid "$B/bin/rgbid"
strip --strip-debug "$B"/bin/*

# The Vulkan loader (the device's NVIDIA driver brings the ICD, not always the loader).
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
mkdir -p /tmp/amd64/partial
# shellcheck disable=SC2086
apt-get $o update -qq >/dev/null
(cd "$B/deb" && apt-get $o download libvulkan1 >/dev/null)

cp scripts/gpu-check.sh "$B/"
git rev-parse HEAD >"$B/commit" 2>/dev/null || echo unknown >"$B/commit"
du -sh "$B"
du -b --max-depth=1 "$B" | sort -n
