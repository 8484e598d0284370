"""One asset as a USD component model whose UsdLod root switches between its mesh and its
aggregate.

`write_asset` writes, beside `ASSET.usda`:

- `ASSET.usda`: the component (default prim, `kind = component`, `assetInfo`) holding
  - `lod` (`LODRootAPI`), whose children in order are the levels:
    - `full`: an Xform whose payload is `ASSET.full.usdc`;
    - `aggregate`: the sidecar prim (type `AggtoolAggregate`, a codeless schema in resources/;
      `aggtool:sidecar = @./ASSET.agg@`, `extent`, the format
      version, the levels' resolutions, the finest voxel's edge);
  - `lodHeuristic` (`LODScreenSizeHeuristic`, not under the LOD root, whose every child is a
    level): full mesh above the screen fraction at which the finest voxel covers one pixel,
    aggregate at or below it;
  - a variant set `lod` {full, aggregate} that deactivates the other level, for consumers older
    than UsdLod (OpenUSD 26.8). No selection is authored, so UsdLod consumers see both levels.
- `ASSET.full.usdc`: the geometry (`UsdGeom.Mesh` with normals and `st`), its
  `UsdPreviewSurface` materials, and instanced meshes as instanceable internal references;
- `ASSET.textures/`: the textures the materials use, as PNG (when there are any).
"""
from __future__ import annotations

import math
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, UsdLod, UsdShade, Vt

from .errors import UsdToolError
from .manifest import relative
from .schema import AGGREGATE_TYPE
from .staging import Staging
from .tool import export_geometry, inspect_aggregate

#: Image width (pixels) and aspect (width / height) at which the LoD threshold is stated.
DEFAULT_IMAGE_WIDTH = 1920
DEFAULT_IMAGE_ASPECT = 16 / 9


@dataclass
class AssetLayer:
    """What `write_asset` wrote and what the assembly needs of it."""
    layer: Path
    prim_name: str
    bounds: tuple[list[float], list[float]]
    threshold: float


def anchored(path: Path, folder: Path) -> str:
    """An asset path relative to a layer in `folder`, always starting with ./ or ../ so that
    USD anchors it to the layer rather than searching for it."""
    rel = relative(path, folder)
    return rel if rel.startswith("../") else "./" + rel


def screen_threshold(lo: list[float], hi: list[float], finest_res: int, width: int, aspect: float) -> float:
    """The `projectedSphere` screen size (disc area over viewport area) below which one voxel of
    the finest level is smaller than a pixel of a `width`-pixel image of the given aspect.

    A bounding sphere of radius R drawn r pixels wide shows a voxel of edge v as v·r/R pixels;
    that is under a pixel for r < R/v, whose disc covers π (R/v)² of the W·H pixels."""
    ext = np.asarray(hi, float) - np.asarray(lo, float)
    radius = 0.5 * float(np.linalg.norm(ext))
    voxel = float(ext.max()) / finest_res
    height = width / aspect
    return math.pi * (radius / voxel) ** 2 / (width * height)


def _view(buf: bytes, view: dict[str, Any] | None, dtype: str, per: int) -> np.ndarray | None:
    """The `count` elements of `per` components at `offset` in geometry.bin."""
    if view is None:
        return None
    a = np.frombuffer(buf, dtype=dtype, count=view["count"] * per, offset=view["offset"])
    return a.reshape(-1, per) if per > 1 else a


IDENTITY_UV = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
#: Shear in a texture transform smaller than this is dropped (UsdTransform2d has none).
SHEAR_TOLERANCE = 1e-5


def st_transform(uv: list[float]) -> tuple[tuple[float, float], float, tuple[float, float]] | None:
    """A glTF texture-coordinate transform (column-major 3×3 acting on (u, v), v down) as the
    UsdTransform2d inputs (scale, rotation in degrees, translation) acting on USD's
    st = (u, 1 − v): with F the flip, st' = F M F st, whose linear part D A D (D = diag(1, −1))
    is split as R(rotation) · diag(scale) and whose offset is D (A e + b) + e, e = (0, 1).
    None when that part has shear, which UsdTransform2d cannot hold."""
    a = np.array([[uv[0], uv[3]], [uv[1], uv[4]]])
    b = np.array([uv[6], uv[7]])
    d, e = np.diag([1.0, -1.0]), np.array([0.0, 1.0])
    lin, off = d @ a @ d, d @ (a @ e + b) + e
    sx = float(np.linalg.norm(lin[:, 0]))
    angle = math.atan2(lin[1, 0], lin[0, 0])
    rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    rest = rot.T @ lin  # diag(sx, sy) when there is no shear
    if sx == 0 or abs(rest[0, 1]) > SHEAR_TOLERANCE * max(1.0, abs(rest[1, 1])) or abs(rest[1, 0]) > SHEAR_TOLERANCE:
        return None
    return (sx, float(rest[1, 1])), math.degrees(angle), (float(off[0]), float(off[1]))


def _texture(stage: Usd.Stage, mat_path: Sdf.Path, name: str, ref: dict[str, Any], reader: UsdShade.Shader,
             textures: str, raw: bool, scale: Gf.Vec4f) -> UsdShade.Shader:
    """A UsdUVTexture reading `ref`'s file through the `st` reader (and a UsdTransform2d for a
    KHR_texture_transform), scaled by the factors."""
    st_source = reader.ConnectableAPI(), "result"
    if ref["uv_transform"] != IDENTITY_UV:
        trs = st_transform(ref["uv_transform"])
        if trs is None:
            print(f"warning: {ref['file']}: its texture transform has shear, which UsdTransform2d cannot hold; "
                  f"left out", file=sys.stderr)
        else:
            xf = UsdShade.Shader.Define(stage, mat_path.AppendChild(f"{name}Transform"))
            xf.CreateIdAttr("UsdTransform2d")
            xf.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(*st_source)
            xf.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(*trs[0]))
            xf.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(trs[1])
            xf.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(*trs[2]))
            xf.CreateOutput("result", Sdf.ValueTypeNames.Float2)
            st_source = xf.ConnectableAPI(), "result"
    tex = UsdShade.Shader.Define(stage, mat_path.AppendChild(name))
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{textures}/{ref['file']}"))
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(*st_source)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw" if raw else "sRGB")
    tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
    tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(scale)
    return tex


def _material(stage: Usd.Stage, path: Sdf.Path, m: dict[str, Any], textures: str) -> UsdShade.Material:
    """A UsdPreviewSurface material from an exported glTF-style material (linear factors)."""
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, path.AppendChild("PreviewSurface"))
    surf.CreateIdAttr("UsdPreviewSurface")
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    r, g, b, a = m["base_color"]
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(r, g, b))
    # glTF OPAQUE ignores alpha; MASK keeps the surface where alpha ≥ cutoff.
    masked = m["alpha_cutoff"] is not None
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(a if masked else 1.0)
    surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(m["metallic"])
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(m["roughness"])
    if masked:
        surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(m["alpha_cutoff"])
    if m["base_color_texture"] or m["metallic_roughness_texture"]:
        reader = UsdShade.Shader.Define(stage, path.AppendChild("stReader"))
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
        if m["base_color_texture"]:
            tex = _texture(stage, path, "baseColorTexture", m["base_color_texture"], reader, textures, False,
                           Gf.Vec4f(r, g, b, a))
            surf.GetInput("diffuseColor").ConnectToSource(
                tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3).GetAttr().GetPath())
            if masked:
                surf.GetInput("opacity").ConnectToSource(
                    tex.CreateOutput("a", Sdf.ValueTypeNames.Float).GetAttr().GetPath())
        if m["metallic_roughness_texture"]:
            # glTF packs roughness in green and metallic in blue.
            tex = _texture(stage, path, "metallicRoughnessTexture", m["metallic_roughness_texture"], reader,
                           textures, True, Gf.Vec4f(1, m["roughness"], m["metallic"], 1))
            surf.GetInput("roughness").ConnectToSource(
                tex.CreateOutput("g", Sdf.ValueTypeNames.Float).GetAttr().GetPath())
            surf.GetInput("metallic").ConnectToSource(
                tex.CreateOutput("b", Sdf.ValueTypeNames.Float).GetAttr().GetPath())
    return mat


def _mesh(stage: Usd.Stage, path: Sdf.Path, mesh: dict[str, Any], buf: bytes) -> UsdGeom.Mesh:
    """A triangle UsdGeom.Mesh with vertex normals and `st` (v flipped: glTF's v = 0 is the
    image's top row, USD's t = 0 its bottom)."""
    points = _view(buf, mesh["positions"], "<f4", 3)
    indices = _view(buf, mesh["indices"], "<u4", 1)
    m = UsdGeom.Mesh.Define(stage, path)
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points)))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(indices) // 3, 3, np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
    if len(points):
        m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, points.min(0))), Gf.Vec3f(*map(float, points.max(0)))]))
    normals = _view(buf, mesh["normals"], "<f4", 3)
    if normals is not None:
        m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals)))
        m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    uvs = _view(buf, mesh["uvs"], "<f4", 2)
    if uvs is not None:
        st = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], axis=1).astype(np.float32)
        UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                             UsdGeom.Tokens.vertex).Set(Vt.Vec2fArray.FromNumpy(st))
    return m


def _write_geometry(layer_path: Path, scene: dict[str, Any], buf: bytes, textures: str) -> None:
    """The `full` level's layer: /full with Looks (materials), Prototypes (meshes placed more than
    once, as a class) and Geom (one prim per instance, column-major matrices as in glTF)."""
    stage = Usd.Stage.CreateNew(str(layer_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    full = UsdGeom.Xform.Define(stage, "/full")
    stage.SetDefaultPrim(full.GetPrim())
    looks = UsdGeom.Scope.Define(stage, "/full/Looks").GetPath()
    materials = [_material(stage, looks.AppendChild(f"material_{i:03}"), m, textures)
                 for i, m in enumerate(scene["materials"])]
    uses = np.bincount([i["mesh"] for i in scene["instances"]], minlength=len(scene["meshes"]))
    protos = Sdf.Path("/full/Prototypes")
    if (uses > 1).any():
        stage.CreateClassPrim(protos)
    for k in np.flatnonzero(uses > 1):
        m = _mesh(stage, protos.AppendChild(f"mesh_{k:03}"), scene["meshes"][k], buf)
        UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(materials[scene["meshes"][k]["material"]])
    geom = UsdGeom.Xform.Define(stage, "/full/Geom").GetPath()
    for n, inst in enumerate(scene["instances"]):
        k = inst["mesh"]
        path = geom.AppendChild(f"instance_{n:04}")
        if uses[k] > 1:
            prim = stage.DefinePrim(path, "Mesh")
            prim.GetReferences().AddInternalReference(protos.AppendChild(f"mesh_{k:03}"))
            prim.SetInstanceable(True)
            xf = UsdGeom.Xformable(prim)
        else:
            xf = _mesh(stage, path, scene["meshes"][k], buf)
            UsdShade.MaterialBindingAPI.Apply(xf.GetPrim()).Bind(materials[scene["meshes"][k]["material"]])
        # Column-major with column vectors is row-major with row vectors: USD's layout.
        matrix = Gf.Matrix4d(*inst["matrix"])
        if matrix != Gf.Matrix4d(1):
            xf.MakeMatrixXform().Set(matrix)
    stage.GetRootLayer().Save()


def write_asset(asset: Path, agg: Path | None, out: Path, *, staging: Staging | None = None,
                image_width: int = DEFAULT_IMAGE_WIDTH, image_aspect: float = DEFAULT_IMAGE_ASPECT,
                asset_name: str | None = None) -> AssetLayer:
    """Writes `out` (ASSET.usda) and its payload and textures beside it; see the module
    documentation. With `staging`, the files are staged there (under paths relative to its
    root) and left for the caller to commit; otherwise they land together or not at all.
    `asset_name` (default: the layer's stem) is the assetInfo name, which manifests read back
    as the asset's id."""
    asset = Path(asset).resolve()
    out = Path(out).resolve()
    agg = Path(agg).resolve() if agg else asset.with_suffix(".agg")
    if not asset.is_file():
        raise UsdToolError(f"missing asset {asset}")
    if out.suffix not in (".usda", ".usd", ".usdc"):
        raise UsdToolError(f"{out}: the output must be a .usda, .usd or .usdc layer")
    info = inspect_aggregate(agg)
    levels = [int(l["res"]) for l in info["levels"]]
    lo, hi = info["bounds"]
    if not levels or not all(math.isfinite(x) for x in lo + hi) or not all(h > l for l, h in zip(lo, hi)):
        raise UsdToolError(f"{agg}: the aggregate has no levels or empty bounds")
    threshold = screen_threshold(lo, hi, max(levels), image_width, image_aspect)
    baked_from = Path(str(info.get("source") or "")).name
    if baked_from and baked_from != asset.name:
        print(f"warning: {agg} was baked from {baked_from}, not {asset.name}", file=sys.stderr)

    own = staging is None
    stage_root = staging.root if staging else out.parent
    staging = staging or Staging(out.parent)
    try:
        rel_dir = Path(relative(out.parent, stage_root))
        stem = out.stem
        payload_name, textures_name = f"{stem}.full.usdc", f"{stem}.textures"
        work = staging.dir / f".export.{stem}"
        scene = export_geometry(asset, work)
        buf = (work / scene["geometry"]).read_bytes()
        pngs = sorted(work.glob("*.png"))
        if pngs:
            tex_dir = staging.path((rel_dir / textures_name).as_posix())
            tex_dir.mkdir()
            for p in pngs:
                shutil.move(p, tex_dir / p.name)
        _write_geometry(staging.path((rel_dir / payload_name).as_posix()), scene, buf, textures_name)
        shutil.rmtree(work)

        layer_tmp = staging.path((rel_dir / out.name).as_posix())
        stage = Usd.Stage.CreateNew(str(layer_tmp), load=Usd.Stage.LoadNone)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        name = Tf.MakeValidIdentifier(stem)
        root = UsdGeom.Xform.Define(stage, f"/{name}").GetPrim()
        stage.SetDefaultPrim(root)
        model = Usd.ModelAPI(root)
        model.SetKind(Kind.Tokens.component)
        model.SetAssetName(asset_name or name)
        model.SetAssetIdentifier(Sdf.AssetPath(f"./{out.name}"))
        root.CreateAttribute("aggtool:source", Sdf.ValueTypeNames.Asset, custom=True).Set(
            Sdf.AssetPath(anchored(asset, out.parent)))

        lod = UsdGeom.Xform.Define(stage, f"/{name}/lod").GetPrim()
        lod_api = UsdLod.RootAPI.Apply(lod)
        full = UsdGeom.Xform.Define(stage, f"/{name}/lod/full").GetPrim()
        full.GetPayloads().AddPayload(f"./{payload_name}")
        # Typed by the codeless schema (resources/). Created as custom attributes, they are
        # written as the schema's own where it is registered; tools without the schema read
        # the same names and values on an untyped prim.
        side = stage.DefinePrim(f"/{name}/lod/aggregate", AGGREGATE_TYPE)
        attr = lambda n, t, v: side.CreateAttribute(n, t, custom=True).Set(v)  # noqa: E731
        attr("aggtool:sidecar", Sdf.ValueTypeNames.Asset, Sdf.AssetPath(anchored(agg, out.parent)))
        attr("extent", Sdf.ValueTypeNames.Float3Array, Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]))
        attr("aggtool:formatVersion", Sdf.ValueTypeNames.String, info["format"])
        attr("aggtool:levelResolutions", Sdf.ValueTypeNames.IntArray, Vt.IntArray(levels))
        attr("aggtool:finestVoxelSize", Sdf.ValueTypeNames.Float, (max(h - l for l, h in zip(lo, hi))) / max(levels))

        heur = UsdLod.ScreenSizeHeuristic.Define(stage, f"/{name}/lodHeuristic")
        heur.CreateLodDomainAttr(UsdLod.Tokens.imaging)
        heur.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]))
        heur.CreateProjectionMethodAttr(UsdLod.Tokens.projectedSphere)
        heur.CreateThresholdsAttr(Vt.FloatArray([threshold]))
        hp = heur.GetPrim()
        hp.SetDocumentation(f"Level 0 (full mesh) above screen size {threshold:.4g}, level 1 (aggregate) at "
                            f"or below it: there the finest voxel ({max(levels)}^3 grid) covers under one "
                            f"pixel of a {image_width}-pixel-wide image of aspect {image_aspect:.4g}.")
        hp.CreateAttribute("aggtool:imageWidth", Sdf.ValueTypeNames.Int, custom=True).Set(image_width)
        hp.CreateAttribute("aggtool:imageAspect", Sdf.ValueTypeNames.Float, custom=True).Set(image_aspect)
        lod_api.CreateLodHeuristicsRel().SetTargets([heur.GetPath()])
        lod_api.CreateLodDefaultIndexAttr(0)

        variants = root.GetVariantSets().AddVariantSet("lod")
        for keep, drop in (("full", "aggregate"), ("aggregate", "full")):
            variants.AddVariant(keep)
            variants.SetVariantSelection(keep)
            with variants.GetVariantEditContext():
                stage.OverridePrim(f"/{name}/lod/{drop}").SetActive(False)
        variants.ClearVariantSelection()
        stage.GetRootLayer().Save()
        if own:
            staging.commit()
    finally:
        if own:
            staging.__exit__(None, None, None)
    return AssetLayer(out, name, (lo, hi), threshold)
