"""The Blender side of tests/python/test_blender.py, run by a Python that has the `bpy` module
(a subprocess: bpy is heavy, pins numpy < 2 and imports once per process):

    python blender_session.py EXTENSION.zip AGGTOOL MODULE_DIR WORK_DIR RESULT.json

It installs the built extension under $BLENDER_USER_RESOURCES (set by the caller to a temporary
folder) with Blender's own `extensions.package_install_files`, builds a small scene, runs both
operators headless, each bad input and a bake with every preset (the tool's, read by the
extension), and writes what it measured to RESULT.json; the checks
are in test_blender.py. An exception in one part is recorded and the next part still runs."""
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import bpy
import numpy as np
from bpy_extras.object_utils import world_to_camera_view
from mathutils import Matrix, Vector

ZIP, AGGTOOL, MODULE_DIR, WORK, RESULT = sys.argv[1:6]
WORK = Path(WORK)
result = {"errors": {}}
#: Settings of the tiny bakes (COMMON.md): the checks are about geometry and plumbing.
TINY = dict(max_res=16, samples=8, aiv_res=8, aiv_rays=4, abv_res=8, abv_full_res=8)
#: Preview size: not square, so that an aspect-ratio mistake shows.
WIDTH, HEIGHT = 64, 48


def part(name):
    """Runs a part of the session, recording its exception instead of stopping."""
    def wrap(fn):
        try:
            fn()
        except Exception:
            result["errors"][name] = traceback.format_exc()
        return fn
    return wrap


def op_error(call):
    """The message of an operator that reports an error (bpy raises RuntimeError), or None."""
    try:
        call()
    except RuntimeError as e:
        return str(e)
    return None


def select(objects, active=None):
    for o in bpy.context.view_layer.objects:
        o.select_set(o in objects)
    bpy.context.view_layer.objects.active = active or (objects[0] if objects else None)


def files_under(folder):
    return sorted(str(p.relative_to(WORK)) for p in Path(folder).rglob("*")) \
        if Path(folder).exists() else []


# -- install --------------------------------------------------------------------------------
for o in list(bpy.data.objects):  # the startup scene's cube, light and camera
    bpy.data.objects.remove(o)
r = bpy.ops.extensions.package_install_files(filepath=ZIP, repo="user_default",
                                             enable_on_install=True)
ext = sys.modules["bl_ext.user_default.aggtool_lod"]
result["install"] = {
    "result": sorted(r),
    "user_resources": bpy.utils.resource_path("USER"),
    "module": ext.__name__,
    "module_file": ext.__file__,
    "enabled": "bl_ext.user_default.aggtool_lod" in bpy.context.preferences.addons,
    "operators": [hasattr(bpy.ops.aggtool, n) for n in ("bake_aggregate", "render_preview")],
    "panel_category": bpy.types.AGGTOOL_PT_panel.bl_category,
    "background": bpy.app.background,
    "blender": bpy.app.version_string,
}
prefs = bpy.context.preferences.addons["bl_ext.user_default.aggtool_lod"].preferences
prefs.aggtool_path = AGGTOOL
prefs.module_path = MODULE_DIR
os.environ.pop("AGGTOOL", None)

# -- scene: three boxes, none symmetric to another about any axis ----------------------------
scene = bpy.context.scene
scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
scene.render.resolution_percentage = 100
scene.render.film_transparent = True
world = bpy.data.worlds.new("aggtool test world")
world.color = (0.9, 0.9, 0.9)  # the viewport colour; the Background node's comes first
background = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
background.inputs[0].default_value = (0.1, 0.15, 0.2, 1.0)
background.inputs[1].default_value = 2.0
scene.world = world


def box(name, location, scale, rotation_z_deg):
    mesh = bpy.data.meshes.new(name)
    v = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh.from_pydata(v, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.location, obj.scale = location, scale
    obj.rotation_euler = (0.0, 0.0, math.radians(rotation_z_deg))
    scene.collection.objects.link(obj)
    return obj


#: Away from the origin, about which a Z-up/Y-up mix-up turns the picture.
CENTRE = Vector((0.5, 1.5, 0.8))
base = box("Base", CENTRE + Vector((0.0, 0.0, 0.0)), (1.6, 0.8, 0.2), 0)
tower = box("Tower", CENTRE + Vector((1.0, 0.4, 1.0)), (0.25, 0.25, 0.9), 30)
block = box("Block", CENTRE + Vector((-0.9, -0.4, 0.5)), (0.35, 0.35, 0.3), 20)
boxes = [base, tower, block]
empty = bpy.data.objects.new("Marker", None)
scene.collection.objects.link(empty)
cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
scene.collection.objects.link(cam)
cam.location = CENTRE + Vector((5.0, -6.0, 4.0))
cam.rotation_euler = (CENTRE + Vector((0, 0, 0.3)) - cam.location).to_track_quat("-Z", "Y").to_euler()
cam.data.angle = math.radians(35)
scene.camera = cam
sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
sun.data.energy = 3.0
sun.rotation_euler = (math.radians(40), 0.0, math.radians(30))
scene.collection.objects.link(sun)
bpy.context.view_layer.update()


def gltf_bounds(objects):
    """The objects' world-space bounds after the exporter's Z-up -> Y-up: (x, z, -y)."""
    pts = np.array([tuple(o.matrix_world @ v.co) for o in objects for v in o.data.vertices])
    pts = np.stack([pts[:, 0], pts[:, 2], -pts[:, 1]], 1)
    return [pts.min(0).tolist(), pts.max(0).tolist()]


def projected_mask(objects, samples_per_edge=96):
    """Pixels the objects cover, from points spread over every face and projected with
    Blender's own world_to_camera_view (independent of the extension's ray generation);
    rows from the bottom, as Blender stores images."""
    mask = np.zeros((HEIGHT, WIDTH), bool)
    t = (np.arange(samples_per_edge) + 0.5) / samples_per_edge
    for o in objects:
        m = o.matrix_world
        for poly in o.data.polygons:
            a, b, c, d = (o.data.vertices[i].co for i in poly.vertices)
            for s in t:
                for u in t:
                    p = m @ ((a * (1 - s) + b * s) * (1 - u) + (d * (1 - s) + c * s) * u)
                    q = world_to_camera_view(scene, cam, p)
                    x, y = int(q.x * WIDTH), int(q.y * HEIGHT)
                    if 0 <= x < WIDTH and 0 <= y < HEIGHT and q.z > 0:
                        mask[y, x] = True
    return mask


def preview_pixels(name="aggtool preview"):
    img = bpy.data.images[name]
    px = np.empty(len(img.pixels), np.float32)
    img.pixels.foreach_get(px)
    return img, px.reshape(img.size[1], img.size[0], 4)


def compare_masks(alpha, mask):
    ours = alpha > 0.5
    inter, union = np.logical_and(ours, mask).sum(), np.logical_or(ours, mask).sum()
    cy = lambda m: np.argwhere(m).mean(0).tolist() if m.any() else [float("nan")] * 2  # noqa
    return {"iou": float(inter / max(union, 1)), "ours_pixels": int(ours.sum()),
            "mask_pixels": int(mask.sum()), "ours_centroid": cy(ours), "mask_centroid": cy(mask)}


@part("bake")
def bake():
    select(boxes + [empty], active=base)
    out = WORK / "bakes" / "scene.agg"
    t0 = time.perf_counter()
    r = bpy.ops.aggtool.bake_aggregate(preset="draft", filepath=str(out), **TINY)
    result["bake"] = {
        "result": sorted(r),
        "seconds": time.perf_counter() - t0,
        "command": ext.last_bake["command"],
        "progress": ext.last_bake["progress"],
        "parsed": ext.last_bake["parsed"],
        "sidecars": {o.name: o.get("aggtool_sidecar") for o in boxes + [empty]},
        "bake_matrix": list(base.get("aggtool_bake_matrix", [])),
        "matrix_world": [v for row in base.matrix_world for v in row],
        "files": files_under(WORK / "bakes"),
        "expected_bounds": gltf_bounds(boxes),
    }
    # The panel: the preset menu and its values are the tool's; a ticked setting starts from
    # the preset's value and is the only one passed to the operator.
    s = scene.aggtool
    result["panel_menu"] = [item[0] for item in ext._preset_items(s, bpy.context)]
    s.preset = "high"
    s.override_max_res = True
    result["panel_override_start"] = s.max_res
    s.max_res = 32
    result["panel_settings"] = {k: list(v) for k, v in ext.panel_settings(bpy.context, s).items()}
    result["panel_operator_args"] = ext.panel_operator_args(s)
    s.override_max_res = False
    s.preset = "default"


@part("preview")
def preview():
    select([base])
    t0 = time.perf_counter()
    bpy.ops.aggtool.render_preview(samples=8)
    seconds = time.perf_counter() - t0
    img, px = preview_pixels()
    result["preview"] = {"size": list(img.size), "is_float": img.is_float, "seconds": seconds,
                         "finite": bool(np.isfinite(px).all()),
                         "covered_mean_rgb": px[px[..., 3] > 0.5, :3].mean(0).tolist(),
                         **compare_masks(px[..., 3], projected_mask(boxes))}
    # Every box moved and turned by the same world transform: the preview, which follows the
    # active object's transform since the bake, must follow them.
    delta = Matrix.Translation((1.0, -0.8, 0.5)) @ Matrix.Rotation(math.radians(50), 4, "Z")
    for o in boxes:
        o.matrix_world = delta @ o.matrix_world
    bpy.context.view_layer.update()
    bpy.ops.aggtool.render_preview(samples=8)
    _, px = preview_pixels()
    result["preview_moved"] = compare_masks(px[..., 3], projected_mask(boxes))
    # The same picture against the boxes where they were: it must have moved away from it.
    for o in boxes:
        o.matrix_world = delta.inverted() @ o.matrix_world
    bpy.context.view_layer.update()
    result["preview_moved"]["iou_with_unmoved"] = compare_masks(px[..., 3],
                                                                projected_mask(boxes))["iou"]
    # Negative control: the same preview without the exporter's Z-up -> Y-up conversion.
    conversion = ext.BLENDER_TO_GLTF
    ext.BLENDER_TO_GLTF = Matrix.Identity(4)
    try:
        bpy.ops.aggtool.render_preview(samples=2)
    finally:
        ext.BLENDER_TO_GLTF = conversion
    _, px = preview_pixels()
    result["preview_z_up"] = compare_masks(px[..., 3], projected_mask(boxes))
    # Opaque film: alpha 1, and the background is the world colour.
    scene.render.film_transparent = False
    bpy.ops.aggtool.render_preview(samples=2)
    _, px = preview_pixels()
    result["preview_opaque"] = {"alpha_min": float(px[..., 3].min()),
                                "corner_rgb": px[0, 0, :3].tolist()}
    scene.render.film_transparent = True
    # The screenshot of the README: the image written as a PNG.
    img = bpy.data.images["aggtool preview"]
    img.file_format = "PNG"
    img.save(filepath=str(WORK / "preview.png"))
    result["preview_png"] = str(WORK / "preview.png")


@part("preview_vs_render")
def preview_vs_render():
    """The opaque preview as a PFM, and the same view as a view file for `aggtool render` in
    the aggregate's (glTF's) space, built from the camera's position, forward axis and field
    of view rather than the extension's ray generation; test_blender.py renders and compares."""
    select([base])
    scene.render.film_transparent = False
    try:
        bpy.ops.aggtool.render_preview(samples=128, seed=5)
    finally:
        scene.render.film_transparent = True
    _, px = preview_pixels()
    with open(WORK / "preview.pfm", "wb") as f:  # PFM rows run bottom-up, as Blender's do
        f.write(f"PF\n{WIDTH} {HEIGHT}\n-1.0\n".encode())
        f.write(np.ascontiguousarray(px[..., :3], dtype="<f4").tobytes())
    y_up = lambda v: [v.x, v.z, -v.y]  # noqa: E731 (the exporter's Z-up -> Y-up)
    forward = cam.matrix_world.to_3x3() @ Vector((0.0, 0.0, -1.0))
    # Sensor fit AUTO on a landscape image: `angle` is the horizontal field of view.
    fov_y = 2 * math.degrees(math.atan(math.tan(cam.data.angle / 2) * HEIGHT / WIDTH))
    towards_sun = sun.matrix_world.to_3x3() @ Vector((0.0, 0.0, 1.0))
    view = {"version": 1, "camera": {"eye": y_up(cam.location), "target": y_up(cam.location + forward),
                                     "fov_y_deg": fov_y, "width": WIDTH, "height": HEIGHT},
            "environment": {"constant": [0.2, 0.3, 0.4]},
            "sun": {"direction": y_up(towards_sun), "irradiance": [3.0, 3.0, 3.0]}, "spp": 128}
    (WORK / "view.json").write_text(json.dumps(view))
    result["preview_vs_render"] = {"pfm": str(WORK / "preview.pfm"), "view": str(WORK / "view.json"),
                                   "agg": str(bpy.path.abspath(base["aggtool_sidecar"]))}


@part("bad_input")
def bad_input():
    bad = {}
    out = WORK / "bad"
    # 1. Nothing exportable: a camera and an empty.
    select([cam, empty], active=empty)
    bad["no_mesh"] = op_error(lambda: bpy.ops.aggtool.bake_aggregate(
        preset="draft", filepath=str(out / "none.agg"), **TINY))
    # 2. The binary: a preference naming a missing file; then none anywhere.
    select([base])
    prefs.aggtool_path = str(WORK / "no" / "aggtool")
    bad["binary_pref_missing"] = op_error(lambda: bpy.ops.aggtool.bake_aggregate(
        preset="draft", filepath=str(out / "nobin.agg"), **TINY))
    prefs.aggtool_path = ""
    path = os.environ.get("PATH", "")
    os.environ["PATH"] = str(WORK / "empty-path")
    bad["binary_none"] = op_error(lambda: bpy.ops.aggtool.bake_aggregate(
        preset="draft", filepath=str(out / "nobin.agg"), **TINY))
    os.environ["PATH"] = path
    # 3. Settings the command line refuses: its own error, nothing written.
    prefs.aggtool_path = AGGTOOL
    bad["bad_setting"] = op_error(lambda: bpy.ops.aggtool.bake_aggregate(
        preset="draft", filepath=str(out / "badres.agg"), **dict(TINY, max_res=7)))
    # 4. A preset the tool does not have: refused before anything is exported.
    bad["unknown_preset"] = op_error(lambda: bpy.ops.aggtool.bake_aggregate(
        preset="fast", filepath=str(out / "fast.agg"), **TINY))
    # 5. The preview: an object never baked, a sidecar whose file is gone, a module folder
    #    that does not exist.
    plain = box("Plain", (0, 3, 0), (0.2, 0.2, 0.2), 0)
    select([plain])
    bad["preview_no_sidecar"] = op_error(lambda: bpy.ops.aggtool.render_preview(samples=1))
    plain["aggtool_sidecar"] = str(out / "gone.agg")
    bad["preview_missing_file"] = op_error(lambda: bpy.ops.aggtool.render_preview(samples=1))
    select([base])
    prefs.module_path = str(WORK / "no-module")
    bad["preview_no_module"] = op_error(lambda: bpy.ops.aggtool.render_preview(samples=1))
    prefs.module_path = MODULE_DIR
    bad["files"] = files_under(out)
    bad["sidecar_of_plain"] = plain.get("aggtool_sidecar")
    result["bad_input"] = bad


@part("cancel")
def cancel():
    """The cancel path the modal operator takes on Esc (modal operators need a window, which a
    background session has not): a bake big enough to run for seconds, killed once its first
    progress line arrived."""
    select(boxes, active=base)
    out = WORK / "cancel" / "big.agg"
    job = ext.BakeJob(AGGTOOL, boxes, str(out), "default",
                      dict(max_res=128, samples=64, aiv_rays=64), ext.preset_table())
    job.export(bpy.context)
    job.start()
    t0 = time.perf_counter()
    while job.progress() == 0 and not job.done() and time.perf_counter() - t0 < 30:
        time.sleep(0.02)
    fraction, finished_first = job.progress(), job.done()
    job.cancel()
    result["cancel"] = {"fraction_at_cancel": fraction, "finished_before_cancel": finished_first,
                        "returncode": job.proc.returncode, "files": files_under(out.parent),
                        "result": ext.last_bake["result"]}


#: Overrides of every preset in the cross-binding bake (test_blender.py bakes the same
#: exported file with them through the CLI and the Python module): the smallest finest level,
#: so that the four presets bake in seconds; every other setting is the preset's.
PRESET_OVERRIDES = dict(max_res=8)


@part("presets")
def presets():
    """The preset table as the extension reads it, from the Python module and (the module
    made unimportable) from the binary; then the boxes baked with every preset, keeping the
    exact GLB each bake exported, for test_blender.py to bake through the CLI and Python."""
    table = ext.preset_table(bpy.context)
    prefs.module_path = str(WORK / "no-module")
    try:
        cli_table = ext.preset_table(bpy.context)
    finally:
        prefs.module_path = MODULE_DIR
    start, bakes = ext.BakeJob.start, {}

    def keeping(job):
        kept = WORK / "presets" / job.preset / os.path.basename(job.glb)
        kept.parent.mkdir(parents=True, exist_ok=True)
        kept.write_bytes(Path(job.glb).read_bytes())
        bakes[job.preset] = {"glb": str(kept)}
        start(job)

    ext.BakeJob.start = keeping
    try:
        for name in table["presets"]:
            select(boxes, active=base)
            out = WORK / "presets" / name / "blender.agg"
            t0 = time.perf_counter()
            r = bpy.ops.aggtool.bake_aggregate(preset=name, filepath=str(out), **PRESET_OVERRIDES)
            bakes[name].update(result=sorted(r), agg=str(out), command=ext.last_bake["command"],
                               seconds=time.perf_counter() - t0)
    finally:
        ext.BakeJob.start = start
    result["presets"] = {"table": table, "cli_table": cli_table, "overrides": PRESET_OVERRIDES,
                         "bakes": bakes}


Path(RESULT).write_text(json.dumps(result, indent=1))
