#!/usr/bin/env bash
# The test command (README, `.ci/run`): installs what the tests need on a fresh machine
# (Python packages into the current interpreter), then runs every test: the Rust suite, the
# host example on the runtime's traversal layer, and the Python tests (Mitsuba cross-check,
# readers). Tests that need ../shared/assets skip with a message when it is absent.
set -euo pipefail
cd "$(dirname "$0")"

echo "== python packages (tests/python/requirements.txt)"
python3 -m pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt

echo "== cargo test"
cargo test

echo "== C ABI: the committed header matches cbindgen's (integrations/c)"
cargo test -p aggtool-capi

echo "== examples/host.rs (a host renderer shading hits with its own code)"
cargo run --quiet --example host -- -o "${TMPDIR:-/tmp}/aggtool-host-ci.ppm"

echo "== pytest"
python3 -m pytest tests/python -q
