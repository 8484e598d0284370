"""The .agg format read from Python with only the schema's generated code
(integrations/python/agg_info.py): the same level table as `aggtool inspect`, and clear
errors on damaged files."""
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

pytest.importorskip("flatbuffers")

from aggtool_cli import ROOT, find_aggtool, run  # noqa: E402

READER = ROOT / "integrations" / "python" / "agg_info.py"


def reader(*args):
    return subprocess.run([sys.executable, str(READER), *map(str, args)], capture_output=True, text=True)


def test_python_reader_matches_inspect():
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        run("gen", "foliage", "-o", tmp, "--triangles", 800, cwd=tmp)
        run("convert", tmp / "foliage.glb", "--max-res", 8, "--min-res", 2, "--samples", 8,
            "--aiv-res", 8, "--aiv-rays", 4, "--abv-res", 8, "--abv-full-res", 4,
            "--visibility-levels", 1, cwd=tmp)
        agg = tmp / "foliage.agg"
        assert agg.exists()
        ours = json.loads(run("inspect", agg, "--json", cwd=tmp))
        r = reader(agg, "--json")
        assert r.returncode == 0, r.stderr
        theirs = json.loads(r.stdout)
        assert theirs["format"] == ours["format"]
        assert theirs["bytes"] == ours["bytes"] == agg.stat().st_size
        assert theirs["source"] == ours["source"] == "foliage.glb"
        assert theirs["abv_full_res"] == ours["settings"]["abv_full_res"] == 4
        assert theirs["shading_res"] == 4 and ours["settings"]["visibility_levels"] == 1
        assert theirs["format"] == "1.8" and theirs["lossless"] is ours["settings"]["lossless"] is False
        assert theirs["compression"] == ours["settings"]["compression"] == 19
        assert [(l["res"], l["voxels"], l["faces"], l["bytes"]) for l in theirs["levels"]] == \
               [(l["res"], l["voxels"], l["faces"], l["bytes"]) for l in ours["levels"]]
        assert [l["res"] for l in theirs["levels"]] == [8, 4, 2]
        # Damaged copies: a clear error, from both readers: exit status 1 from agg_info.py,
        # 3 (an input error) from aggtool.
        data = agg.read_bytes()
        for name, bad, words in [("cut.agg", data[:-10], "truncated"),
                                 ("long.agg", data + b"\0", "trailing"),
                                 ("text.agg", b"hello", "identifier")]:
            p = tmp / name
            p.write_bytes(bad)
            r = reader(p)
            assert r.returncode == 1 and words in r.stderr, r.stderr
            r = subprocess.run([str(find_aggtool()), "inspect", str(p)], capture_output=True, text=True)
            assert r.returncode == 3 and words in r.stderr, r.stderr
