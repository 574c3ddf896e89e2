#!/usr/bin/env bash
# Fills .whl/ (git-ignored through .git/info/exclude) with what benchmarks/gpu_check.sh needs on the device
# machine and its image lacks: Ray (slimmed to fit one call's 64 MiB: its Java jars, RLlib, Serve, Data, Tune,
# Train, LLM and the dashboard's web client removed; the core, raylet and GCS kept; tar.xz), jsonschema and its
# needs (Ray's), gymnasium. For Python 3.12 on x86-64 Linux, the device image's interpreter.
set -eu
cd "$(dirname "$0")/.."
grep -qx "/.whl/" .git/info/exclude 2>/dev/null || echo "/.whl/" >> .git/info/exclude
mkdir -p .whl
RAY=$(python3 -c "import ray; print(ray.__version__)")
dl() { python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$@"; }
dl .whl jsonschema jsonschema-specifications referencing rpds-py gymnasium farama-notifications
TMP=$(mktemp -d); dl "$TMP" "ray==$RAY"
(cd "$TMP" && unzip -q ray-*.whl && rm ray-*.whl && rm -rf ray/jars ray/rllib ray/data ray/serve ray/llm ray/train \
    ray/tune ray/dashboard/client/build)
# the archive is written beside the unpacked tree, not in it (tar refuses a folder that changes as it reads)
tar -cJf .whl/ray_slim.tar.xz -C "$TMP" . && rm -rf "$TMP"
du -sh .whl
