#!/usr/bin/env bash
# The test command (README, `.ci/run`): installs what the tests need on a fresh machine
# (Python packages into the current interpreter), then runs every test: the Rust suite, the
# host example on the runtime's traversal layer, and the Python tests (Mitsuba cross-check,
# readers). Tests that need ../shared/assets skip with a message when it is absent.
set -euo pipefail
cd "$(dirname "$0")"

echo "== python packages (tests/python/requirements.txt)"
python3 -m pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt

# bpy pins numpy < 2 (Mitsuba and the rest use numpy 2), so it gets a venv of its own, which
# tests/python/test_blender.py runs the Blender side in; bpy 5.0.1 is the last wheel for
# CPython 3.11 (5.1 and later are 3.13 only). Without it those tests skip.
BPY_VENV="${AGGTOOL_BPY_VENV:-$HOME/.cache/aggtool/bpy-5.0.1}"
echo "== bpy 5.0.1 (Blender as a Python module) in $BPY_VENV"
if ! "$BPY_VENV/bin/python" -c "import bpy" 2>/dev/null; then
    python3 -m venv "$BPY_VENV" &&
        "$BPY_VENV/bin/python" -m pip install --quiet --disable-pip-version-check "bpy==5.0.1" ||
        echo "bpy 5.0.1 could not be installed (it needs CPython 3.11 and PyPI): test_blender.py will skip"
fi
export AGGTOOL_BPY_VENV="$BPY_VENV"

echo "== cargo test"
cargo test

echo "== tools/ (the measurement probes build; docs/src/performance.md runs them)"
cargo build -p aggtool-tools

echo "== C ABI: the committed header matches cbindgen's (integrations/c)"
cargo test -p aggtool-capi

echo "== examples/host.rs (a host renderer shading hits with its own code)"
cargo run --quiet --example host -- -o "${TMPDIR:-/tmp}/aggtool-host-ci.ppm"

echo "== pytest"
# -rs: each skip with its reason (a skip for want of ../shared/assets fails .ci/run when it is here).
python3 -m pytest tests/python -q -rs
