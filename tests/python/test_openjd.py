"""Farm bakes through Open Job Description (integrations/openjd): `openjd check` accepts both
templates, and `openjd run` of each, locally, writes the bytes of the one-machine commands:
the assembly template's aggregates (and stamps) equal `aggtool assemble`'s on a copy of the
manifest, and the sharded template's aggregate equals `aggtool convert`'s.

Skips with a message when openjd-cli (PyPI) is not installed."""
import filecmp
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from aggtool_cli import ROOT, find_aggtool, run  # noqa: E402

OPENJD = shutil.which("openjd")
if OPENJD is None:
    pytest.skip("openjd-cli is not installed (pip install openjd-cli)", allow_module_level=True)

TEMPLATES = ROOT / "integrations" / "openjd"
# Tiny bake settings (the CI budget), the same for the farm run and the local one.
TINY = {"MaxRes": 16, "MinRes": 4, "Samples": 8, "AivRes": 8, "AivRays": 4, "AbvRes": 8, "AbvFullRes": 8}


def flags(settings):
    """The job parameters as `aggtool` flags (MaxRes -> --max-res)."""
    out = []
    for k, v in settings.items():
        name = "".join("-" + c.lower() if c.isupper() else c for c in k).lstrip("-")
        out += [f"--{name}", str(v)]
    return out


def openjd(*args):
    r = subprocess.run([OPENJD, *map(str, args)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"openjd {args[0]} failed:\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}"
    return r.stdout


def job_params(params):
    return [a for k, v in params.items() for a in ("-p", f"{k}={v}")]


@pytest.mark.parametrize("name", ["assembly.yaml", "sharded.yaml"])
def test_templates_pass_openjd_check(name):
    out = openjd("check", TEMPLATES / name)
    assert "passes validation" in out, out


def test_assembly_template_run_equals_local_assemble(tmp_path):
    # A manifest of three small generated assets: a ground and two tree species.
    run("gen", "forest", "-o", tmp_path / "farm", "--species", "2", "--instances", "5", "--triangles", "600", cwd=tmp_path)
    shutil.copytree(tmp_path / "farm", tmp_path / "local")
    manifest = tmp_path / "farm" / "forest.json"
    ids = run("assemble", manifest, "--list", cwd=tmp_path).split()
    assert len(ids) == 3, ids

    local = run("assemble", tmp_path / "local" / "forest.json", *flags(TINY), cwd=tmp_path)
    assert "3 baked, 0 reused" in local, local

    params = {"Manifest": manifest, "AssetCount": len(ids), "Aggtool": find_aggtool(), **TINY}
    out = openjd("run", TEMPLATES / "assembly.yaml", *job_params(params), "--run-dependencies")
    # Each Bake task baked its asset; the Assemble step (after them) baked nothing.
    assert out.count("baked: asset") == 3, out
    assert "3 assets: 0 baked, 3 reused" in out, out

    local_files = sorted(p.name for p in (tmp_path / "local").iterdir())
    farm_files = sorted(p.name for p in (tmp_path / "farm").iterdir())
    assert local_files == farm_files
    aggs = [n for n in local_files if n.endswith(".agg")]
    assert len(aggs) == 3, local_files
    for n in local_files:
        assert filecmp.cmp(tmp_path / "local" / n, tmp_path / "farm" / n, shallow=False), f"{n} differs"


def test_sharded_template_run_equals_one_machine_convert(tmp_path):
    run("gen", "foliage", "--triangles", "2000", "-o", tmp_path, cwd=tmp_path)
    asset = tmp_path / "foliage.glb"
    # 32³ finest level: several chunks, spread over the shards.
    settings = {**TINY, "MaxRes": 32, "Samples": 4}
    run("convert", asset, "-o", tmp_path / "one.agg", *flags(settings), cwd=tmp_path)
    out_agg = tmp_path / "out" / "foliage.agg"
    params = {"Asset": asset, "Output": out_agg, "Shards": 3, "LastShard": 2, "Aggtool": find_aggtool(), **settings}
    out = openjd("run", TEMPLATES / "sharded.yaml", *job_params(params), "--run-dependencies")
    assert out.count(".aggpart (") == 3, out
    assert (tmp_path / "one.agg").read_bytes() == out_agg.read_bytes()
    # The parts are gone once merged.
    assert sorted(p.name for p in out_agg.parent.iterdir()) == ["foliage.agg"]
