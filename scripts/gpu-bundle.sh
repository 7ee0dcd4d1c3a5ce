#!/usr/bin/env bash
# Builds the bundle that scripts/gpu-check.sh runs on a machine with a real GPU: stripped,
# gzipped release binaries (the CLI and the test executables that hold GPU tests) and the
# Vulkan loader package, in .gpu-check/ (ignored by git), well under the 64 MiB a device run
# may carry with the working tree.
#
#   bash scripts/gpu-bundle.sh            # build the bundle
#   bash .gpu-check/gpu-check.sh OUTDIR   # run it (here on lavapipe, or on the device)
set -euo pipefail
cd "$(dirname "$0")/.."
B=.gpu-check
rm -rf "$B"
mkdir -p "$B/bin" "$B/deb"

cargo build --release --bin rgbid
# Test executables with GPU tests: the library's unit tests (kernel parity) and every
# integration test file with a test ignored as needing a GPU adapter.
args=(--lib)
for f in $(grep -l '^#\[ignore = "needs a GPU adapter"\]' tests/*.rs); do
    args+=(--test "$(basename "$f" .rs)")
done
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
# Compressed, so that the bundle and the working tree fit in one device run's 64 MiB.
gzip -9 "$B"/bin/*

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
