"""The assembly manifest of issue 18 (`"version": 1`), read and written.

    { "version": 1,
      "assets": { "beech": { "source": "trees/copperBeech.obj" },
                  "inn":   { "source": "village/fantasy_inn.glb", "aggregate": "bakes/inn.agg" } },
      "instances": [ { "asset": "beech", "translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1] },
                     { "asset": "inn", "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 12,0,-4,1] } ] }

Paths resolve against the manifest's folder; `aggregate` defaults to the source's path with
`.agg`; `rotation` is a unit quaternion [x, y, z, w] and `matrix` is column-major, both as in
glTF. Transforms are held as 4×4 matrices acting on column vectors (p' = M p).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import UsdToolError

VERSION = 1

#: |RᵀR − I| above this after removing the column scales is shear, which no TRS holds.
SHEAR_TOLERANCE = 1e-4
#: |q| may differ from 1 by this much (float text round-off); larger is an error.
UNIT_TOLERANCE = 1e-3


@dataclass
class Asset:
    """One asset: its source scene and its baked aggregate (absolute paths)."""
    source: Path
    aggregate: Path


@dataclass
class Instance:
    """A placement of an asset: `matrix` is object-to-world, column vectors."""
    asset: str
    matrix: np.ndarray


@dataclass
class Manifest:
    """Assets by id and the instances placing them."""
    assets: dict[str, Asset] = field(default_factory=dict)
    instances: list[Instance] = field(default_factory=list)


def default_aggregate(source: Path) -> Path:
    """Where `aggtool convert SOURCE` writes its aggregate."""
    return source.with_suffix(".agg")


def trs_matrix(translation: Any, rotation: Any, scale: Any) -> np.ndarray:
    """M = T · R · S from a translation, a quaternion [x, y, z, w] and a per-axis scale."""
    x, y, z, w = rotation
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r * np.asarray(scale, dtype=float)[None, :]
    m[:3, 3] = translation
    return m


def quaternion_from_rotation(r: np.ndarray) -> np.ndarray:
    """Unit quaternion [x, y, z, w] (w ≥ 0) of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2 * math.sqrt(1 + t)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2 * math.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2 * math.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2 * math.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def decompose(m: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translation, quaternion [x, y, z, w], scale) with M = T · R · S; a mirror is a negative
    x scale. Errors (naming `what`) on projective, singular or sheared matrices."""
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise UsdToolError(f"{what}: projective matrix (last row {m[3].tolist()}), not an affine transform")
    a = m[:3, :3]
    scale = np.linalg.norm(a, axis=0)
    det = np.linalg.det(a)
    if not np.all(scale > 1e-12) or abs(det) < 1e-12 * np.prod(scale):
        raise UsdToolError(f"{what}: singular transform")
    if det < 0:
        scale[0] = -scale[0]
    r = a / scale[None, :]
    if np.abs(r.T @ r - np.eye(3)).max() > SHEAR_TOLERANCE:
        raise UsdToolError(f"{what}: the transform has shear; only translation, rotation and scale can be instanced")
    return m[:3, 3].copy(), quaternion_from_rotation(r), scale


def _numbers(v: Any, n: int, what: str) -> list[float]:
    """`v` as n finite numbers, or an error naming `what`."""
    if not isinstance(v, list) or len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise UsdToolError(f"{what}: expected {n} numbers")
    if not all(math.isfinite(x) for x in v):
        raise UsdToolError(f"{what}: non-finite value")
    return [float(x) for x in v]


def _instance_matrix(inst: dict[str, Any], what: str) -> np.ndarray:
    """An instance's object-to-world matrix from `matrix` or translation/rotation/scale."""
    if "matrix" in inst:
        if any(k in inst for k in ("translation", "rotation", "scale")):
            raise UsdToolError(f"{what}: give either matrix or translation/rotation/scale, not both")
        m = np.array(_numbers(inst["matrix"], 16, f"{what} matrix")).reshape(4, 4).T
    else:
        t = _numbers(inst.get("translation", [0, 0, 0]), 3, f"{what} translation")
        q = _numbers(inst.get("rotation", [0, 0, 0, 1]), 4, f"{what} rotation")
        s = _numbers(inst.get("scale", [1, 1, 1]), 3, f"{what} scale")
        norm = math.sqrt(sum(x * x for x in q))
        if abs(norm - 1) > UNIT_TOLERANCE:
            raise UsdToolError(f"{what} rotation: not a unit quaternion (length {norm:g})")
        m = trs_matrix(t, [x / norm for x in q], s)
    if abs(np.linalg.det(m[:3, :3])) < 1e-12:
        raise UsdToolError(f"{what}: singular transform")
    return m


def load_manifest(path: Path, check_files: bool = True) -> Manifest:
    """Reads and checks a manifest; errors name the asset id or instance index. With
    `check_files`, every source must exist (aggregates are checked where they are used)."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UsdToolError(f"{path}: no such manifest") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UsdToolError(f"{path}: not a JSON manifest ({e})") from None
    if not isinstance(doc, dict):
        raise UsdToolError(f"{path}: a manifest is a JSON object")
    if doc.get("version") != VERSION:
        raise UsdToolError(f"{path}: manifest version {doc.get('version')!r} is not supported (this reads version {VERSION})")
    folder = Path(path).resolve().parent
    assets, instances = doc.get("assets"), doc.get("instances")
    if not isinstance(assets, dict) or not assets:
        raise UsdToolError(f"{path}: 'assets' must be a non-empty object")
    if not isinstance(instances, list):
        raise UsdToolError(f"{path}: 'instances' must be a list")
    out = Manifest()
    for key, a in assets.items():
        if not isinstance(a, dict) or not isinstance(a.get("source"), str):
            raise UsdToolError(f"asset '{key}': needs a 'source' path")
        source = (folder / a["source"]).resolve()
        if check_files and not source.is_file():
            raise UsdToolError(f"asset '{key}': missing source file {source}")
        agg = a.get("aggregate")
        if agg is not None and not isinstance(agg, str):
            raise UsdToolError(f"asset '{key}': 'aggregate' must be a path")
        out.assets[key] = Asset(source, (folder / agg).resolve() if agg else default_aggregate(source))
    for i, inst in enumerate(instances):
        what = f"instance {i}"
        if not isinstance(inst, dict):
            raise UsdToolError(f"{what}: expected an object")
        if inst.get("asset") not in out.assets:
            raise UsdToolError(f"{what}: unknown asset {inst.get('asset')!r}")
        out.instances.append(Instance(inst["asset"], _instance_matrix(inst, what)))
    return out


def relative(path: Path, folder: Path) -> str:
    """`path` relative to `folder`, with forward slashes (portable manifests and layers)."""
    return Path(os.path.relpath(path, folder)).as_posix()


def manifest_json(m: Manifest, folder: Path) -> dict[str, Any]:
    """The manifest as JSON, paths relative to `folder`, instances as translation/rotation/scale."""
    assets: dict[str, Any] = {}
    for key, a in m.assets.items():
        entry = {"source": relative(a.source, folder)}
        if a.aggregate.resolve() != default_aggregate(a.source).resolve():
            entry["aggregate"] = relative(a.aggregate, folder)
        assets[key] = entry
    instances = []
    for i, inst in enumerate(m.instances):
        t, q, s = decompose(inst.matrix, f"instance {i}")
        instances.append({"asset": inst.asset, "translation": _digits(t), "rotation": _digits(q), "scale": _digits(s)})
    return {"version": VERSION, "assets": assets, "instances": instances}


def _digits(v: np.ndarray) -> list[float]:
    """Values rounded to 8 significant digits: USD stores them as float32 (about 7), so the
    digits beyond are noise of the conversion."""
    return [float(f"{x:.8g}") + 0.0 for x in v]  # + 0.0 turns -0.0 into 0.0


def dumps(doc: dict[str, Any]) -> str:
    """Manifest JSON with one line per instance."""
    head = {k: v for k, v in doc.items() if k != "instances"}
    text = json.dumps(head, indent=2)[:-2]
    rows = ",\n".join("    " + json.dumps(i) for i in doc["instances"])
    return f'{text},\n  "instances": [\n{rows}\n  ]\n}}\n'

