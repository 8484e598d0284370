"""Running the aggtool binary: `export` (geometry for USD, since usd-core reads neither glTF nor
OBJ) and `inspect --json` (what an .agg file holds)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

from .errors import UsdToolError

#: The repository root when the package runs from its checkout (integrations/usd/aggtool_usd).
REPO = Path(__file__).resolve().parents[3]


def find_aggtool() -> Path:
    """`$AGGTOOL`, else the newer of the repository's target/release and target/debug builds,
    else `aggtool` on PATH."""
    if os.environ.get("AGGTOOL"):
        return Path(os.environ["AGGTOOL"])
    builds = [p for p in (REPO / "target" / "release" / "aggtool", REPO / "target" / "debug" / "aggtool")
              if p.is_file()]
    if builds:
        return max(builds, key=lambda p: p.stat().st_mtime)
    found = shutil.which("aggtool")
    if found:
        return Path(found)
    raise UsdToolError("cannot find the aggtool binary: set AGGTOOL, run `cargo build --release`, or put it on PATH")


def run_aggtool(*args: str | Path) -> str:
    """Runs aggtool and returns its stdout; its last stderr line becomes the error on failure."""
    exe = find_aggtool()
    r = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        lines = [l for l in r.stderr.strip().splitlines() if l.strip()]
        raise UsdToolError(f"aggtool {args[0]} failed: {lines[-1] if lines else f'exit status {r.returncode}'}")
    return r.stdout


def export_geometry(asset: Path, folder: Path) -> dict[str, Any]:
    """`aggtool export ASSET -o FOLDER`; returns the parsed scene.json (see src/scene/export.rs)."""
    run_aggtool("export", asset, "-o", folder)
    scene = json.loads((folder / "scene.json").read_text())
    if scene.get("version") != 1:
        raise UsdToolError(f"aggtool export wrote scene.json version {scene.get('version')}; this package reads version 1")
    return scene


def inspect_aggregate(agg: Path) -> dict[str, Any]:
    """`aggtool inspect --json FILE.agg`: format version, bounds and levels."""
    if not agg.is_file():
        raise UsdToolError(f"missing aggregate {agg}: bake it with `aggtool convert`")
    return json.loads(run_aggtool("inspect", agg, "--json"))
