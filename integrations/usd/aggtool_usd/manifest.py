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
from typing import Any, Callable

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


def trs_matrices(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """M = T · R · S for N translations (N×3), unit quaternions [x, y, z, w] (N×4) and per-axis
    scales (N×3): N×4×4."""
    x, y, z, w = np.asarray(q, float).T
    r = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    m = np.zeros((len(r), 4, 4))
    m[:, :3, :3] = r * np.asarray(s, float)[:, None, :]
    m[:, :3, 3] = t
    m[:, 3, 3] = 1
    return m


def trs_matrix(translation: Any, rotation: Any, scale: Any) -> np.ndarray:
    """One M = T · R · S (see `trs_matrices`)."""
    return trs_matrices(np.array([translation], float), np.array([rotation], float), np.array([scale], float))[0]


def quaternions_from_rotations(r: np.ndarray) -> np.ndarray:
    """Unit quaternions [x, y, z, w] (w ≥ 0) of N rotation matrices (Shepperd's method: the
    branch of the largest of trace, r00, r11, r22 keeps the square root away from zero)."""
    r00, r11, r22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    q = np.empty((len(r), 4))
    cases = [
        (1 + r00 + r11 + r22, lambda s: [r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], 3),
        (1 + r00 - r11 - r22, lambda s: [r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 2, 1] - r[:, 1, 2]], 0),
        (1 + r11 - r00 - r22, lambda s: [r[:, 0, 1] + r[:, 1, 0], r[:, 1, 2] + r[:, 2, 1], r[:, 0, 2] - r[:, 2, 0]], 1),
        (1 + r22 - r00 - r11, lambda s: [r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1], r[:, 1, 0] - r[:, 0, 1]], 2),
    ]
    pick = np.argmax(np.stack([c[0] for c in cases], 1), axis=1)
    for k, (radicand, others, slot) in enumerate(cases):
        sel = pick == k
        if not sel.any():
            continue
        s = 2 * np.sqrt(np.maximum(radicand[sel], 1e-300))
        rest = [o[sel] / s for o in others(s)]
        cols = [c for c in range(4) if c != slot]
        q[np.ix_(sel, [slot])] = (s / 4)[:, None]
        q[np.ix_(sel, cols)] = np.stack(rest, 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, 3:] < 0, -q, q)


def decompose_many(ms: np.ndarray, label: Callable[[int], str] = lambda i: f"instance {i}"
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translations, quaternions [x, y, z, w], scales) with M = T · R · S for N×4×4 matrices;
    a mirror is a negative x scale. Errors (naming `label(i)` of the first bad one) on
    projective, singular or sheared matrices."""
    ms = np.asarray(ms, float).reshape(-1, 4, 4)
    first = lambda bad: int(np.argmax(bad))  # noqa: E731
    bad = np.abs(ms[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-6
    if bad.any():
        i = first(bad)
        raise UsdToolError(f"{label(i)}: projective matrix (last row {ms[i, 3].tolist()}), not an affine transform")
    a = ms[:, :3, :3]
    scale = np.linalg.norm(a, axis=1)  # column lengths
    det = np.linalg.det(a)
    bad = ~((scale > 1e-12).all(axis=1) & (np.abs(det) >= 1e-12 * np.prod(scale, axis=1)))
    if bad.any():
        raise UsdToolError(f"{label(first(bad))}: singular transform")
    scale[det < 0, 0] *= -1
    r = a / scale[:, None, :]
    bad = np.abs(np.einsum("nji,njk->nik", r, r) - np.eye(3)).max(axis=(1, 2)) > SHEAR_TOLERANCE
    if bad.any():
        raise UsdToolError(f"{label(first(bad))}: the transform has shear; only translation, rotation and scale "
                           f"can be instanced")
    return ms[:, :3, 3].copy(), quaternions_from_rotations(r), scale


def decompose(m: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One matrix's (translation, quaternion, scale) (see `decompose_many`)."""
    t, q, s = decompose_many(np.asarray(m)[None], lambda _: what)
    return t[0], q[0], s[0]


def _numbers(v: Any, n: int, what: str) -> list[float]:
    """`v` as n finite numbers, or an error naming `what`."""
    if not isinstance(v, list) or len(v) != n or not all(type(x) in (int, float) for x in v):
        raise UsdToolError(f"{what}: expected {n} numbers")
    if not all(math.isfinite(x) for x in v):
        raise UsdToolError(f"{what}: non-finite value")
    return v


def _instance_matrices(instances: list[dict[str, Any]]) -> np.ndarray:
    """Every instance's object-to-world matrix (N×4×4) from `matrix` or translation/rotation/
    scale; errors name the instance."""
    n = len(instances)
    ms = np.zeros((n, 4, 4))
    trs_rows, t, q, s = [], [], [], []
    for i, inst in enumerate(instances):
        what = f"instance {i}"
        if "matrix" in inst:
            if any(k in inst for k in ("translation", "rotation", "scale")):
                raise UsdToolError(f"{what}: give either matrix or translation/rotation/scale, not both")
            ms[i] = np.array(_numbers(inst["matrix"], 16, f"{what} matrix"), float).reshape(4, 4).T
        else:
            trs_rows.append(i)
            t.append(_numbers(inst.get("translation", [0, 0, 0]), 3, f"{what} translation"))
            q.append(_numbers(inst.get("rotation", [0, 0, 0, 1]), 4, f"{what} rotation"))
            s.append(_numbers(inst.get("scale", [1, 1, 1]), 3, f"{what} scale"))
    if trs_rows:
        q_ = np.array(q, float)
        norm = np.linalg.norm(q_, axis=1)
        bad = np.abs(norm - 1) > UNIT_TOLERANCE
        if bad.any():
            k = int(np.argmax(bad))
            raise UsdToolError(f"instance {trs_rows[k]} rotation: not a unit quaternion (length {norm[k]:g})")
        ms[trs_rows] = trs_matrices(np.array(t, float), q_ / norm[:, None], np.array(s, float))
    bad = np.abs(np.linalg.det(ms[:, :3, :3])) < 1e-12 if n else np.zeros(0, bool)
    if bad.any():
        raise UsdToolError(f"instance {int(np.argmax(bad))}: singular transform")
    return ms


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
        if not isinstance(inst, dict):
            raise UsdToolError(f"instance {i}: expected an object")
        if inst.get("asset") not in out.assets:
            raise UsdToolError(f"instance {i}: unknown asset {inst.get('asset')!r}")
    ms = _instance_matrices(instances)
    out.instances = [Instance(inst["asset"], m) for inst, m in zip(instances, ms)]
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
    if m.instances:
        ts, qs, ss = decompose_many(np.stack([inst.matrix for inst in m.instances]))
        for inst, t, q, s in zip(m.instances, _digits(ts), _digits(qs), _digits(ss)):
            instances.append({"asset": inst.asset, "translation": t, "rotation": q, "scale": s})
    return {"version": VERSION, "assets": assets, "instances": instances}


def _digits(v: np.ndarray) -> list[list[float]]:
    """Rows of values rounded to 8 significant digits: USD stores them as float32 (about 7), so
    the digits beyond are noise of the conversion."""
    return [[float(f"{x:.8g}") + 0.0 for x in row] for row in v.tolist()]  # + 0.0: no -0.0


def dumps(doc: dict[str, Any]) -> str:
    """Manifest JSON with one line per instance."""
    head = {k: v for k, v in doc.items() if k != "instances"}
    text = json.dumps(head, indent=2)[:-2]
    rows = ",\n".join("    " + json.dumps(i) for i in doc["instances"])
    return f'{text},\n  "instances": [\n{rows}\n  ]\n}}\n'

