"""aggtool LoD: appearance-preserving level of detail for Blender.

- `bpy.ops.aggtool.bake_aggregate`: exports the selected objects to a temporary glTF binary
  (`bpy.ops.export_scene.gltf`, use_selection), runs `aggtool convert` on it as a subprocess
  (modal with a timer and `WindowManager.progress_*`; Esc cancels; synchronous in the
  background and from scripts) and stores the `.agg` path on each selected object as the custom
  property `aggtool_sidecar` (and the object's world matrix then as `aggtool_bake_matrix`).
- `bpy.ops.aggtool.render_preview`: cone-traces the active object's aggregate through the
  `aggtool` Python module from the scene camera into the image datablock "aggtool preview".
- A panel in the 3D Viewport's sidebar, tab "aggtool": preset, settings, both operators.

The presets are the tool's (`aggtool presets --json`, or `aggtool.preset_table()` from the
Python module when it is importable): the menu lists them, the panel shows their values, and
a bake passes `--preset NAME` and the settings the user overrode, nothing else.

The binary: the add-on preference, else $AGGTOOL, else PATH. The Python module: importable
`aggtool`, or the add-on preference naming a folder that holds it. README "Blender".
"""
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty,
                       PointerProperty, StringProperty)
from mathutils import Matrix, Vector

#: The custom properties written on baked objects.
SIDECAR = "aggtool_sidecar"
BAKE_MATRIX = "aggtool_bake_matrix"

#: The bake settings the panel and the operator offer, named as the tool names them (`aggtool
#: presets --json`, `aggtool.presets()`); each reaches `aggtool convert` as its flag
#: (`--max-res`, ...) only when the user sets it, over the preset's value. The presets
#: themselves, their values and the defaults are the tool's, read from it (`preset_table`).
SETTINGS = ("max_res", "min_res", "samples", "aiv_res", "aiv_rays", "abv_res", "abv_rays",
            "abv_full_res", "visibility_levels", "size_mib")

#: Read tables of presets, by where they came from (the module's file, or the binary and its
#: modification time), so that the menu does not run the tool at every redraw.
_tables = {}

#: The preset menu's items as last built: Blender needs the strings of a dynamic enum's
#: items kept alive by the add-on.
_preset_menu = []

#: Blender's Z-up world to glTF's Y-up, as the glTF exporter converts (export_yup):
#: (x, y, z) -> (x, z, -y). The .agg is in the exported glTF's space.
BLENDER_TO_GLTF = Matrix(((1, 0, 0, 0), (0, 0, 1, 0), (0, -1, 0, 0), (0, 0, 0, 1)))

#: Object types the glTF exporter writes as meshes (io_scene_gltf2 blender/exp/nodes.py).
MESH_LIKE = {"MESH", "CURVE", "SURFACE", "FONT"}

#: What the last bake did, for scripts and the tests: the command, the fractions passed to
#: `progress_update` (one per timer tick or poll), the fraction after each of convert's
#: progress lines, the output and the outcome.
last_bake = {}

#: The bake in progress (one at a time).
_running = None


class AggtoolError(Exception):
    """A user-facing error: the operator reports its text and writes nothing."""


# ------------------------------------------------------------------------------------------
# Preferences: where the binary and the Python module are


class AggtoolPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    aggtool_path: StringProperty(
        name="aggtool binary",
        description="The aggtool executable; empty: the AGGTOOL environment variable, else PATH",
        subtype="FILE_PATH",
    )
    module_path: StringProperty(
        name="Python module folder",
        description="A folder holding the `aggtool` Python package (for the preview); empty: "
                    "import it from Blender's Python path",
        subtype="DIR_PATH",
    )

    def draw(self, context):
        self.layout.prop(self, "aggtool_path")
        self.layout.prop(self, "module_path")


def preferences(context):
    addon = context.preferences.addons.get(__package__)
    return addon.preferences if addon else None


def find_aggtool(context):
    """The aggtool binary: the preference, else $AGGTOOL, else PATH; AggtoolError if none."""
    def checked(path, origin):
        if not (os.path.isfile(path) and os.access(path, os.X_OK)):
            raise AggtoolError(f"aggtool binary not found: {path} ({origin}) is not an "
                               "executable file")
        return path

    prefs = preferences(context)
    if prefs and prefs.aggtool_path:
        return checked(bpy.path.abspath(prefs.aggtool_path), "add-on preference")
    if os.environ.get("AGGTOOL"):
        return checked(os.environ["AGGTOOL"], "AGGTOOL environment variable")
    found = shutil.which("aggtool")
    if found:
        return found
    raise AggtoolError("aggtool binary not found: set it in Preferences > Add-ons > aggtool "
                       "LoD, or the AGGTOOL environment variable, or put aggtool on PATH")


def import_module(context):
    """The `aggtool` Python module (from the preference's folder first); AggtoolError if the
    native module cannot be imported."""
    prefs = preferences(context)
    folder = bpy.path.abspath(prefs.module_path) if prefs and prefs.module_path else ""
    if folder:
        if not os.path.isdir(folder):
            raise AggtoolError(f"aggtool Python module folder not found: {folder} (add-on "
                               "preference)")
        if folder not in sys.path:
            sys.path.insert(0, folder)
    try:
        import aggtool
        aggtool.open  # the package without its native module raises ImportError here
    except ImportError as e:
        where = f" in {folder}" if folder else ""
        raise AggtoolError(f"the aggtool Python module is not importable{where}: {e} (build it "
                           "with maturin in integrations/python and set its folder in the "
                           "add-on preferences)") from None
    return aggtool


# ------------------------------------------------------------------------------------------
# Bake


def _normalised(table, source):
    """`aggtool presets --json`'s object as {"default", "presets": {name: {"summary",
    "settings"}}} in the tool's order, with where it came from."""
    presets = {p["name"]: {"summary": p.get("summary", ""), "settings": dict(p["settings"])}
               for p in table["presets"]}
    if table["default"] not in presets or not all(k in p["settings"] for p in presets.values()
                                                  for k in SETTINGS):
        raise AggtoolError(f"the bake presets from {source} lack a setting this add-on "
                           f"offers ({', '.join(SETTINGS)}): a newer add-on needs a newer tool")
    return {"default": table["default"], "presets": presets, "source": source}


def preset_table(context=None):
    """The tool's bake presets: from the aggtool Python module if it is importable
    (`aggtool.preset_table()`), else from the binary (`aggtool presets --json`). The add-on
    keeps no copy, so a preset name bakes the same file here as on the command line.
    AggtoolError when neither can be read."""
    context = context or bpy.context
    errors = []
    try:
        module = import_module(context)
        key = ("module", getattr(module, "__file__", ""))
        if key not in _tables:
            _tables[key] = _normalised(module.preset_table(), "the aggtool Python module")
        return _tables[key]
    except (AggtoolError, AttributeError) as e:
        errors.append(str(e))
    binary = find_aggtool(context)
    try:
        key = ("cli", binary, os.path.getmtime(binary))
    except OSError as e:
        raise AggtoolError(f"cannot read the bake presets from {binary}: {e}") from None
    if key not in _tables:
        try:
            r = subprocess.run([binary, "presets", "--json"], capture_output=True, text=True,
                               timeout=60)
            if r.returncode != 0:
                raise AggtoolError(r.stderr.strip() or f"exit status {r.returncode}")
            _tables[key] = _normalised(json.loads(r.stdout), f"{binary} presets --json")
        except (OSError, ValueError, KeyError, TypeError, subprocess.TimeoutExpired,
                AggtoolError) as e:
            raise AggtoolError(f"cannot read the bake presets from {binary} (`aggtool presets "
                               f"--json`): {e}; nor from the Python module: {errors[0]}") \
                from None
    return _tables[key]


def resolve_preset(table, name):
    """The preset's name as the tool spells it (any case; empty: the tool's default);
    AggtoolError naming the presets there are."""
    name = (name or "").strip().lower() or table["default"]
    if name not in table["presets"]:
        raise AggtoolError(f"unknown bake preset '{name}'; aggtool's presets are: "
                           f"{', '.join(table['presets'])}")
    return name


def operator_overrides(op):
    """The settings given explicitly to the operator: the user's overrides of the preset."""
    return {key: getattr(op, key) for key in SETTINGS if op.properties.is_property_set(key)}


def convert_flags(preset, overrides):
    """`aggtool convert`'s flags: the preset by name, then each override as its flag."""
    flags = ["--preset", preset]
    for key, value in overrides.items():
        flags += ["--" + key.replace("_", "-"), str(value)]
    return flags


def exportable(objects, depsgraph):
    """The objects the glTF exporter writes with at least one face (modifiers applied)."""
    out = []
    for obj in objects:
        if obj.type not in MESH_LIKE:
            continue
        evaluated = obj.evaluated_get(depsgraph)
        try:
            mesh = evaluated.to_mesh()
        except RuntimeError:
            continue
        faces = len(mesh.polygons) if mesh else 0
        evaluated.to_mesh_clear()
        if faces:
            out.append(obj)
    return out


def default_output(context, name):
    """The settings' output folder (blend-relative `//aggtool` by default) + NAME.agg; a
    temporary folder when the blend file is unsaved and the folder is blend-relative."""
    folder = context.scene.aggtool.output_dir
    if folder.startswith("//") and not bpy.data.filepath:
        folder = os.path.join(tempfile.gettempdir(), "aggtool-bakes")
    return os.path.join(bpy.path.abspath(folder), bpy.path.clean_name(name) + ".agg")


class BakeJob:
    """One `aggtool convert` run. It writes into a private folder beside the output and the
    finished file is moved into place with one rename, so a cancelled or failed bake leaves
    nothing behind (convert itself also writes atomically)."""

    def __init__(self, binary, objects, output, preset, overrides, table):
        self.binary = binary
        self.objects = [o.name for o in objects]
        self.output = os.path.abspath(output)
        self.preset = resolve_preset(table, preset)
        self.overrides = dict(overrides)
        #: What the tool will bake with (for the progress estimate only; the tool applies
        #: the preset and the overrides itself).
        self.settings = dict(table["presets"][self.preset]["settings"], **self.overrides)
        settings = self.settings
        self.proc = None
        self.lines = queue.Queue()
        self.stderr = []
        self.stdout = []
        self.threads = []
        # The stages in the order the bake reports them: per level, finest first, voxels
        # then faces. Levels cost about the same (the same sample density per unit area on
        # every level, README "The bake"), so each stage counts equally.
        res, self.stages = settings["max_res"], []
        while res >= max(settings["min_res"], 1):
            self.stages += [f"{res}³ voxels", f"{res}³ faces"]
            res //= 2
        self.fraction = 0.0
        self.parsed = []  # the fraction after each progress line
        self.created_dir = None
        self.workdir = None

    def export(self, context):
        """Exports the objects (selected) to a GLB in the private folder."""
        folder = os.path.dirname(self.output)
        if not os.path.isdir(folder):
            os.makedirs(folder)
            self.created_dir = folder
        self.workdir = tempfile.mkdtemp(prefix=".aggtool-bake-", dir=folder)
        self.glb = os.path.join(self.workdir, "selection.glb")
        self.tmp_agg = os.path.join(self.workdir, os.path.basename(self.output))
        result = bpy.ops.export_scene.gltf(
            filepath=self.glb, export_format="GLB", use_selection=True, export_apply=True,
            export_yup=True, export_cameras=False, export_lights=False,
            export_animations=False, export_extras=False)
        if "FINISHED" not in result or not os.path.isfile(self.glb):
            raise AggtoolError(f"the glTF export of the selection failed ({result})")

    def start(self):
        self.command = [self.binary, "convert", self.glb, "-o", self.tmp_agg,
                        *convert_flags(self.preset, self.overrides), "--progress-json"]
        last_bake.clear()
        last_bake.update(command=self.command, progress=[], parsed=self.parsed,
                         output=self.output, result=None)
        try:
            self.proc = subprocess.Popen(self.command, stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, text=True,
                                         encoding="utf-8", errors="replace")
        except OSError as e:
            self.cleanup()
            raise AggtoolError(f"cannot run {self.binary}: {e}") from None
        for stream, sink in ((self.proc.stdout, self.stdout), (self.proc.stderr, self.stderr)):
            t = threading.Thread(target=self._read, args=(stream, sink), daemon=True)
            t.start()
            self.threads.append(t)

    def _read(self, stream, sink):
        for line in stream:
            sink.append(line.rstrip("\n"))
            if line.startswith("{"):
                self.lines.put(line)

    def progress(self):
        """The fraction done, from convert's JSON progress lines read so far."""
        while True:
            try:
                line = self.lines.get_nowait()
            except queue.Empty:
                break
            try:
                p = json.loads(line)
                k = self.stages.index(p["stage"])
                part = p["done"] / p["total"] if p["total"] else 1.0
            except (ValueError, KeyError, TypeError, ZeroDivisionError):
                continue  # not a progress line, or a stage this estimate does not know
            self.fraction = max(self.fraction, (k + part) / len(self.stages))
            self.parsed.append(self.fraction)
        return self.fraction

    def done(self):
        """Whether convert has ended and its output has been read to the end: the reader
        threads can still be queueing the last progress lines when the process has exited,
        and a final `progress()` must see them (else the bar stops short of 100%)."""
        return self.proc.poll() is not None and not any(t.is_alive() for t in self.threads)

    def finish(self):
        """After the process ended: moves the .agg into place; returns its path. Raises
        AggtoolError with convert's own error lines when it failed."""
        for t in self.threads:
            t.join(5)
        try:
            if self.proc.returncode != 0 or not os.path.isfile(self.tmp_agg):
                errors = [l for l in self.stderr if not l.startswith("{")]
                reason = " / ".join(errors[-3:]) or f"exit status {self.proc.returncode}"
                raise AggtoolError(f"aggtool convert failed: {reason}")
            os.replace(self.tmp_agg, self.output)
        finally:
            self.cleanup()
        last_bake["result"] = "finished"
        return self.output

    def cancel(self):
        if self.proc and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        for t in self.threads:
            t.join(5)
        self.cleanup()
        last_bake["result"] = "cancelled"

    def cleanup(self):
        if self.workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None
        if self.created_dir and os.path.isdir(self.created_dir) \
                and not os.listdir(self.created_dir) and not os.path.exists(self.output):
            os.rmdir(self.created_dir)
        self.created_dir = None


def store_sidecar(job):
    """`aggtool_sidecar` (blend-relative when the blend file is saved) and the world matrix
    at bake time on every baked object that still exists."""
    path = bpy.path.relpath(job.output) if bpy.data.filepath else job.output
    for name in job.objects:
        obj = bpy.data.objects.get(name)
        if obj is not None:
            obj[SIDECAR] = path
            obj[BAKE_MATRIX] = [v for row in obj.matrix_world for v in row]


#: The settings' names, descriptions and ranges in the UI (their values are the tool's).
SETTING_HINTS = {
    "max_res": ("Max resolution", "Finest level resolution (a power of two)", 1, 4096),
    "min_res": ("Min resolution", "Coarsest level resolution (a power of two)", 1, 4096),
    "samples": ("Samples", "Surface samples per voxel at the finest level", 1, 1 << 20),
    "aiv_res": ("AIV resolution", "Interior-visibility map resolution per voxel", 2, 256),
    "aiv_rays": ("AIV rays", "Interior-visibility rays per surface sample", 1, 1 << 16),
    "abv_res": ("ABV resolution", "Boundary-visibility map resolution per face", 2, 256),
    "abv_rays": ("ABV rays", "Boundary-visibility rays per direction cell", 1, 1 << 16),
    "abv_full_res": ("ABV full resolution", "Finer levels share boundary-visibility rays "
                     "among blocks of cells", 1, 4096),
    "visibility_levels": ("Visibility levels", "The finest levels that keep no interior "
                          "visibility of their own (fewer bytes and less bake time; for "
                          "foliage seen up close)", 0, 16),
    "size_mib": ("Size budget (MiB)", "The whole file's size in MiB (0: none): the bake spends "
                 "it on the visibility details that matter most to the picture", 0.0, 1e6),
}


def _setting_props(cls_annotations, update=None):
    """An IntProperty per setting (a FloatProperty where its range is of floats). Its
    default is only the bottom of its range: a setting reaches the tool only when set (the
    operator) or ticked (the panel), the rest is the preset's, which the tool holds."""
    for key in SETTINGS:
        name, desc, lo, hi = SETTING_HINTS[key]
        kind = FloatProperty if isinstance(lo, float) else IntProperty
        cls_annotations[key] = kind(name=name, description=desc + " (unset: the preset's)",
                                    default=lo, min=lo, max=hi)


def _preset_items(self, context):
    """The preset menu, read from the tool (the default preset first: a dynamic enum's
    default is its first item)."""
    global _preset_menu
    try:
        table = preset_table(context)
        names = [table["default"]] + [n for n in table["presets"] if n != table["default"]]
        items = [(n, n.capitalize(), table["presets"][n]["summary"]) for n in names]
    except AggtoolError as e:
        items = [("default", "Default", f"aggtool's presets could not be read: {e}")]
    _preset_menu = items
    return items


class AGGTOOL_OT_bake_aggregate(bpy.types.Operator):
    """Bake the selected objects into an appearance-preserving LoD aggregate (.agg) with
    aggtool convert"""
    bl_idname = "aggtool.bake_aggregate"
    bl_label = "Bake LoD Aggregate"
    bl_options = {"REGISTER"}

    preset: StringProperty(name="Preset", default="",
                           description="An aggtool bake preset (`aggtool presets`); empty: "
                                       "the tool's default. Settings given explicitly "
                                       "override it")
    filepath: StringProperty(name="Output", subtype="FILE_PATH",
                             description="The .agg to write; empty: the output folder of the "
                                         "aggtool settings + the active object's name")
    _setting_props(__annotations__)

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def prepare(self, context):
        """Checks the input and exports the selection; a BakeJob ready to start."""
        if _running is not None:
            raise AggtoolError("a bake is already running")
        selected = list(context.selected_objects)
        objects = exportable(selected, context.evaluated_depsgraph_get())
        if not objects:
            names = ", ".join(o.name for o in selected) or "nothing selected"
            raise AggtoolError(f"nothing to bake: the selection ({names}) has no mesh with "
                               "faces")
        skipped = [o.name for o in selected if o not in objects]
        if skipped:
            self.report({"WARNING"}, f"not baked (no faces): {', '.join(skipped)}")
        binary = find_aggtool(context)
        active = context.active_object if context.active_object in objects else objects[0]
        output = bpy.path.abspath(self.filepath) if self.filepath \
            else default_output(context, active.name)
        job = BakeJob(binary, objects, output, self.preset, operator_overrides(self),
                      preset_table(context))
        try:
            job.export(context)
        except BaseException:
            job.cleanup()
            raise
        return job

    def _update(self, wm, job):
        f = job.progress()
        last_bake["progress"].append(f)
        wm.progress_update(f * 100.0)
        return f

    def _finished(self, job):
        path = job.finish()
        store_sidecar(job)
        self.report({"INFO"}, f"aggtool: baked {len(job.objects)} object(s) into {path}")

    def execute(self, context):
        """Synchronous bake (the background, scripts): the same progress calls, blocking."""
        global _running
        try:
            job = self.prepare(context)
        except AggtoolError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        wm = context.window_manager
        wm.progress_begin(0.0, 100.0)
        _running = job
        try:
            job.start()
            decile = -1
            while not job.done():
                time.sleep(0.05)
                f = self._update(wm, job)
                if bpy.app.background and int(f * 10) > decile:
                    decile = int(f * 10)
                    print(f"aggtool: bake {100 * f:.0f}%", flush=True)
            self._update(wm, job)
            self._finished(job)
        except AggtoolError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        except BaseException:  # Ctrl-C in a script: kill the subprocess, write nothing
            job.cancel()
            raise
        finally:
            _running = None
            wm.progress_end()
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        global _running
        try:
            job = self.prepare(context)
            job.start()
        except AggtoolError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        _running = self._job = job
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0.0, 100.0)
        wm.modal_handler_add(self)
        self.report({"INFO"}, "aggtool: baking (Esc cancels)")
        return {"RUNNING_MODAL"}

    def _end(self, context):
        global _running
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        _running = None

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancel()
            self._end(context)
            self.report({"WARNING"}, "aggtool: bake cancelled, nothing written")
            return {"CANCELLED"}
        if event.type == "TIMER":
            self._update(context.window_manager, job)
            if job.done():
                self._update(context.window_manager, job)
                self._end(context)
                try:
                    self._finished(job)
                except AggtoolError as e:
                    self.report({"ERROR"}, str(e))
                    return {"CANCELLED"}
                # The sidecar properties as one undo step (no UNDO option: its redo panel
                # would re-run the bake synchronously).
                bpy.ops.ed.undo_push(message=self.bl_label)
                return {"FINISHED"}
        return {"PASS_THROUGH"}


# ------------------------------------------------------------------------------------------
# Preview


def world_light(scene):
    """The constant environment: the world's Background node (colour × strength) when it has
    one unlinked, else the world's viewport colour."""
    world = scene.world
    if world is None:
        return (0.0, 0.0, 0.0)
    tree = getattr(world, "node_tree", None)
    if tree is not None:
        for node in tree.nodes:
            if node.type == "BACKGROUND" and not node.inputs[0].is_linked:
                c, s = node.inputs[0].default_value, node.inputs[1].default_value
                return tuple(max(0.0, c[i] * s) for i in range(3))
    return tuple(world.color)


def camera_rays(scene, camera, width, height, rng):
    """One jittered ray per pixel from the camera, in world space, rows from the bottom (as
    Blender stores images); and the cone aperture of a pixel (its angle at the centre)."""
    import numpy as np
    frame = camera.data.view_frame(scene=scene)  # corners in camera space, sensor fit applied
    xs, ys = [v.x for v in frame], [v.y for v in frame]
    x0, x1, y0, y1, z = min(xs), max(xs), min(ys), max(ys), frame[0].z
    j, i = np.mgrid[0:height, 0:width]
    u = x0 + (i + rng.random((height, width))) / width * (x1 - x0)
    v = y0 + (j + rng.random((height, width))) / height * (y1 - y0)
    m = np.array(camera.matrix_world, dtype=np.float64)
    if camera.data.type == "PERSP":
        local = np.stack([u, v, np.full_like(u, z)], -1).reshape(-1, 3)
        dirs = local @ m[:3, :3].T
        origins = np.broadcast_to(m[:3, 3], dirs.shape)
        aperture = (y1 - y0) / height / abs(z)
    elif camera.data.type == "ORTHO":
        local = np.stack([u, v, np.zeros_like(u)], -1).reshape(-1, 3)
        origins = local @ m[:3, :3].T + m[:3, 3]
        dirs = np.broadcast_to(m[:3, :3] @ np.array([0.0, 0.0, -1.0]), origins.shape)
        aperture = 0.0  # parallel rays: the finest level
    else:
        raise AggtoolError(f"camera '{camera.name}': only perspective and orthographic "
                           "cameras are supported")
    return origins, dirs, aperture


def to_aggregate(obj):
    """World space -> the aggregate's space: back to the object's transform at bake time (the
    aggregate moves with the object), then Blender Z-up -> glTF Y-up."""
    baked = obj.get(BAKE_MATRIX)
    at_bake = Matrix([list(baked[r * 4:r * 4 + 4]) for r in range(4)]) if baked is not None \
        and len(baked) == 16 else obj.matrix_world
    try:
        inverse = obj.matrix_world.inverted()
    except ValueError:
        raise AggtoolError(f"object '{obj.name}' has a singular transform") from None
    return BLENDER_TO_GLTF @ at_bake @ inverse


class AGGTOOL_OT_render_preview(bpy.types.Operator):
    """Render the active object's LoD aggregate from the scene camera into the image
    "aggtool preview" (cone tracing through the aggtool Python module)"""
    bl_idname = "aggtool.render_preview"
    bl_label = "Render Aggregate Preview"
    bl_options = {"REGISTER"}

    samples: IntProperty(name="Samples", description="Cones per pixel", default=4, min=1,
                         max=4096)
    resolution_percentage: IntProperty(
        name="Resolution %", description="Percentage of the scene's render resolution",
        default=100, min=1, max=100, subtype="PERCENTAGE")
    seed: IntProperty(name="Seed", default=0, min=0)
    image: StringProperty(name="Image", default="aggtool preview",
                          description="The image datablock to render into")

    def execute(self, context):
        try:
            self.render(context)
        except AggtoolError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        return {"FINISHED"}

    def render(self, context):
        import numpy as np
        scene, obj = context.scene, context.active_object
        if obj is None:
            raise AggtoolError("no active object: select a baked object")
        if SIDECAR not in obj:
            raise AggtoolError(f"object '{obj.name}' has no {SIDECAR}: bake it first (aggtool "
                               "> Bake LoD Aggregate)")
        path = bpy.path.abspath(str(obj[SIDECAR]))
        if not os.path.isfile(path):
            raise AggtoolError(f"object '{obj.name}': its aggregate {path} does not exist")
        camera = scene.camera
        if camera is None or camera.type != "CAMERA":
            raise AggtoolError("the scene has no active camera")
        aggtool = import_module(context)
        try:
            agg = aggtool.open(path)
        except ValueError as e:
            raise AggtoolError(str(e)) from None

        r = scene.render
        scale = r.resolution_percentage * self.resolution_percentage / 1e4
        w, h = max(1, round(r.resolution_x * scale)), max(1, round(r.resolution_y * scale))
        to_agg = np.array(to_aggregate(obj), dtype=np.float64)
        background = world_light(scene)
        sun = next((o for o in scene.objects if o.type == "LIGHT" and o.data.type == "SUN"
                    and o.visible_get()), None)
        sun_args = {}
        if sun is not None:
            towards = sun.matrix_world.to_3x3() @ Vector((0.0, 0.0, 1.0))
            d = to_agg[:3, :3] @ np.array(towards)
            e = [c * sun.data.energy for c in sun.data.color]
            if np.linalg.norm(d) > 0:
                sun_args = dict(sun_direction=tuple(float(x) for x in d),
                                sun_irradiance=tuple(e))
        lights = aggtool.Lights(constant=background, **sun_args)

        rng = np.random.default_rng(self.seed)
        acc = np.zeros((w * h, 4), np.float64)
        wm = context.window_manager
        wm.progress_begin(0, self.samples)
        try:
            for s in range(self.samples):
                o, d, aperture = camera_rays(scene, camera, w, h, rng)
                o = o @ to_agg[:3, :3].T + to_agg[:3, 3]
                d = d @ to_agg[:3, :3].T
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                try:
                    rgba = agg.trace(np.ascontiguousarray(o, np.float32),
                                     np.ascontiguousarray(d, np.float32), float(aperture),
                                     lights, seed=self.seed * 65536 + s)
                except ValueError as e:
                    raise AggtoolError(str(e)) from None
                acc += rgba
                wm.progress_update(s + 1)
        finally:
            wm.progress_end()
        acc /= self.samples
        pixels = np.empty((w * h, 4), np.float32)
        transparent = r.film_transparent
        if transparent:
            # Premultiplied: the surfaces alone, alpha their coverage.
            pixels[:, :3] = acc[:, :3] - np.outer(acc[:, 3], background)
            pixels[:, 3] = 1.0 - acc[:, 3]
        else:
            pixels[:, :3] = acc[:, :3]
            pixels[:, 3] = 1.0

        img = bpy.data.images.get(self.image)
        if img is not None and (tuple(img.size) != (w, h) or not img.is_float):
            bpy.data.images.remove(img)
            img = None
        if img is None:
            img = bpy.data.images.new(self.image, w, h, alpha=True, float_buffer=True)
        img.alpha_mode = "PREMUL" if transparent else "STRAIGHT"
        img.pixels.foreach_set(pixels.ravel())
        img.update()
        self.report({"INFO"}, f"aggtool: preview {w}×{h}, {self.samples} cones/pixel, "
                              f"levels {agg.levels} into image '{img.name}'")


# ------------------------------------------------------------------------------------------
# Settings and panel


def _override_toggled(key):
    """The update of the panel's override tick of `key`: ticked, the value starts from the
    preset's (as the tool has it)."""
    def update(self, context):
        if getattr(self, "override_" + key):
            try:
                table = preset_table(context)
                preset = table["presets"][resolve_preset(table, self.preset)]
            except AggtoolError:
                return
            setattr(self, key, preset["settings"][key])
    return update


def panel_settings(context, settings):
    """The panel's bake settings as {setting: (value, overridden)}: the preset's values
    from the tool, and the user's ticked overrides."""
    table = preset_table(context)
    values = table["presets"][resolve_preset(table, settings.preset)]["settings"]
    return {key: (getattr(settings, key), True) if getattr(settings, "override_" + key)
            else (values[key], False) for key in SETTINGS}


def panel_operator_args(settings):
    """The bake operator's arguments from the panel: the preset and the ticked overrides
    alone."""
    args = {"preset": settings.preset}
    args.update({key: getattr(settings, key) for key in SETTINGS
                 if getattr(settings, "override_" + key)})
    return args


class AggtoolSettings(bpy.types.PropertyGroup):
    preset: EnumProperty(name="Preset", items=_preset_items, default=0,
                         description="aggtool's bake preset (read from the tool); ticked "
                                     "settings below override it")
    output_dir: StringProperty(name="Output folder", default="//aggtool", subtype="DIR_PATH",
                               description="Where bakes are written, as OBJECT.agg")
    preview_samples: IntProperty(name="Preview samples", default=4, min=1, max=4096,
                                 description="Cones per pixel of the preview")
    _setting_props(__annotations__)
    for _key in SETTINGS:
        __annotations__["override_" + _key] = BoolProperty(
            name="Override", default=False, update=_override_toggled(_key),
            description=f"Bake with this {SETTING_HINTS[_key][0].lower()} instead of the "
                        "preset's")
    del _key


class AGGTOOL_PT_panel(bpy.types.Panel):
    bl_label = "aggtool LoD"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "aggtool"

    def draw(self, context):
        s = context.scene.aggtool
        layout = self.layout
        layout.prop(s, "preset")
        col = layout.column(align=True)
        try:
            shown = panel_settings(context, s)
        except AggtoolError as e:
            shown = None
            col.label(text=str(e), icon="ERROR")
        for key in SETTINGS if shown else ():
            row = col.row(align=True)
            row.prop(s, "override_" + key, text="")
            value, overridden = shown[key]
            if overridden:
                row.prop(s, key)
            else:
                row.label(text=f"{SETTING_HINTS[key][0]}: {value}")
        layout.prop(s, "output_dir")
        op = layout.operator(AGGTOOL_OT_bake_aggregate.bl_idname, icon="RENDER_STILL")
        for key, value in panel_operator_args(s).items():
            setattr(op, key, value)
        obj = context.active_object
        if obj is not None and SIDECAR in obj:
            layout.label(text=str(obj[SIDECAR]), icon="FILE")
        layout.prop(s, "preview_samples")
        layout.operator(AGGTOOL_OT_render_preview.bl_idname, icon="IMAGE").samples = \
            s.preview_samples


CLASSES = (AggtoolPreferences, AggtoolSettings, AGGTOOL_OT_bake_aggregate,
           AGGTOOL_OT_render_preview, AGGTOOL_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.aggtool = PointerProperty(type=AggtoolSettings)


def unregister():
    if _running is not None:
        _running.cancel()
    del bpy.types.Scene.aggtool
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
