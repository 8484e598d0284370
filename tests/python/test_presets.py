"""One settings source (issue 40): `aggtool convert`, the Python module and the Blender
extension take their presets and settings from the library (`bake::Preset`, `BakeSettings`
and its one by-name mapping). Here the CLI and the Python module: the same preset table, the
same settings for a preset and overrides, the same bytes for every preset, and the same
refusals. The Blender operator's part is test_blender.py's
`test_presets_same_bytes_as_cli_and_python` (it needs bpy, and skips without it)."""
import json
import math
from pathlib import Path

import pytest

from aggtool_cli import run

#: Overrides of every preset here: the smallest finest level, so that the four presets bake
#: in about a second each; every other setting is the preset's.
OVERRIDES = dict(max_res=8)


def flags(overrides):
    return [str(a) for k, v in overrides.items() for a in ("--" + k.replace("_", "-"), v)]


def same_settings(a, b):
    """Equal settings; the fractions (f32 in the file) to f32 precision (`inspect --json` prints
    the f32 0.95 as 0.949999988...)."""
    return a.keys() == b.keys() and all(
        a[k] == pytest.approx(b[k], rel=1e-6) if isinstance(b[k], float) else a[k] == b[k] for k in a)


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    return json.loads(run("presets", "--json", cwd=tmp_path_factory.mktemp("presets")))


def test_the_module_has_the_cli_table(aggtool_module, table):
    aggtool = aggtool_module
    assert aggtool.preset_table() == table
    names = [p["name"] for p in table["presets"]]
    assert names[:4] == ["draft", "default", "high", "max"] and table["default"] == "default"
    presets = aggtool.presets()
    assert list(presets) == names
    assert presets == {p["name"]: p["settings"] for p in table["presets"]}
    # Every setting of every preset, named as convert's keywords take them.
    assert all(sorted(s) == table["fields"] for s in presets.values())
    assert aggtool.bake_settings() == presets[table["default"]]
    assert aggtool.bake_settings("draft", max_res=16, keep="1%", lossless=True) == \
        dict(presets["draft"], max_res=16, keep=0.01, lossless=True)
    # The human table lists every preset and setting.
    text = run("presets", cwd=Path.cwd())
    assert all(n in text for n in names) and all(f in text for f in table["fields"])


def test_every_preset_bakes_the_same_bytes_from_cli_and_python(aggtool_module, table, tmp_path):
    aggtool = aggtool_module
    run("gen", "plane45", "-o", tmp_path, "--triangles", 200, cwd=tmp_path)
    glb = tmp_path / "plane45.glb"
    seen = set()
    for p in table["presets"]:
        name = p["name"]
        cli, py = tmp_path / f"{name}-cli.agg", tmp_path / f"{name}-py.agg"
        run("convert", glb, "-o", cli, "--preset", name, *flags(OVERRIDES), cwd=tmp_path)
        assert aggtool.convert(str(glb), str(py), preset=name, **OVERRIDES) == py
        assert cli.read_bytes() == py.read_bytes(), name
        recorded = json.loads(run("inspect", cli, "--json", cwd=tmp_path))["settings"]
        assert same_settings({k: recorded[k] for k in table["fields"]}, dict(p["settings"], **OVERRIDES)), name
        seen.add(cli.read_bytes())
    # The presets reached the files: no two presets gave the same bytes.
    assert len(seen) == len(table["presets"])


def test_convert_refuses_bad_settings(aggtool_module, tmp_path):
    aggtool = aggtool_module
    run("gen", "plane45", "-o", tmp_path, "--triangles", 200, cwd=tmp_path)
    src, out = str(tmp_path / "plane45.glb"), tmp_path / "never.agg"
    # Unknown names and values of the wrong kind: TypeError naming the valid names or kind.
    with pytest.raises(TypeError, match=r"unknown bake setting 'lobes'.*ndf_lobes"):
        aggtool.convert(src, str(out), lobes=2)
    for name, value, kind in (("max_res", 16.0, "an integer"), ("denoise", 1, "true or false"),
                              ("keep", True, "a number"), ("samples", "many", "an integer"),
                              ("samples", [4], "got list")):
        with pytest.raises(TypeError, match=kind):
            aggtool.convert(src, str(out), **{name: value})
    # Unknown presets and values out of range: ValueError saying what is valid.
    with pytest.raises(ValueError, match="unknown bake preset 'fast'; the presets are: draft, default"):
        aggtool.convert(src, str(out), preset="fast")
    for name, value, words in (("max_res", 48, "power of two"), ("ndf_lobes", 9, "1 to 4"),
                               ("samples", -1, "samples=-1"), ("keep", math.nan, "finite"),
                               ("max_res", 2 ** 70, "out of range"), ("compression", 23, "22")):
        with pytest.raises(ValueError, match=words):
            aggtool.convert(src, str(out), **{name: value})
        with pytest.raises(ValueError, match=words):
            aggtool.bake_settings(**{name: value})
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plane45.glb"]


#: Settings whose `convert` flag is not `--NAME` (the rest are, dashes for underscores).
FLAG_OF = {"compression": "--compression-level", "denoise": "--no-denoise"}


def test_every_setting_has_a_cli_flag_that_means_the_python_keyword(aggtool_module, table, tmp_path):
    """The command line's flags are typed (clap) and mapped onto the library's settings by
    hand; this keeps them the same settings as the by-name mapping Python and Blender use: a
    flag for every setting, and the special ones (switches, renamed flags) baking the same
    bytes as the Python keywords."""
    aggtool = aggtool_module
    help_text = run("convert", "--help", cwd=tmp_path)
    for name in table["fields"]:
        flag = FLAG_OF.get(name, "--" + name.replace("_", "-"))
        assert f" {flag}" in help_text, f"{name}: no {flag} in convert --help"
    run("gen", "plane45", "-o", tmp_path, "--triangles", 200, cwd=tmp_path)
    glb = tmp_path / "plane45.glb"
    cli, py = tmp_path / "cli.agg", tmp_path / "py.agg"
    run("convert", glb, "-o", cli, "--preset", "draft", "--max-res", 8, "--keep", 0.2,
        "--no-denoise", "--lossless", "--keep-all-effects", "--abv-windows", "true",
        "--compression-level", 5, "--aiv-min-rays", 2, cwd=tmp_path)
    overrides = dict(max_res=8, keep=0.2, denoise=False, lossless=True, keep_all_effects=True,
                     abv_windows=True, compression=5, aiv_min_rays=2)
    aggtool.convert(str(glb), str(py), preset="draft", **overrides)
    assert cli.read_bytes() == py.read_bytes()
    recorded = json.loads(run("inspect", cli, "--json", cwd=tmp_path))["settings"]
    assert same_settings({k: recorded[k] for k in table["fields"]},
                         aggtool.bake_settings("draft", **overrides))
