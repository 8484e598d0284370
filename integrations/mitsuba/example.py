"""Renders a tree beside a ground mesh twice with Mitsuba 3: as an aggtool aggregate through
the `aggtool_lod` integrator, and as its own triangle mesh through Mitsuba's `direct`
integrator, under the same environment map and directional emitter; writes both side by side
(LoD left, mesh right) as an EXR and a PNG and prints their relative RMSE and times.

    python3 integrations/mitsuba/example.py [--variant scalar_rgb|llvm_ad_rgb] [--size 128]
        [--spp 16] [--triangles 20000] [--max-res 32] [-o mitsuba-tree]

It runs `aggtool gen foliage` and `aggtool convert` (the `aggtool` on PATH, or target/release)
into the output folder first. tests/python/test_mitsuba_host.py uses the functions here.
"""
from __future__ import annotations

import argparse
import json
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

# Where the camera, the sun and the tree sit (the view file's conventions: y up, the sun's
# direction points towards the sun).
EYE, TARGET = [1.6, 0.9, 2.2], [0.0, 0.45, 0.0]
SUN_DIRECTION, SUN_IRRADIANCE = [0.6, 0.7, 0.35], 2.5
TREE_TO_WORLD = dict(translate=[0.1, 0.0, -0.1], rotate_y=30.0)

_GL = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def find_aggtool() -> str:
    for c in (ROOT / "target" / "release" / "aggtool", shutil.which("aggtool")):
        if c and Path(c).exists():
            return str(c)
    sys.exit("aggtool not found: cargo build --release -p aggtool")


def make_tree(folder: Path, aggtool: str, triangles=2000, max_res=16) -> tuple[Path, Path]:
    """`aggtool gen foliage` (Lambertian, so Mitsuba's `diffuse` is the same material) and a
    tiny bake of it. Returns (glb, agg)."""
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run([aggtool, "gen", "foliage", "-o", str(folder), "--triangles", str(triangles),
                    "--lambertian"], check=True, capture_output=True)
    glb = folder / "foliage.glb"
    subprocess.run([aggtool, "convert", str(glb), "--max-res", str(max_res), "--min-res", "4",
                    "--samples", "8", "--aiv-res", "8", "--aiv-rays", "4", "--abv-res", "8",
                    "--abv-full-res", "8"], check=True, capture_output=True)
    return glb, folder / "foliage.agg"


def _read_glb(path: Path):
    data = path.read_bytes()
    if data[:4] != b"glTF":
        raise ValueError(f"{path}: not a GLB file")
    n = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + n])
    m = struct.unpack_from("<I", data, 20 + n)[0]
    return gltf, data[28 + n:28 + n + m]


def _accessor(gltf, binary, i):
    acc = gltf["accessors"][i]
    view = gltf["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(_GL[acc["componentType"]])
    width = _WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", dtype.itemsize * width)
    a = np.ndarray((acc["count"], width), dtype, binary, start, (stride, dtype.itemsize))
    return a.copy()


def write_ply(path: Path, pos, nrm, uv, faces):
    """A binary little-endian PLY that Mitsuba's `ply` shape reads (positions, normals, uv)."""
    v = np.concatenate([pos, nrm, uv], axis=1).astype("<f4")
    f = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<u4", (3,))])
    f["n"], f["i"] = 3, faces
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property float nx\nproperty float ny\nproperty float nz\n"
            "property float u\nproperty float v\n"
            f"element face {len(f)}\nproperty list uchar uint vertex_indices\nend_header\n")
    path.write_bytes(head.encode() + v.tobytes() + f.tobytes())


def _bilinear(img, uv):
    """glTF texture lookup (uv (0, 0) at the image's top left, clamped), bilinear."""
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)


def cut_out(pos, nrm, uv, faces, alpha, cutoff, k=16):
    """Alpha cut-outs as geometry: each triangle split into k² sub-triangles on a barycentric
    grid, those whose centre's alpha is below the cut-off dropped. Mitsuba's `direct` cannot
    take the cut-outs as a `mask` BSDF: its shadow rays (`ray_test`) see masked surfaces as
    opaque and its camera rays stop at them, which rendered the foliage ~20% darker than
    `aggtool reference`."""
    ij = np.array([(i, j) for i in range(k) for j in range(k - i)], np.float64)
    up = np.stack([ij, ij + [1, 0], ij + [0, 1]], axis=1)            # (U, 3, 2)
    dn = ij[ij.sum(axis=1) < k - 1]
    dn = np.stack([dn + [1, 0], dn + [1, 1], dn + [0, 1]], axis=1)
    sub = np.concatenate([up, dn]) / k                                # (S, 3, 2) barycentric
    w = np.concatenate([1 - sub.sum(axis=2, keepdims=True), sub], axis=2)  # (S, 3, 3)

    def lerp(attr):
        a = attr[faces]                                               # (F, 3, C)
        return np.einsum("svc,fcd->fsvd", w, a)                       # (F, S, 3, C)

    P, N, T = lerp(pos), lerp(nrm), lerp(uv)
    keep = _bilinear(alpha, T.mean(axis=2).reshape(-1, 2))[:, 0] >= cutoff
    P, N, T = (x.reshape(-1, 3, x.shape[-1])[keep].reshape(-1, x.shape[-1]) for x in (P, N, T))
    return P, N, T, np.arange(len(P), dtype=np.uint32).reshape(-1, 3)


def glb_shapes(mi, glb: Path, folder: Path, to_world=None, cut=True) -> dict:
    """The GLB's triangle meshes as Mitsuba shapes (PLY files in `folder`), each with a
    two-sided `diffuse` of its base colour (texture × factor, sRGB decoded), alphaMode MASK
    cut out of the geometry ([`cut_out`]): what aggtool's Lambertian model reduces to; with
    `cut=False` the leaves stay whole, opaque quads (a cut-out 1M-triangle tree needs more
    than 23 GB). Node transforms are not read (aggtool gen writes none)."""
    gltf, binary = _read_glb(glb)
    textures = {}
    shapes = {}
    for mi_idx, mesh in enumerate(gltf["meshes"]):
        for pi, prim in enumerate(mesh["primitives"]):
            at = prim["attributes"]
            pos = _accessor(gltf, binary, at["POSITION"])
            nrm = _accessor(gltf, binary, at["NORMAL"])
            uv = (_accessor(gltf, binary, at["TEXCOORD_0"]) if "TEXCOORD_0" in at
                  else np.zeros((len(pos), 2), np.float32))
            faces = _accessor(gltf, binary, prim["indices"]).reshape(-1, 3).astype(np.uint32)
            name = f"mesh{mi_idx}_{pi}"
            mat = gltf["materials"][prim.get("material", 0)]
            pbr = mat.get("pbrMetallicRoughness", {})
            factor = np.array(pbr.get("baseColorFactor", [1, 1, 1, 1]), np.float32)
            tex = pbr.get("baseColorTexture")
            if tex is None:
                refl = {"type": "rgb", "value": factor[:3].tolist()}
            else:
                src = gltf["textures"][tex["index"]]["source"]
                if src not in textures:
                    img = gltf["images"][src]
                    view = gltf["bufferViews"][img["bufferView"]]
                    o = view.get("byteOffset", 0)
                    png = folder / f"image{src}.png"
                    png.write_bytes(binary[o:o + view["byteLength"]])
                    bmp = mi.Bitmap(str(png)).convert(mi.Bitmap.PixelFormat.RGBA,
                                                      mi.Struct.Type.Float32, srgb_gamma=False)
                    textures[src] = np.array(bmp)
                rgba = textures[src] * factor
                refl = {"type": "bitmap", "raw": True,
                        "bitmap": mi.Bitmap(np.ascontiguousarray(rgba[..., :3]))}
                if cut and mat.get("alphaMode") == "MASK":
                    pos, nrm, uv, faces = cut_out(pos, nrm, uv, faces, rgba[..., 3:4],
                                                  mat.get("alphaCutoff", 0.5))
            write_ply(folder / f"{name}.ply", pos, nrm, uv, faces)
            bsdf = {"type": "twosided", "material": {"type": "diffuse", "reflectance": refl}}
            shape = {"type": "ply", "filename": str(folder / f"{name}.ply"), "bsdf": bsdf,
                     "face_normals": False}
            if to_world is not None:
                shape["to_world"] = to_world
            shapes[name] = shape
    return shapes


def sky(mi, path: Path):
    """A 64×32 equirectangular sky: a blue gradient above, a dark ground below, a bright patch."""
    h, w = 32, 64
    img = np.zeros((h, w, 3), np.float32)
    for y in range(h):
        t = y / (h - 1)
        img[y] = np.array([0.3, 0.5, 1.0]) * (1.2 - t) if t < 0.5 else [0.15, 0.12, 0.1]
    img[6:9, 40:44] = [20.0, 18.0, 14.0]
    mi.Bitmap(img).write(str(path))


def tree_to_world(mi):
    return (mi.ScalarTransform4f().translate(TREE_TO_WORLD["translate"])
            @ mi.ScalarTransform4f().rotate([0, 1, 0], TREE_TO_WORLD["rotate_y"]))


def scene_dict(mi, folder: Path, integrator: dict, size: int, spp: int, extra=None) -> dict:
    """Camera, ground (a 2.4 × 2.4 grey square at y = 0), environment map and directional
    emitter; `extra` adds shapes (the tree's mesh for the reference)."""
    if not (folder / "sky.exr").exists():
        sky(mi, folder / "sky.exr")
    d = {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective", "fov": 40.0, "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(origin=EYE, target=TARGET, up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": size, "height": size,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "env": {"type": "envmap", "filename": str(folder / "sky.exr"), "scale": 1.0},
        "sun": {"type": "directional", "direction": [-c for c in SUN_DIRECTION],
                "irradiance": {"type": "rgb", "value": [SUN_IRRADIANCE] * 3}},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(1.2),
                   "bsdf": {"type": "diffuse",
                            "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.45]}}},
    }
    d.update(extra or {})
    return d


def render_pair(mi, folder: Path, glb: Path, agg: Path, size: int, spp: int, seed=1):
    """(LoD image, mesh image, LoD seconds, mesh seconds): the tree as an aggregate through
    aggtool_lod, and as its mesh through Mitsuba's `direct`."""
    import aggtool_mitsuba
    aggtool_mitsuba.register()
    lod = mi.load_dict(scene_dict(mi, folder, {"type": "aggtool_lod", "agg_tree": str(agg),
                                               "agg_tree_to_world": tree_to_world(mi)},
                                  size, spp))
    t0 = time.perf_counter()
    a = np.array(mi.render(lod, spp=spp, seed=seed), np.float64)[..., :3]
    t1 = time.perf_counter()
    ref = mi.load_dict(scene_dict(mi, folder, {"type": "direct"}, size, spp,
                                  glb_shapes(mi, glb, folder, tree_to_world(mi))))
    t2 = time.perf_counter()
    b = np.array(mi.render(ref, spp=spp, seed=seed), np.float64)[..., :3]
    t3 = time.perf_counter()
    return a, b, t1 - t0, t3 - t2


def relative_rmse(a, b):
    """RMSE relative to the reference's mean: sqrt(mean((a - b)²)) / mean(b)."""
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.mean(b))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", default="scalar_rgb")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--triangles", type=int, default=20000)
    ap.add_argument("--max-res", type=int, default=32, help="the bake's finest level")
    ap.add_argument("-o", "--output", type=Path, default=Path("mitsuba-tree"))
    args = ap.parse_args()
    import mitsuba as mi
    mi.set_variant(args.variant)
    sys.path.insert(0, str(Path(__file__).parent))
    glb, agg = make_tree(args.output, find_aggtool(), args.triangles, args.max_res)
    a, b, ta, tb = render_pair(mi, args.output, glb, agg, args.size, args.spp)
    side = np.concatenate([a, b], axis=1).astype(np.float32)
    mi.Bitmap(side).write(str(args.output / "side-by-side.exr"))
    png = mi.Bitmap(side).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    png.write(str(args.output / "side-by-side.png"))
    print(f"{args.variant} {args.size}² {args.spp} spp: aggtool_lod {ta:.2f} s, direct on the "
          f"mesh {tb:.2f} s, relative RMSE {relative_rmse(a, b):.4f}, means "
          f"{a.mean():.4f} / {b.mean():.4f}")
    print(f"wrote {args.output / 'side-by-side.exr'} and {args.output / 'side-by-side.png'} "
          f"(left: aggregate, right: mesh)")


if __name__ == "__main__":
    main()
