"""The Mitsuba host against Mitsuba's own `direct` on the mesh, timed as the runtime issue
asks: each integrator in a process of its own (Mitsuba's virtual calls dispatch over every
shape and BSDF loaded in the process, so one scene's kernels grow with the other's: the
forest's mesh kernel had 21,152 operations beside the instanced trees and 1,927 alone), after
a warm-up render there (its kernels compiled); two processes each, alternating, two renders in
each, the medians' ratio.

    python3 integrations/mitsuba/bench.py tree [--triangles 200000] [--max-res 64]
        [--size 256] [--spp 64] [-o bench-tree]
    python3 integrations/mitsuba/bench.py forest --glb foliage.glb --agg foliage.agg
        [--size 128] [--spp 16] [-o bench-forest]

`tree`: example.py's scene (a generated Lambertian foliage tree beside a ground, its bake made
first). `forest`: 100 instances of the given tree on a 10 × 10 grid one unit apart, instance k
turned by 37·k degrees, seen from (9, 7, 11): the manifest (written into the output folder)
through `aggtool_lod`, the mesh once in a `shapegroup` with 100 `instance`s through `direct`.
The forest's leaves are opaque quads for `direct` (cut-out geometry of a 1M-triangle tree
needs more than 23 GB), which makes its time a lower bound for the real tree.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import example  # noqa: E402


def timed(mi, scene, spp: int, runs=2) -> list:
    """Seconds of `runs` renders of `scene` after a warm-up render."""
    np.array(mi.render(scene, spp=spp, seed=0))
    t = []
    for r in range(runs):
        t0 = time.perf_counter()
        np.array(mi.render(scene, spp=spp, seed=1 + r))
        t.append(time.perf_counter() - t0)
    return t


def forest_scene(mi, folder: Path, glb: Path, agg: Path, size: int, spp: int, only: str):
    inst, xf = [], []
    for k in range(100):
        i, j = k % 10, k // 10
        th = math.radians(37 * k)
        inst.append({"asset": "tree", "translation": [i - 4.5, 0, j - 4.5],
                     "rotation": [0, math.sin(th / 2), 0, math.cos(th / 2)]})
        xf.append(mi.ScalarTransform4f().translate([i - 4.5, 0, j - 4.5])
                  @ mi.ScalarTransform4f().rotate([0, 1, 0], 37 * k))
    manifest = folder / "forest100.json"
    manifest.write_text(json.dumps({"version": 1, "assets": {"tree": {
        "source": str(glb.resolve()), "aggregate": str(agg.resolve())}}, "instances": inst}))

    def scene(integrator, extra=None):
        d = example.scene_dict(mi, folder, integrator, size, spp, extra)
        d["sensor"]["to_world"] = mi.ScalarTransform4f().look_at(
            origin=[9, 7, 11], target=[0, 0.3, 0], up=[0, 1, 0])
        d["ground"]["to_world"] = mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(8.0)
        return d

    if only == "aggtool_lod":
        return mi.load_dict(scene({"type": "aggtool_lod", "agg_forest": str(manifest)}))
    shapes = example.glb_shapes(mi, glb, folder, None, cut=False)
    extra = {"trees": {"type": "shapegroup", **shapes}}
    for k, t in enumerate(xf):
        extra[f"tree{k}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": "trees"},
                             "to_world": t}
    return mi.load_dict(scene({"type": "direct"}, extra))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=["tree", "forest"])
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--size", type=int)
    ap.add_argument("--spp", type=int)
    ap.add_argument("--triangles", type=int, default=200000)
    ap.add_argument("--max-res", type=int, default=64)
    ap.add_argument("--glb", type=Path)
    ap.add_argument("--agg", type=Path)
    ap.add_argument("-o", "--output", type=Path)
    # Internal: render one integrator's scene in this process and print its times as JSON.
    ap.add_argument("--only", choices=["aggtool_lod", "direct"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    out = args.output or Path(f"bench-{args.what}")
    out.mkdir(parents=True, exist_ok=True)
    if args.what == "tree":
        size, spp = args.size or 256, args.spp or 64
    else:
        if not (args.glb and args.agg):
            sys.exit("forest: give --glb TREE.glb and --agg TREE.agg")
        size, spp = args.size or 128, args.spp or 16
    if args.only is None:
        if args.what == "tree":
            glb, agg = example.make_tree(out, example.find_aggtool(), args.triangles,
                                         args.max_res)
            given = ["--glb", str(glb), "--agg", str(agg)]
        else:
            given = []
        t = {"aggtool_lod": [], "direct": []}
        for _ in range(2):
            for k in t:
                r = subprocess.run([sys.executable, __file__, *sys.argv[1:], *given, "--only", k],
                                   check=True, capture_output=True, text=True)
                t[k] += json.loads(r.stdout.strip().splitlines()[-1])
        for k, v in t.items():
            print(f"{k}: " + " ".join(f"{x:.3f}" for x in v) + " s")
        print(f"{args.what}, {size}², {spp} spp: aggtool_lod / direct = "
              f"{np.median(t['aggtool_lod']) / np.median(t['direct']):.2f} (medians)")
        return
    import mitsuba as mi
    mi.set_variant(args.variant)
    import aggtool_mitsuba
    aggtool_mitsuba.register()
    if args.what == "tree":
        if args.only == "aggtool_lod":
            scene = mi.load_dict(example.scene_dict(
                mi, out, {"type": "aggtool_lod", "agg_tree": str(args.agg),
                          "agg_tree_to_world": example.tree_to_world(mi)}, size, spp))
        else:
            scene = mi.load_dict(example.scene_dict(
                mi, out, {"type": "direct"}, size, spp,
                example.glb_shapes(mi, args.glb, out, example.tree_to_world(mi))))
    else:
        scene = forest_scene(mi, out, args.glb, args.agg, size, spp, args.only)
    print(json.dumps(timed(mi, scene, spp)))


if __name__ == "__main__":
    main()
