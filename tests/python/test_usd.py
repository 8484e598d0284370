"""The USD integration (integrations/usd, `python -m aggtool_usd`) on tiny generated assets:
asset layers compose and switch levels with UsdLod, assemblies round-trip through manifests,
and bad input fails with one line and writes nothing."""
import json
import math
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("pxr", reason="usd-core is not installed (pip install 'usd-core>=26.8,<27')")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLod, UsdShade, UsdUtils  # noqa: E402

if not hasattr(UsdLod, "ScreenSizeHeuristic"):
    pytest.skip("usd-core older than 26.8 (no UsdLod)", allow_module_level=True)

import numpy as np  # noqa: E402

from aggtool_cli import ROOT, find_aggtool, run  # noqa: E402

USD_PACKAGE = ROOT / "integrations" / "usd"
#: ../shared/assets beside the checkout (as tests/common/mod.rs finds it), or beside the checkout
#: that holds this one as a worktree.
SHARED = next((p for p in (ROOT.parent / "shared" / "assets", ROOT.parent.parent / "shared" / "assets")
               if p.is_dir()), ROOT.parent / "shared" / "assets")
#: Tiny bakes: the tests check structure and paths, not appearance.
BAKE = ["--max-res", 8, "--min-res", 2, "--samples", 4, "--aiv-rays", 4, "--aiv-res", 8, "--abv-res", 8]
#: Instance transforms survive float32 positions/scales and float quaternions to this.
TRANSFORM_TOLERANCE = 1e-5


def usd_tool(*args, cwd):
    """Runs `python -m aggtool_usd`; returns the completed process (no check)."""
    env = dict(os.environ, AGGTOOL=str(find_aggtool()),
               PYTHONPATH=os.pathsep.join([str(USD_PACKAGE), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", "aggtool_usd", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True)


def usd_ok(*args, cwd):
    r = usd_tool(*args, cwd=cwd)
    assert r.returncode == 0, r.stderr
    return r


def usd_fails(*args, cwd, words):
    """The command fails with status 1, and stderr is one error line naming `words`."""
    r = usd_tool(*args, cwd=cwd)
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("aggtool_usd: error:") and words in lines[0], r.stderr
    return r


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    """Two baked generated assets: scene/foliage.glb and scene/buildings.glb with their .agg."""
    d = tmp_path_factory.mktemp("usd")
    scene = d / "scene"
    for name in ("foliage", "buildings"):
        run("gen", name, "-o", scene, "--triangles", 800, cwd=d)
        run("convert", scene / f"{name}.glb", *BAKE, cwd=d)
        assert (scene / f"{name}.agg").exists()
    return d


@pytest.fixture(scope="module")
def foliage_layer(assets):
    usd_ok("asset", "scene/foliage.glb", "-o", "layers/foliage.usda", cwd=assets)
    return assets / "layers" / "foliage.usda"


def lod_frustum(distance, fov_y=40.0, aspect=16 / 9, centre=(0.0, 0.0, 0.0)):
    """A perspective camera `distance` away from `centre` along +z, looking at it."""
    f = Gf.Frustum()
    f.SetPerspective(fov_y, aspect, 0.01, 1e6)
    f.SetPosition(Gf.Vec3d(*centre) + Gf.Vec3d(0, 0, distance))
    return f


def test_asset_layer_composes(assets, foliage_layer):
    """The component model: kind and assetInfo; LOD root children in order full, aggregate; the
    full level's meshes with normals, st and a UsdPreviewSurface; the sidecar prim's attributes
    agree with `aggtool inspect`; the heuristic sits beside the LOD root; the variant set."""
    stage = Usd.Stage.Open(str(foliage_layer))
    root = stage.GetDefaultPrim()
    assert root.GetName() == "foliage"
    model = Usd.ModelAPI(root)
    assert model.GetKind() == "component" and model.GetAssetName() == "foliage"
    assert model.GetAssetIdentifier().path == "./foliage.usda"
    assert root.GetAttribute("aggtool:source").Get().path == "../scene/foliage.glb"

    lod = root.GetChild("lod")
    assert lod.HasAPI(UsdLod.RootAPI)
    assert [c.GetName() for c in lod.GetChildren()] == ["full", "aggregate"]
    full, side = lod.GetChildren()
    assert full.HasAuthoredPayloads() and full.IsLoaded()
    meshes = [p for p in Usd.PrimRange(full, Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)]
    assert meshes
    tris = 0
    for p in meshes:
        m = UsdGeom.Mesh(p)
        n = len(m.GetPointsAttr().Get())
        assert set(m.GetFaceVertexCountsAttr().Get()) == {3}
        tris += len(m.GetFaceVertexCountsAttr().Get())
        assert len(m.GetNormalsAttr().Get()) == n and m.GetNormalsInterpolation() == "vertex"
        st = UsdGeom.PrimvarsAPI(p).GetPrimvar("st")
        assert st and len(st.Get()) == n
        mat, _ = UsdShade.MaterialBindingAPI(p).ComputeBoundMaterial()
        shader = mat.ComputeSurfaceSource()[0]
        assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    info = json.loads(run("inspect", assets / "scene" / "foliage.agg", "--json", cwd=assets))
    imported = json.loads(run("info", assets / "scene" / "foliage.glb", "--json", cwd=assets))
    assert tris == imported["instanced_triangles"]

    sidecar = side.GetAttribute("aggtool:sidecar").Get()
    assert sidecar.path == "../scene/foliage.agg"
    assert Path(sidecar.resolvedPath) == (assets / "scene" / "foliage.agg").resolve()
    assert side.GetAttribute("aggtool:formatVersion").Get() == info["format"]
    assert list(side.GetAttribute("aggtool:levelResolutions").Get()) == [l["res"] for l in info["levels"]] == [8, 4, 2]
    lo, hi = side.GetAttribute("extent").Get()
    assert np.allclose([lo, hi], info["bounds"], rtol=1e-6)

    heuristic = UsdLod.ScreenSizeHeuristic(root.GetChild("lodHeuristic"))
    assert heuristic and heuristic.GetLodDomainAttr().Get() == "imaging"
    assert UsdLod.RootAPI(lod).GetLodHeuristicsRel().GetTargets() == [heuristic.GetPath()]
    assert not heuristic.GetPath().HasPrefix(lod.GetPath())

    variants = root.GetVariantSets().GetVariantSet("lod")
    assert sorted(variants.GetVariantNames()) == ["aggregate", "full"]
    assert variants.GetVariantSelection() == ""  # UsdLod consumers see both levels
    variants.SetVariantSelection("aggregate")
    assert not full.IsActive() and side.IsActive()
    variants.SetVariantSelection("full")
    assert lod.GetChild("full").IsActive() and not lod.GetChild("aggregate").IsActive()


def test_instanced_meshes_compose(assets):
    """The generated buildings place 13 meshes 1219 times: meshes placed more than once become
    instanceable references to one prototype each, and the composed full level has every
    placed triangle and the world bounds of `aggtool info` (the transforms are read the right
    way round)."""
    usd_ok("asset", "scene/buildings.glb", "-o", "layers/buildings.usda", cwd=assets)
    stage = Usd.Stage.Open(str(assets / "layers" / "buildings.usda"))
    full = stage.GetPrimAtPath("/buildings/lod/full")
    imported = json.loads(run("info", assets / "scene" / "buildings.glb", "--json", cwd=assets))
    placed = [p for p in Usd.PrimRange(full, Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)]
    assert len(placed) == imported["instances"]
    assert sum(p.IsInstance() for p in placed) > 0 and len(stage.GetPrototypes()) <= imported["meshes"]
    assert sum(len(UsdGeom.Mesh(p).GetFaceVertexCountsAttr().Get()) for p in placed) == imported["instanced_triangles"]
    for p in placed:
        assert UsdShade.MaterialBindingAPI(p).ComputeBoundMaterial()[0], p.GetPath()
    bound = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default"]).ComputeWorldBound(full).ComputeAlignedRange()
    assert np.allclose([bound.GetMin(), bound.GetMax()], imported["bounds"], atol=1e-4)


def test_compute_lod_switches_where_the_finest_voxel_reaches_a_pixel(assets, foliage_layer):
    """ComputeLOD picks the full mesh (0) for a near camera and the aggregate (1) for a far one;
    the switch lies between the distances where a finest-level voxel covers 2 pixels and half a
    pixel of the stated image (1920 wide, 16:9)."""
    stage = Usd.Stage.Open(str(foliage_layer))
    root = stage.GetDefaultPrim()
    heuristic = UsdLod.ScreenSizeHeuristic(root.GetChild("lodHeuristic"))
    side = root.GetChild("lod").GetChild("aggregate")
    voxel = side.GetAttribute("aggtool:finestVoxelSize").Get()
    lo, hi = (np.array(v) for v in side.GetAttribute("extent").Get())
    centre = tuple(float(x) for x in 0.5 * (lo + hi))
    width, aspect, fov_y = heuristic.GetPrim().GetAttribute("aggtool:imageWidth").Get(), 16 / 9, 40.0
    assert width == 1920
    height = width / aspect

    def distance_for(pixels_per_voxel):
        # A pixel at distance d spans 2 d tan(fov/2) / H world units.
        return voxel * height / (2 * pixels_per_voxel * math.tan(math.radians(fov_y / 2)))

    world = Gf.Matrix4d(1)
    assert heuristic.ComputeLOD(lod_frustum(distance_for(2.0), fov_y, aspect, centre), world) == 0
    assert heuristic.ComputeLOD(lod_frustum(distance_for(0.5), fov_y, aspect, centre), world) == 1
    assert heuristic.ComputeLOD(lod_frustum(0.1 * distance_for(1.0), fov_y, aspect, centre), world) == 0
    assert heuristic.ComputeLOD(lod_frustum(100 * distance_for(1.0), fov_y, aspect, centre), world) == 1


def with_texture_transform(glb, out, offset, rotation, scale):
    """A copy of a GLB whose base-colour textures carry a KHR_texture_transform."""
    data = glb.read_bytes()
    (n, _), rest = struct.unpack_from("<II", data, 12), 20
    doc = json.loads(data[rest:rest + n])
    for m in doc["materials"]:
        t = m.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if t is not None:
            t["extensions"] = {"KHR_texture_transform": {"offset": offset, "rotation": rotation, "scale": scale}}
    doc["extensionsUsed"] = sorted(set(doc.get("extensionsUsed", [])) | {"KHR_texture_transform"})
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary = data[rest + n:]
    out.write_bytes(struct.pack("<4sII", b"glTF", 2, 20 + len(text) + len(binary))
                    + struct.pack("<II", len(text), 0x4E4F534A) + text + binary)
    return out


def test_texture_transform_becomes_usdtransform2d(assets):
    """KHR_texture_transform (offset, rotation, scale in glTF's v-down space) is carried as a
    UsdTransform2d on st = (u, 1 − v) that maps every point where the glTF transform does."""
    if str(USD_PACKAGE) not in sys.path:
        sys.path.insert(0, str(USD_PACKAGE))
    import aggtool_usd.asset as usd_asset  # (registers the schema in this process: harmless here)

    offset, rotation, scale = [0.5, 0.25], 0.3, [2.0, -1.5]
    glb = with_texture_transform(assets / "scene" / "foliage.glb", assets / "scene" / "moved.glb", offset, rotation, scale)
    shutil.copy(assets / "scene" / "foliage.agg", assets / "scene" / "moved.agg")
    usd_ok("asset", glb, "-o", "layers/moved.usda", cwd=assets)
    stage = Usd.Stage.Open(str(assets / "layers" / "moved.usda"))
    xfs = [UsdShade.Shader(p) for p in stage.Traverse() if p.GetName() == "baseColorTextureTransform"]
    assert len(xfs) == 1 and xfs[0].GetIdAttr().Get() == "UsdTransform2d"
    tex = UsdShade.Shader(xfs[0].GetPrim().GetParent().GetChild("baseColorTexture"))
    assert tex.GetInput("st").GetConnectedSources()[0][0].source.GetPrim() == xfs[0].GetPrim()
    s_ = np.array(xfs[0].GetInput("scale").Get())
    a = math.radians(xfs[0].GetInput("rotation").Get())
    t_ = np.array(xfs[0].GetInput("translation").Get())
    c, sn = math.cos(rotation), math.sin(rotation)
    # src/scene/material.rs: M = T · R · S with R's columns (c, −s) and (s, c).
    m = np.array([[1, 0, offset[0]], [0, 1, offset[1]], [0, 0, 1]]) @ np.array([[c, sn, 0], [-sn, c, 0], [0, 0, 1]]) \
        @ np.diag([scale[0], scale[1], 1])
    for u, v in np.random.default_rng(1).uniform(-2, 2, (20, 2)):
        want = m @ [u, v, 1]
        got = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ (s_ * [u, 1 - v]) + t_
        assert np.allclose(got, [want[0], 1 - want[1]], atol=1e-5)
    assert usd_asset.st_transform([1, 0, 0, 1, 1, 0, 0, 0, 1]) is None  # shear: left out with a warning


def test_every_asset_path_resolves(assets, foliage_layer):
    """Every layer, payload, reference and asset-valued attribute (source, sidecar, textures)
    of the asset layer resolves to a file."""
    layers, paths, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(foliage_layer)))
    assert not unresolved, unresolved
    names = {Path(l.realPath).name for l in layers}
    assert {"foliage.usda", "foliage.full.usdc"} <= names
    assert {Path(p).name for p in paths} >= {"foliage.glb", "foliage.agg"}
    stage = Usd.Stage.Open(str(foliage_layer))
    for prim in stage.Traverse():
        for a in prim.GetAttributes():
            v = a.Get()
            if isinstance(v, Sdf.AssetPath) and v.path:
                assert v.resolvedPath and Path(v.resolvedPath).is_file(), (a.GetPath(), v)


def test_codeless_schema_types_the_sidecar(foliage_layer):
    """With the package's plugInfo.json on PXR_PLUGINPATH_NAME, any USD process knows the
    sidecar prim's type (a Boundable, as UsdVol's field assets are) and its documented
    properties; a process without it reads the same attributes on an untyped prim."""
    code = (
        "import json, sys\n"
        "from pxr import Usd, UsdGeom\n"
        "stage = Usd.Stage.Open(sys.argv[1])\n"
        "p = stage.GetPrimAtPath('/foliage/lod/aggregate')\n"
        "d = Usd.SchemaRegistry().FindConcretePrimDefinition('AggtoolAggregate')\n"
        "print(json.dumps({'type': str(p.GetTypeName()), 'boundable': p.IsA(UsdGeom.Boundable),\n"
        "    'doc': d.GetPropertyMetadata('aggtool:sidecar', 'documentation') if d else None,\n"
        "    'sidecar': p.GetAttribute('aggtool:sidecar').Get().path,\n"
        "    'extent': len(p.GetAttribute('extent').Get())}))\n"
    )
    def probe(schema):
        env = {k: v for k, v in os.environ.items() if k != "PXR_PLUGINPATH_NAME"}
        if schema:
            env["PXR_PLUGINPATH_NAME"] = str(USD_PACKAGE / "aggtool_usd" / "resources")
        r = subprocess.run([sys.executable, "-c", code, str(foliage_layer)], env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    assert probe(True) == {"type": "AggtoolAggregate", "boundable": True, "extent": 2, "sidecar": "../scene/foliage.agg",
                           "doc": "The .agg file (anchored to the layer that authors it)."}
    assert probe(False) == {"type": "AggtoolAggregate", "boundable": False, "extent": 2, "sidecar": "../scene/foliage.agg",
                            "doc": None}


def write_manifest(path, doc):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))
    return path


def trs(t, q, s):
    """Column-vector matrix T · R · S, quaternion [x, y, z, w]."""
    m = np.array(Gf.Matrix4d().SetScale(Gf.Vec3d(*s)) * Gf.Matrix4d().SetRotate(Gf.Quatd(q[3], *q[:3]))
                 * Gf.Matrix4d().SetTranslate(Gf.Vec3d(*t))).T
    return m


def manifest_matrices(doc):
    """(asset source, column-vector matrix) per instance of a manifest document."""
    out = []
    for inst in doc["instances"]:
        if "matrix" in inst:
            m = np.array(inst["matrix"], float).reshape(4, 4).T
        else:
            m = trs(inst.get("translation", [0, 0, 0]), inst.get("rotation", [0, 0, 0, 1]), inst.get("scale", [1, 1, 1]))
        out.append((doc["assets"][inst["asset"]]["source"], m))
    return out


CITY = {
    "version": 1,
    "assets": {"tree": {"source": "../scene/foliage.glb"},
               "city-block": {"source": "../scene/buildings.glb", "aggregate": "../scene/buildings.agg"}},
    "instances": [
        {"asset": "tree", "translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1]},
        {"asset": "city-block", "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 12, 0, -4, 1]},
        {"asset": "tree", "translation": [3.5, 0.25, -7], "rotation": [0, 0.3826834, 0, 0.9238795], "scale": [2, 2, 2]},
        {"asset": "tree", "translation": [-100, 2, 40], "rotation": [0.5, 0.5, 0.5, 0.5], "scale": [0.5, 1.5, -1]},
    ],
}


def test_assembly_round_trip(assets):
    """manifest → USD → manifest gives the same instances (sources and matrices within float
    tolerance); the city is a kind=assembly root with one PointInstancer whose prototypes
    reference the asset layers, and all of its asset paths resolve."""
    manifest = write_manifest(assets / "city" / "city.json", CITY)
    usd_ok("assembly", manifest, "-o", "city/city.usda", cwd=assets)
    city = assets / "city" / "city.usda"
    stage = Usd.Stage.Open(str(city))
    root = stage.GetDefaultPrim()
    assert Usd.ModelAPI(root).GetKind() == "assembly"
    pis = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert len(pis) == 1
    pi = UsdGeom.PointInstancer(pis[0])
    assert list(pi.GetIdsAttr().Get()) == [0, 1, 2, 3]
    assert list(pi.GetProtoIndicesAttr().Get()) == [0, 1, 0, 0]
    assert len(pi.GetPositionsAttr().Get()) == len(pi.GetOrientationsfAttr().Get()) == len(pi.GetScalesAttr().Get()) == 4
    for target in pi.GetPrototypesRel().GetTargets():
        proto = stage.GetPrimAtPath(target)
        refs = proto.GetPrimStack()[0].referenceList.prependedItems
        assert len(refs) == 1 and refs[0].assetPath.startswith("./city_assets/")
        assert Usd.ModelAPI(proto).GetKind() == "component"
    xfs = pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    for (src, want), got in zip(manifest_matrices(CITY), xfs):
        assert np.allclose(np.array(got).T, want, atol=TRANSFORM_TOLERANCE * max(1, np.abs(want).max()))
    _, _, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(city)))
    assert not unresolved, unresolved

    usd_ok("manifest", city, "-o", "city/back.json", cwd=assets)
    back = json.loads((assets / "city" / "back.json").read_text())
    assert back["version"] == 1
    assert {k: a["source"] for k, a in back["assets"].items()} == \
           {"tree": "../scene/foliage.glb", "city-block": "../scene/buildings.glb"}  # ids kept in assetInfo
    assert all("aggregate" not in a for a in back["assets"].values())  # both are the default .agg
    got, want = manifest_matrices(back), manifest_matrices(CITY)
    assert [s for s, _ in got] == [s for s, _ in want]
    for (_, g), (_, w) in zip(got, want):
        assert np.allclose(g, w, atol=TRANSFORM_TOLERANCE * max(1, np.abs(w).max())), (g, w)

    # The USD city renders with `aggtool render` through the manifest read back from it, as
    # the original manifest does (same view and seed: the same image up to float rounding), and the city is in the
    # picture (without its city block the image changes). Its first three instances stand
    # together, the fourth 100 units away: the view frames the three.
    near = {**CITY, "instances": CITY["instances"][:3]}
    near_back = {**back, "instances": back["instances"][:3]}
    fewer = {**back, "instances": [i for i in near_back["instances"] if i["asset"] != "city-block"]}
    for name, doc in (("near", near), ("near-back", near_back), ("fewer", fewer)):
        (assets / "city" / f"{name}.json").write_text(json.dumps(doc))
    run("reference", assets / "city" / "near.json", "--auto-view", "--width", 32, "--height", 24,
        "--spp", 1, "--save-view", "city/view.json", "-o", "city/ref.exr", cwd=assets)
    for name in ("near", "near-back", "fewer"):
        run("render", assets / "city" / f"{name}.json", "--view", "city/view.json", "--spp", 4,
            "-o", f"city/{name}.exr", cwd=assets)
    same = json.loads(run("compare", "city/near-back.exr", "city/near.exr", "--json", cwd=assets))
    assert same["rmse"] < 1e-6, same  # float rounding of the transforms only
    diff = json.loads(run("compare", "city/fewer.exr", "city/near.exr", "--json", cwd=assets))
    assert diff["rmse"] > 1e-2, diff


def test_manifest_composes_nested_transforms(assets, foliage_layer):
    """A hand-made stage: a PointInstancer under a moved Xform whose prototype holds the asset
    under its own transform, and the asset placed directly (behind a payload) under a scaled
    Xform. Every enclosing transform is composed into the manifest's instances; invisible and
    inactive instances are left out."""
    path = assets / "layers" / "nested.usda"
    stage = Usd.Stage.CreateNew(str(path))
    world = UsdGeom.Xform.Define(stage, "/World")
    world.AddTranslateOp().Set(Gf.Vec3d(10, 0, 0))
    pi = UsdGeom.PointInstancer.Define(stage, "/World/Trees")
    proto = UsdGeom.Xform.Define(stage, "/World/Trees/Prototypes/tree")
    inner = UsdGeom.Xform.Define(stage, "/World/Trees/Prototypes/tree/lifted")
    inner.AddTranslateOp().Set(Gf.Vec3d(0, 1, 0))
    inner.GetPrim().GetReferences().AddReference("./foliage.usda")
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    pi.CreateProtoIndicesAttr([0, 0, 0, 0])
    pi.CreatePositionsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(0, 0, 5), Gf.Vec3f(9, 9, 9), Gf.Vec3f(8, 8, 8)])
    pi.CreateIdsAttr([10, 11, 12, 13])
    pi.CreateInvisibleIdsAttr([12])  # not drawn, so not in the manifest
    pi.DeactivateId(13)  # inactive: likewise
    single = UsdGeom.Xform.Define(stage, "/World/Big")
    single.AddScaleOp().Set(Gf.Vec3f(3, 3, 3))
    single.GetPrim().GetPayloads().AddPayload("./foliage.usda")  # a set dressed behind a payload
    stage.GetRootLayer().Save()

    usd_ok("manifest", path, "-o", "layers/nested.json", cwd=assets)
    doc = json.loads((assets / "layers" / "nested.json").read_text())
    assert doc["assets"] == {"foliage": {"source": "../scene/foliage.glb"}}
    got = [m for _, m in manifest_matrices(doc)]
    want = [trs([10, 1, 0], [0, 0, 0, 1], [1, 1, 1]), trs([10, 1, 5], [0, 0, 0, 1], [1, 1, 1]),
            trs([10, 0, 0], [0, 0, 0, 1], [3, 3, 3])]
    assert len(got) == 3
    for g, w in zip(got, want):
        assert np.allclose(g, w, atol=TRANSFORM_TOLERANCE)


def no_leftovers(folder):
    """No staging folders or temporary files were left behind."""
    return not [p for p in Path(folder).iterdir() if p.name.startswith(".aggtool_usd.")]


def test_missing_aggregate_writes_nothing(assets):
    """An asset without its .agg: one clear line, no layer, payload or staging folder."""
    out = assets / "bad" / "lonely.usda"
    out.parent.mkdir(exist_ok=True)
    shutil.copy(assets / "scene" / "foliage.glb", out.parent / "lonely.glb")
    usd_fails("asset", "bad/lonely.glb", "-o", out, cwd=assets, words="missing aggregate")
    assert sorted(p.name for p in out.parent.iterdir()) == ["lonely.glb"]


def test_aggregate_of_another_asset_warns(assets):
    """An .agg baked from another source still makes a layer, with a warning naming both."""
    r = usd_ok("asset", "scene/buildings.glb", "--agg", "scene/foliage.agg", "-o", "bad/mixed.usda", cwd=assets)
    assert "baked from foliage.glb, not buildings.glb" in r.stderr


def test_stage_without_instancers(assets):
    """A stage with no PointInstancer and no aggtool asset: an error, no manifest."""
    path = assets / "bad" / "empty.usda"
    path.parent.mkdir(exist_ok=True)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Cube.Define(stage, "/World/box")
    stage.GetRootLayer().Save()
    usd_fails("manifest", path, "-o", "bad/empty.json", cwd=assets, words="no PointInstancer")
    assert not (assets / "bad" / "empty.json").exists() and no_leftovers(assets / "bad")


def test_prototype_without_geometry(assets, foliage_layer):
    """A PointInstancer whose prototype is a plain cube (no aggtool asset): an error naming the
    prototype; an existing manifest at the output path is left as it was."""
    path = assets / "bad" / "cubes.usda"
    path.parent.mkdir(exist_ok=True)
    stage = Usd.Stage.CreateNew(str(path))
    pi = UsdGeom.PointInstancer.Define(stage, "/World/cubes")
    cube = UsdGeom.Cube.Define(stage, "/World/cubes/Prototypes/box")
    pi.CreatePrototypesRel().SetTargets([cube.GetPath()])
    pi.CreateProtoIndicesAttr([0])
    pi.CreatePositionsAttr([Gf.Vec3f(0, 0, 0)])
    stage.GetRootLayer().Save()
    old = assets / "bad" / "cubes.json"
    old.write_text("previous\n")
    usd_fails("manifest", path, "-o", old, cwd=assets, words="/World/cubes/Prototypes/box")
    assert old.read_text() == "previous\n" and no_leftovers(assets / "bad")


def test_prototype_with_missing_layer(assets):
    """A prototype referencing a layer that does not exist has no resolvable geometry either."""
    path = assets / "bad" / "missing.usda"
    path.parent.mkdir(exist_ok=True)
    stage = Usd.Stage.CreateNew(str(path))
    pi = UsdGeom.PointInstancer.Define(stage, "/World/trees")
    proto = UsdGeom.Xform.Define(stage, "/World/trees/Prototypes/tree")
    proto.GetPrim().GetReferences().AddReference("./no_such_tree.usda")
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    pi.CreateProtoIndicesAttr([0])
    pi.CreatePositionsAttr([Gf.Vec3f(0, 0, 0)])
    stage.GetRootLayer().Save()
    r = usd_fails("manifest", path, "-o", "bad/missing.json", cwd=assets, words="has no resolvable geometry")
    assert "no_such_tree.usda" in r.stderr  # the composition error says why
    assert not (assets / "bad" / "missing.json").exists()


def test_not_a_stage(assets):
    """A file that USD cannot open, and a missing stage."""
    bad = assets / "bad" / "text.usda"
    bad.parent.mkdir(exist_ok=True)
    bad.write_text("hello")
    usd_fails("manifest", bad, "-o", "bad/text.json", cwd=assets, words="cannot open the stage")
    usd_fails("manifest", "bad/none.usda", "-o", "bad/text.json", cwd=assets, words="no such stage")
    assert not (assets / "bad" / "text.json").exists() and no_leftovers(assets / "bad")


@pytest.mark.parametrize("change, words", [
    (lambda d: d.update(version=2), "version 2"),
    (lambda d: d["instances"].append({"asset": "ghost"}), "instance 4: unknown asset 'ghost'"),
    (lambda d: d["instances"][2].update(translation=[0, float("nan"), 0]), "instance 2 translation: non-finite"),
    (lambda d: d["instances"][1].update(matrix=[1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]), "instance 1: singular"),
    (lambda d: d["instances"][1].update(matrix=[1, 0, 0, 0, 1, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]), "instance 1: the transform has shear"),
    (lambda d: d["instances"][0].update(rotation=[0, 0, 0, 2]), "instance 0 rotation: not a unit quaternion"),
    (lambda d: d["assets"]["tree"].update(source="../scene/nothing.glb"), "asset 'tree': missing source"),
    (lambda d: d["assets"]["city-block"].update(aggregate="../scene/nothing.agg"), "asset 'city-block': missing aggregate"),
])
def test_bad_manifests(assets, change, words):
    """Each broken manifest fails with a line naming the asset or instance; no city layer, no
    asset layers and no staging folder are left."""
    doc = json.loads(json.dumps(CITY))
    change(doc)
    folder = assets / "badcity"
    shutil.rmtree(folder, ignore_errors=True)
    manifest = folder / "city.json"
    folder.mkdir()
    manifest.write_text(json.dumps(doc))  # NaN is written as the JSON extension NaN
    usd_fails("assembly", manifest, "-o", folder / "city.usda", cwd=assets, words=words)
    assert sorted(p.name for p in folder.iterdir()) == ["city.json"]


def test_not_a_manifest(assets):
    """A file that is not JSON, and a missing manifest."""
    bad = assets / "bad" / "text.json"
    bad.parent.mkdir(exist_ok=True)
    bad.write_text("hello")
    usd_fails("assembly", bad, "-o", "bad/x.usda", cwd=assets, words="not a JSON manifest")
    usd_fails("assembly", "bad/none.json", "-o", "bad/x.usda", cwd=assets, words="no such manifest")
    assert not (assets / "bad" / "x.usda").exists()


@pytest.mark.skipif(not (SHARED / "kenney_city_kit" / "building-small-a.glb").exists(),
                    reason="(no ../shared/assets): its Kenney city kit is needed")
def test_shared_textured_asset(tmp_path):
    """A textured shared asset (Kenney city kit): its base-colour texture is written beside the
    layer, wired into the UsdPreviewSurface as sRGB, and resolves."""
    src = SHARED / "kenney_city_kit" / "building-small-a.glb"
    run("convert", src, "-o", tmp_path / "building.agg", *BAKE, cwd=tmp_path)
    usd_ok("asset", src, "--agg", tmp_path / "building.agg", "-o", tmp_path / "building.usda", cwd=tmp_path)
    layer = tmp_path / "building.usda"
    _, _, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(layer)))
    assert not unresolved, unresolved
    stage = Usd.Stage.Open(str(layer))
    textures = [UsdShade.Shader(p) for p in stage.Traverse() if p.GetName() == "baseColorTexture"]
    assert textures
    for t in textures:
        assert t.GetInput("sourceColorSpace").Get() == "sRGB"
        f = t.GetInput("file").Get()
        assert f.resolvedPath and Path(f.resolvedPath).parent.name == "building.textures"
