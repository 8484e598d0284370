"""Finding and running the aggtool binary from the Python checks."""
import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def find_aggtool():
    """$AGGTOOL, else the newer of target/release and target/debug builds (skips without one)."""
    if "AGGTOOL" in os.environ:
        return Path(os.environ["AGGTOOL"])
    builds = [p for p in (ROOT / "target" / "release" / "aggtool", ROOT / "target" / "debug" / "aggtool") if p.exists()]
    if not builds:
        pytest.skip("no aggtool build: run `cargo build` first", allow_module_level=True)
    return max(builds, key=lambda p: p.stat().st_mtime)


def run(*args, cwd):
    """Runs aggtool; fails the test with its stderr when it fails."""
    r = subprocess.run([str(find_aggtool()), *map(str, args)], cwd=cwd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r.stdout
