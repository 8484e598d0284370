"""Assemblies: a manifest as a `kind = assembly` stage with one `UsdGeom.PointInstancer`, and any
USD stage's PointInstancers and referenced aggtool assets back as a manifest.

`write_assembly` writes `CITY.usda` and, beside it in `CITY_assets/`, one asset layer per
manifest asset (see `asset.py`); the instancer's prototypes reference those layers.
`read_manifest` walks a composed stage: each PointInstancer instance (mask honoured) of a
prototype holding aggtool assets, and each aggtool asset prim outside prototypes, becomes a
manifest instance with its world transform (every enclosing transform composed).
"""
from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, Vt

from .asset import DEFAULT_IMAGE_ASPECT, DEFAULT_IMAGE_WIDTH, anchored, write_asset
from .errors import UsdToolError
from .manifest import Asset, Instance, Manifest, decompose_many, dumps, load_manifest, manifest_json
from .staging import Staging

#: The attribute that marks an asset prim written by `write_asset`.
SOURCE_ATTR = "aggtool:source"
SIDECAR_ATTR = "aggtool:sidecar"


def _to_numpy(m: Gf.Matrix4d) -> np.ndarray:
    """USD's row-vector matrix as a column-vector one (p' = M p)."""
    return np.array(m, dtype=float).T


def write_assembly(manifest_path: Path, out: Path, *, image_width: int = DEFAULT_IMAGE_WIDTH,
                   image_aspect: float = DEFAULT_IMAGE_ASPECT) -> Path:
    """Writes the assembly layer `out` and its asset layers; all land together or none does."""
    manifest_path, out = Path(manifest_path).resolve(), Path(out).resolve()
    m = load_manifest(manifest_path)
    if not m.instances:
        raise UsdToolError(f"{manifest_path}: the manifest places no instances")
    ids = list(m.assets)
    # Every transform must fit a PointInstancer (translation, rotation, scale) before any work.
    positions, orientations, scales = decompose_many(np.stack([inst.matrix for inst in m.instances]))
    used = {inst.asset for inst in m.instances}
    ids = [k for k in ids if k in used]
    for key in ids:
        if not m.assets[key].aggregate.is_file():
            raise UsdToolError(f"asset '{key}': missing aggregate {m.assets[key].aggregate}: bake it with `aggtool convert`")
    # Prim and file names: ids made valid identifiers, kept distinct ("a-b" and "a_b").
    names: dict[str, str] = {}
    for key in ids:
        name, n = Tf.MakeValidIdentifier(key), 2
        while name in names.values():
            name, n = f"{Tf.MakeValidIdentifier(key)}_{n}", n + 1
        names[key] = name
    assets_dir = f"{out.stem}_assets"
    with Staging(out.parent) as staging:
        layers = {}
        for key in ids:
            a = m.assets[key]
            try:
                layers[key] = write_asset(a.source, a.aggregate, out.parent / assets_dir / f"{names[key]}.usda",
                                          staging=staging, image_width=image_width, image_aspect=image_aspect,
                                          asset_name=key)
            except UsdToolError as e:
                raise UsdToolError(f"asset '{key}': {e}") from None

        stage = Usd.Stage.CreateNew(str(staging.path(out.name)), load=Usd.Stage.LoadNone)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root_name = Tf.MakeValidIdentifier(out.stem)
        root = UsdGeom.Xform.Define(stage, f"/{root_name}").GetPrim()
        stage.SetDefaultPrim(root)
        Usd.ModelAPI(root).SetKind(Kind.Tokens.assembly)
        Usd.ModelAPI(root).SetAssetName(root_name)
        root.SetCustomDataByKey("aggtool:manifest", anchored(manifest_path, out.parent))
        pi = UsdGeom.PointInstancer.Define(stage, f"/{root_name}/instancer")
        protos = UsdGeom.Scope.Define(stage, pi.GetPath().AppendChild("prototypes")).GetPath()
        targets = []
        for key in ids:
            p = UsdGeom.Xform.Define(stage, protos.AppendChild(names[key])).GetPrim()
            p.GetReferences().AddReference(anchored(layers[key].layer, out.parent))
            targets.append(p.GetPath())
        pi.CreatePrototypesRel().SetTargets(targets)
        index = {k: i for i, k in enumerate(ids)}
        pi.CreateProtoIndicesAttr(Vt.IntArray([index[inst.asset] for inst in m.instances]))
        pi.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(positions.astype(np.float32)))
        # Float quaternions (orientationsf): half precision would move a point 100 m away by ~10 cm.
        # GfQuatf's memory is (i, j, k, real): the manifest's [x, y, z, w] order.
        pi.CreateOrientationsfAttr(Vt.QuatfArray.FromNumpy(orientations.astype(np.float32)))
        pi.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(scales.astype(np.float32)))
        pi.CreateIdsAttr(Vt.Int64Array.FromNumpy(np.arange(len(m.instances), dtype=np.int64)))
        # Extent: the aggregates' bounds carried by every instance.
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for inst in m.instances:
            blo, bhi = layers[inst.asset].bounds
            corners = np.array([[x, y, z, 1.0] for x in (blo[0], bhi[0]) for y in (blo[1], bhi[1])
                                for z in (blo[2], bhi[2])])
            w = (inst.matrix @ corners.T).T[:, :3]
            lo, hi = np.minimum(lo, w.min(0)), np.maximum(hi, w.max(0))
        pi.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        stage.GetRootLayer().Save()
        staging.commit()
    return out


def _asset_of(prim: Usd.Prim, stage_path: Path) -> tuple[str, Asset]:
    """The manifest asset (id, source and aggregate) of an aggtool asset prim."""
    src = prim.GetAttribute(SOURCE_ATTR).Get()
    if not isinstance(src, Sdf.AssetPath) or not src.resolvedPath:
        raise UsdToolError(f"{stage_path}: {prim.GetPath()}: {SOURCE_ATTR} @{getattr(src, 'path', src)}@ does not resolve to a file")
    agg = None
    for p in Usd.PrimRange(prim, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        a = p.GetAttribute(SIDECAR_ATTR)
        if a and a.HasValue():
            v = a.Get()
            # A missing sidecar is no error here: the manifest names where it is to be baked.
            agg = Path(v.resolvedPath) if v.resolvedPath else Path(
                Sdf.ComputeAssetPathRelativeToLayer(a.GetPropertyStack()[0].layer, v.path))
            break
    source = Path(src.resolvedPath).resolve()
    name = Usd.ModelAPI(prim).GetAssetName() or prim.GetName()
    return name, Asset(source, agg.resolve() if agg else source.with_suffix(".agg"))


def _assets_under(root: Usd.Prim) -> list[Usd.Prim]:
    """The aggtool asset prims at or under `root` (not looking inside an asset)."""
    found = []
    it = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for p in it:
        if p.HasAttribute(SOURCE_ATTR):
            found.append(p)
            it.PruneChildren()
    return found


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silences USD's own diagnostics on the process's stderr (file descriptor 2): the errors
    that matter are read from the stage and reported in the one error line."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _tf_message(e: Exception) -> str:
    """The quoted message of a Tf error, without its source location."""
    text = " ".join(str(e).split())
    return text.rsplit(" : ", 1)[-1].strip("'")


def _load_payloads_outside_assets(stage: Usd.Stage) -> None:
    """Loads the payloads that may hold assets (a set dressed behind payloads), level by level,
    but none inside an aggtool asset: its `full` level's geometry is not needed."""
    while True:
        pending = []
        it = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)))
        for p in it:
            if p.HasAttribute(SOURCE_ATTR):
                it.PruneChildren()
            elif p.HasAuthoredPayloads() and not p.IsLoaded():
                pending.append(p.GetPath())
                it.PruneChildren()
        if not pending:
            return
        with _quiet_stderr():
            stage.LoadAndUnload(pending, [], Usd.LoadWithoutDescendants)


def read_manifest(stage_path: Path) -> Manifest:
    """Every aggtool asset placed on the stage, by PointInstancer or by reference, as a manifest."""
    stage_path = Path(stage_path).resolve()
    if not stage_path.is_file():
        raise UsdToolError(f"{stage_path}: no such stage")
    try:
        with _quiet_stderr():
            stage = Usd.Stage.Open(str(stage_path), load=Usd.Stage.LoadNone)
    except Tf.ErrorException as e:
        raise UsdToolError(f"{stage_path}: cannot open the stage ({_tf_message(e)})") from None
    if not stage:
        raise UsdToolError(f"{stage_path}: cannot open the stage")
    _load_payloads_outside_assets(stage)
    m = Manifest()
    keys: dict[tuple[Path, Path], str] = {}
    cache = UsdGeom.XformCache()

    def key_of(prim: Usd.Prim) -> str:
        name, asset = _asset_of(prim, stage_path)
        ident = (asset.source, asset.aggregate)
        if ident not in keys:
            key, n = name, 2
            while key in m.assets:
                key, n = f"{name}_{n}", n + 1
            keys[ident] = key
            m.assets[key] = asset
        return keys[ident]

    instancers = 0
    it = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            instancers += 1
            it.PruneChildren()  # prototypes are placed by the instancer only
            pi = UsdGeom.PointInstancer(prim)
            protos = pi.GetPrototypesRel().GetTargets()
            # Each prototype's assets and their transforms relative to the prototype's root frame.
            contents = []
            for path in protos:
                proto = stage.GetPrimAtPath(path)
                if not proto:
                    raise UsdToolError(f"{stage_path}: {prim.GetPath()}: prototype {path} does not exist")
                nested = [p for p in Usd.PrimRange(proto) if p.IsA(UsdGeom.PointInstancer)]
                if nested:
                    raise UsdToolError(f"{stage_path}: {path}: nested PointInstancers ({nested[0].GetPath()}) are not supported")
                found = _assets_under(proto)
                if not found:
                    why = [str(e).strip() for e in stage.GetCompositionErrors() if f"<{path}" in str(e)]
                    raise UsdToolError(f"{stage_path}: prototype {path} of {prim.GetPath()} has no resolvable geometry "
                                       f"({why[0] if why else 'no asset layer written by `aggtool_usd asset` under it'})")
                root_inv = cache.GetLocalToWorldTransform(proto).GetInverse()
                contents.append([(key_of(a), cache.GetLocalToWorldTransform(a) * root_inv) for a in found])
            xfs = pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
            indices = pi.GetProtoIndicesAttr().Get() or []
            # Inactive (the mask) and invisible instances are not drawn: they are left out.
            mask = pi.ComputeMaskAtTime(Usd.TimeCode.Default())
            ids = pi.GetIdsAttr().Get()
            invisible = set(pi.GetInvisibleIdsAttr().Get() or [])
            world = cache.GetLocalToWorldTransform(prim)
            for i, xf in enumerate(xfs):
                if (mask and not mask[i]) or (invisible and (ids[i] if ids else i) in invisible):
                    continue
                if not 0 <= indices[i] < len(contents):
                    raise UsdToolError(f"{stage_path}: {prim.GetPath()}: instance {i} has protoIndex {indices[i]} "
                                       f"but there are {len(contents)} prototypes")
                for key, rel in contents[indices[i]]:
                    m.instances.append(Instance(key, _to_numpy(rel * xf * world)))
        elif prim.HasAttribute(SOURCE_ATTR):
            it.PruneChildren()
            m.instances.append(Instance(key_of(prim), _to_numpy(cache.GetLocalToWorldTransform(prim))))
    if not m.instances:
        what = "no PointInstancer" if not instancers else "PointInstancers with no instances"
        raise UsdToolError(f"{stage_path}: {what} and no aggtool asset placed on the stage")
    return m


def write_manifest(stage_path: Path, out: Path) -> Path:
    """`read_manifest` written as JSON at `out` (paths relative to its folder), atomically."""
    out = Path(out).resolve()
    doc = manifest_json(read_manifest(stage_path), out.parent)
    with Staging(out.parent) as staging:
        staging.path(out.name).write_text(dumps(doc))
        staging.commit()
    return out
