"""Independent check of `aggtool reference` against Mitsuba 3.

Both renderers see the same generated scene (Lambertian materials: KHR_materials_specular
specularFactor 0 and metallic 0, so that aggtool's model reduces exactly to Mitsuba's
`diffuse`), the same camera, the same equirectangular environment map (Mitsuba's own
convention) and the same sun, with direct illumination only (`direct` integrator, box filter).

Threshold. Each renderer is run twice with different seeds; for two unbiased estimates of the
same image, E[RMSE(a, b)^2] = var_a + var_b, so the noise floor of a cross comparison is
sqrt((RMSE(ours, ours')^2 + RMSE(mi, mi')^2) / 2). We require RMSE(ours, mitsuba) below 1.2 times
that floor (the RMSE over 12k channel values has ~1% relative spread, the rest is margin for
pixels where the two ray tracers' f32 edge tests differ), and the mean radiance to agree within
0.5% (about 4 standard errors of the mean at this size and spp: a bias check far tighter
than the noise of a single pixel).
"""

import json
import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
mi.set_variant("scalar_rgb")

from aggtool_cli import find_aggtool, run

AGGTOOL = find_aggtool()

SIZE = 48
SPP = 256


def aggtool(*args, cwd):
    return run(*args, cwd=cwd)


def write_envmap(path):
    """A 64x32 sky: blue gradient, a dark ground and a bright patch (~2000:1)."""
    h, w = 32, 64
    img = np.zeros((h, w, 3), dtype=np.float32)
    for y in range(h):
        t = y / (h - 1)
        sky = np.array([0.3, 0.5, 1.0]) * (1.2 - t) if t < 0.5 else np.array([0.15, 0.12, 0.1])
        img[y, :, :] = sky
    img[6:9, 40:44, :] = [60.0, 55.0, 40.0]
    mi.Bitmap(img).write(str(path))


def look_at(cam):
    return mi.ScalarTransform4f().look_at(origin=cam["eye"], target=cam["target"], up=cam["up"])


def render_mitsuba(flat_dir, view, seed):
    cam = view["camera"]
    env = view["environment"]
    sun = view["sun"]
    scene = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {
            "type": "perspective",
            "fov": cam["fov_y_deg"],
            "fov_axis": "y",
            "to_world": look_at(cam),
            "film": {"type": "hdrfilm", "width": cam["width"], "height": cam["height"],
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": view["spp"], "seed": seed},
        },
        "env": {"type": "envmap", "filename": env["path"], "scale": env["intensity"],
                "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], env["rotation_deg"])},
        "sun": {"type": "directional", "direction": [-c for c in sun["direction"]],
                "irradiance": {"type": "rgb", "value": [sun["irradiance"]] * 3}},
    }
    for i, m in enumerate(json.loads((flat_dir / "materials.json").read_text())):
        scene[f"shape{i}"] = {
            "type": "obj",
            "filename": str(flat_dir / m["file"]),
            "bsdf": {"type": "twosided", "material": {"type": "diffuse",
                     "reflectance": {"type": "rgb", "value": m["base_color"]}}},
        }
    img = mi.render(mi.load_dict(scene), spp=view["spp"], seed=seed)
    return np.array(img, dtype=np.float64)[:, :, :3]


def read_exr(path):
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)[:, :, :3]


def rmse(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)))


@pytest.mark.parametrize("name,eye,target", [
    ("buildings", [0.9, 0.9, 1.3], [0.0, 0.15, 0.0]),
    ("displaced-sphere", [0.4, 0.5, 1.8], [0.0, 0.0, 0.0]),
])
def test_matches_mitsuba(name, eye, target):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        aggtool("gen", name, "-o", tmp, "--triangles", 6000, "--lambertian", cwd=tmp)
        asset = tmp / f"{name}.glb"
        aggtool("flatten", asset, "-o", tmp / "flat", cwd=tmp)
        write_envmap(tmp / "sky.exr")
        view = {
            "version": 1,
            "camera": {"eye": eye, "target": target, "up": [0, 1, 0], "fov_y_deg": 40,
                       "width": SIZE, "height": SIZE},
            "environment": {"path": str(tmp / "sky.exr"), "intensity": 1.5, "rotation_deg": 30},
            "sun": {"direction": [0.5, 0.8, 0.3], "irradiance": 2.0},
            "spp": SPP,
            "seed": 1,
        }
        (tmp / "view.json").write_text(json.dumps(view))
        ours = []
        for seed in (1, 2):
            aggtool("reference", asset, "--view", "view.json", "--seed", seed, "-o", f"ours{seed}.exr", cwd=tmp)
            ours.append(read_exr(tmp / f"ours{seed}.exr"))
        theirs = [render_mitsuba(tmp / "flat", view, seed) for seed in (1, 2)]
        floor = np.sqrt((rmse(*ours) ** 2 + rmse(*theirs) ** 2) / 2)
        cross = rmse(ours[0], theirs[0])
        mean_ours, mean_theirs = ours[0].mean(), theirs[0].mean()
        print(f"{name}: rmse(ours, mitsuba) {cross:.5f}, noise floor {floor:.5f}, "
              f"means {mean_ours:.5f} / {mean_theirs:.5f}")
        assert mean_theirs > 0.01, "the scene is lit"
        assert abs(mean_ours - mean_theirs) / mean_theirs < 0.005
        assert cross < 1.2 * floor
