"""Shared fixtures of the Python checks.

`aggtool_module` builds the Python module (integrations/python) once per test session with
maturin into a temporary folder and imports it from there, for every test that needs it (the
module's own tests, the Mitsuba host, the Blender extension): the build is the slow part."""
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from aggtool_cli import ROOT, find_aggtool

PKG = ROOT / "integrations" / "python"


@pytest.fixture(scope="session")
def aggtool_module():
    if shutil.which("maturin") is None:
        pytest.skip("maturin is not installed (pip install maturin)")
    out = Path(tempfile.mkdtemp(prefix="aggtool-wheel-"))
    profile = "release" if "release" in str(find_aggtool()) else "dev"
    r = subprocess.run(["maturin", "build", "--profile", profile, "-o", str(out / "dist")],
                       cwd=PKG, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-4000:]
    wheel = next((out / "dist").glob("aggtool-*.whl"))
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                        "--target", str(out / "site"), str(wheel)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    sys.path.insert(0, str(out / "site"))
    import aggtool
    assert Path(aggtool.__file__).is_relative_to(out / "site")
    yield aggtool
    sys.path.remove(str(out / "site"))
    shutil.rmtree(out, ignore_errors=True)


