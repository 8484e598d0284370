"""Writing several output files so that either all of them land or none does.

A [`Staging`] folder is created beside the outputs (same file system, so renames are atomic);
files are written into it under their final relative names, and `commit` renames each into
place. Leaving the `with` block through an exception removes the staging folder and leaves every
earlier file untouched.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType


class Staging:
    """A temporary folder inside `root` whose contents replace `root`'s on `commit`."""

    def __init__(self, root: Path) -> None:
        self.root = root.resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.dir = Path(tempfile.mkdtemp(prefix=".aggtool_usd.", dir=self.root))
        self._outputs: list[str] = []

    def path(self, relative: str) -> Path:
        """Where to write the output that will live at `root / relative` (its folder exists)."""
        p = self.dir / relative
        p.parent.mkdir(parents=True, exist_ok=True)
        if relative not in self._outputs:
            self._outputs.append(relative)
        return p

    def commit(self) -> list[Path]:
        """Moves every staged output into place (a folder replaces the folder of its name) and
        returns the final paths."""
        done = []
        for rel in self._outputs:
            src, dst = self.dir / rel, self.root / rel
            if not src.exists():
                continue
            dst.parent.mkdir(parents=True, exist_ok=True)
            if src.is_dir() and dst.is_dir():
                shutil.rmtree(dst)
            os.replace(src, dst)
            done.append(dst)
        shutil.rmtree(self.dir, ignore_errors=True)
        return done

    def __enter__(self) -> "Staging":
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 tb: TracebackType | None) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
