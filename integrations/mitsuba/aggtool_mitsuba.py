"""A Mitsuba 3 integrator, `aggtool_lod`, that renders a scene where some objects are aggtool
aggregates (`.agg` files) beside Mitsuba's own meshes.

    import mitsuba as mi
    mi.set_variant("scalar_rgb")          # or llvm_ad_rgb
    import aggtool_mitsuba                 # registers "aggtool_lod" for the active variant
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aggtool_lod",
                       "agg_tree": "tree.agg",                       # any key agg_<name>
                       "agg_tree_to_world": mi.ScalarTransform4f().translate([1, 0, 0])},
        ...                                  # sensor, meshes, envmap, directional
    })
    image = mi.render(scene, spp=16)

Parameters (properties of the integrator):

    agg_<name>            string     path of an .agg file (any number of them)
    agg_<name>_to_world   transform  where it sits: rotation, uniform scale, translation
                                     (default: identity; shear, non-uniform scale, singular,
                                     projective or non-finite transforms are refused)
    hide_emitters         boolean    hide the environment where camera rays escape
                                     (default: false)
    lod_bias              float      level-of-detail bias in levels (default 0, the
                                     footprint's level; 1 walks the next coarser level:
                                     faster where cones cross many voxels, blurrier)
    batch_rays            integer    rays traced together in one batch (default 524288,
                                     a few hundred bytes a ray; larger is a little faster)
    samples_per_walk      integer    samples of a pixel that share one camera ray and one
                                     walk of the aggregates, each with its own pick, light
                                     and BSDF samples (default 0: pairs from 64 spp up,
                                     else 1, and more where the pixel's cone is 2 or 4
                                     times finer than the voxels, as `aggtool render`)

`mi.render(scene, spp=N, seed=S)`: N samples per pixel (default: the sensor's sampler's
count), S seeds numpy's PCG64 (one stream per batch of rays).

What it computes (direct illumination, as Mitsuba's `direct` integrator does for meshes):

- Camera rays meet Mitsuba's meshes (`Scene.ray_intersect`) and each aggregate's primitives
  (`aggtool.Scene.pick` with `tmax` clipped at the mesh), so the nearer surface wins: the
  aggregate's surfaces in front of the mesh add their radiance, weighted by their coverage
  (Eq. 30 of the paper), and pass what lies behind (the mesh, or the environment) through the
  aggregate's transmittance (its ABV). Several aggregates composite front to back.
- Mesh points are shaded as `direct` does (one emitter sample and one BSDF sample, combined by
  MIS) with Mitsuba's emitters; their shadow rays are Mitsuba's (other meshes) times each
  aggregate's transmittance along a shadow cone (`aggtool.Scene.transmittance`), so aggregates
  shadow meshes.
- Aggregate hits are shaded here, not by the runtime: one primitive per cone, picked by the
  runtime in proportion to its coverage weight (the weight sum carried, an unbiased estimate
  of Eq. 30's sum), lit by one emitter sample of Mitsuba's scene (environment map, directional emitter,
  area lights) and one ABSDF sample (`voxel_sample`), combined by MIS; the ABSDF comes from
  `voxel_eval`, self-shadowing from the voxel's interior visibility (`voxel_visibility`), and
  Mitsuba's shadow rays decide whether a mesh blocks the light, so meshes shadow aggregates.
- Shadow cones and the aggregate's level of detail use the camera's pixel angle as aperture.

All per-pixel work runs as whole-image batches: numpy arrays into the aggtool module (which
releases the GIL and runs in parallel) and, in JIT variants (`llvm_ad_rgb`), one vectorised
Mitsuba call per phase. In `scalar_*` variants Mitsuba has no batched queries, so the Mitsuba
phases loop over rays in Python (slow: keep images small there). Pixels are box-filtered
(uniform jitter over the pixel) whatever the film's `rfilter`; the sampler's seed is
`mi.render`'s `seed` (numpy's PCG64), not the scene's sampler.

An `agg_<name>` may also name an assembly manifest (`.json`, the README's "Assemblies"),
placed by `agg_<name>_to_world`: it is opened as one `aggtool.Scene` (each aggregate file
once), whose instances the runtime walks through one instance BVH and composes front to back
into one layer, so the integrator's loops run over `agg_` properties, not instances.

Limits: `to_world` must be a similarity (rotation, uniform scale, translation): cone apertures
and ABSDF directions do not survive shear or non-uniform scale, so those are refused. Where a
mesh pierces an aggregate (the cone clipped inside its bounds), the transmittance in front of
the mesh is max(ABV, 1 − coverage in front), an approximation.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import aggtool

__all__ = ["AggtoolLod", "Aggregate", "integrator_class", "register"]

_KEY = re.compile(r"^agg_(\w+?)$")
# Rays per batch (the `batch_rays` property's default): every phase's arrays are a few
# hundred bytes per ray. Each batch calls Dr.Jit's kernels, after which its worker threads
# spin for a while (nanothread's TaskQueue::pop, 14% of the CPU samples of a render at 2^18),
# taking the CPU from the runtime's threads: fewer, larger batches spin less. bench.py's
# 200k-triangle tree at 256², 64 spp: 2^18 / 2^19 / 2^20 rays a batch, render 3.78–3.87 /
# 3.32–3.55 / 3.22–3.42 s, the whole process's peak RSS 315 / 438 / 709 MiB.
BATCH = 1 << 19


def _jit() -> bool:
    return dr.is_jit_v(mi.Float)


# --- batches: one vectorised call in JIT variants, a loop over rows in scalar ones ---------

def _aligned(a, dtype):
    """A contiguous copy of `a` as `dtype` whose data starts on a 64-byte boundary. Dr.Jit
    reads numpy arrays in place and compiles a kernel for the alignment of its inputs: with
    numpy's own allocations (16-byte aligned or not, as malloc places them) the phases'
    kernels came out different from pass to pass, a cache miss and 160 ms of LLVM each
    (12 of 16 passes of a 256², 64-spp render; 12% of its time)."""
    a = np.asarray(a, dtype)
    if a.flags.c_contiguous and a.ctypes.data % 64 == 0:
        return a
    buf = np.empty(a.nbytes + 64, np.uint8)
    off = -buf.ctypes.data % 64
    out = buf[off:off + a.nbytes].view(dtype).reshape(a.shape)
    out[...] = a
    return out


def _to_mi(a, kind):
    if kind == "f":
        return mi.Float(_aligned(a, np.float32))
    if kind == "b":
        return mi.Bool(_aligned(a, bool))
    a = np.asarray(a, np.float32)
    cols = [mi.Float(_aligned(a[:, k], np.float32)) for k in range(a.shape[1])]
    return {"p2": mi.Point2f, "v3": mi.Vector3f, "p3": mi.Point3f}[kind](*cols)


def _scalar_row(r, kind):
    if kind == "f":
        return float(r)
    if kind == "b":
        return bool(r)
    return {"p2": mi.Point2f, "v3": mi.Vector3f, "p3": mi.Point3f}[kind](*r)


def _batch(fn, n, *args):
    """Calls the Mitsuba-side `fn` on n rows of numpy arrays (each with its kind: f, b, p2,
    v3, p3) and returns its outputs as numpy arrays of n rows."""
    if _jit():
        outs = fn(*[_to_mi(a, k) for a, k in args])
        dr.eval(*outs)
        res = []
        for x in outs:
            # A view of the evaluated array (a third of np.array's time, which copies): the
            # phases' outputs are fresh arrays, read here and never written.
            a = x.numpy() if hasattr(x, "numpy") else np.array(x)
            a = a.T if a.ndim == 2 else a
            if a.shape[0] != n:  # a literal broadcast over the batch
                a = np.broadcast_to(a, (n,) + a.shape[1:]).copy()
            res.append(a)
        return res
    rows = [a.tolist() for a, _ in args]
    kinds = [k for _, k in args]
    per = [fn(*[_scalar_row(r[i], k) for r, k in zip(rows, kinds)]) for i in range(n)]
    return [np.array([np.array(p[j], dtype=np.float64) for p in per]) for j in range(len(per[0]))]


def _power(a, b):
    a2, b2 = a * a, b * b
    return dr.select(a2 + b2 > 0, a2 / dr.maximum(a2 + b2, 1e-30), 0.0)


def _power_np(a, b):
    a2, b2 = a * a, b * b
    s = a2 + b2
    return np.where(s > 0, a2 / np.where(s > 0, s, 1.0), 0.0)


def _emit(em, si, active=True):
    """An emitter's radiance towards a surface interaction (the environment on a miss)."""
    if em is None:  # scalar variants: no emitter there
        return mi.Color3f(0.0)
    return em.eval(si, active)


def _infinite(em):
    if em is None:
        return False
    return mi.has_flag(em.flags(), mi.EmitterFlags.Infinite)


def _times(v, m):
    """v @ m for rows v (N, 3) and a 3 × 3 m, by numpy's own einsum loop: `@` hands this to
    OpenBLAS, whose threads then spin waiting for more work and took 11% of a render's CPU
    time from the runtime's own threads (einsum without `optimize` does not call BLAS; half
    the time of three scaled rows of m)."""
    return np.einsum("ij,jk->ik", v, m)


def _normalize(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


# --- aggregates ------------------------------------------------------------------------

def _matrix(to_world, what):
    if to_world is None:
        return np.eye(4)
    if hasattr(to_world, "matrix"):
        m = np.array(to_world.matrix, dtype=np.float64)
    else:
        try:
            m = np.array(to_world, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{what}: not a transform (a mi.ScalarTransform4f or a 4x4 "
                             f"matrix), got {type(to_world).__name__}") from None
    m = m.reshape(4, 4) if m.size == 16 else m
    if m.shape != (4, 4):
        raise ValueError(f"{what}: a transform needs 4x4 numbers, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError(f"{what}: the transform is not finite")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise ValueError(f"{what}: a projective transform (last row {m[3].tolist()})")
    a = m[:3, :3]
    g = a.T @ a
    s2 = np.trace(g) / 3
    if not s2 > 1e-24:
        raise ValueError(f"{what}: the transform is singular (scale 0)")
    if not np.allclose(g, s2 * np.eye(3), rtol=0, atol=1e-4 * s2):
        raise ValueError(f"{what}: shear or non-uniform scale; aggregates take rotations, "
                         f"uniform scales and translations only (cone apertures and ABSDF "
                         f"directions do not survive the others)")
    return m


def _world_box(m, box):
    """The world AABB of local box (lo, hi) under the 4 × 4 transform `m`, padded by a
    thousandth of its diagonal (the module tests rays in the aggregate's frame, in other
    rounding): ((x, y, z), (x, y, z))."""
    lo, hi = (np.asarray(x, np.float64) for x in box)
    c = np.array([[(hi if k & b else lo)[i] for i, b in enumerate((1, 2, 4))]
                  for k in range(8)])
    w = c @ m[:3, :3].T + m[:3, 3]
    a, b = w.min(axis=0), w.max(axis=0)
    pad = 1e-3 * float(np.linalg.norm(b - a)) + 1e-6
    return (a - pad).tolist(), (b + pad).tolist()


# Culling masks carry one bit an aggregate; aggregates from this index on are never culled.
_MASK_BITS = 32


def _meets(mask, j):
    """Rows whose culling `mask` (as a phase returned it) says they may meet aggregate j."""
    if j >= _MASK_BITS:
        return np.ones(len(mask), bool)
    return ((np.asarray(mask).astype(np.uint64) >> np.uint64(j)) & np.uint64(1)).astype(bool)


class Aggregate:
    """An aggtool aggregate placed in the scene by `to_world` (a similarity transform)."""

    def __init__(self, path, to_world=None, name="aggregate", scene=None):
        path = Path(path)
        self.name = name
        self.path = path
        # aggtool.AggError naming the file; a manifest's instances share one opened scene.
        self.scene = scene if scene is not None else aggtool.open(str(path))
        # An assembly manifest: every instance in one scene (one instance BVH), picked and
        # shaded by instance.
        self.assembly = path.suffix.lower() == ".json"
        self.to_world = _matrix(to_world, f"{name}_to_world")
        self.linear = self.to_world[:3, :3]
        self.scale = float(np.sqrt(np.trace(self.linear.T @ self.linear) / 3))
        inv = np.linalg.inv(self.to_world)
        self.inv_linear, self.inv_offset = inv[:3, :3], inv[:3, 3]
        # Whole batches go through these in float32 (a float64 product and its temporaries
        # were a sixth of a small image's time); the identity skips them.
        self.identity = bool(np.array_equal(self.to_world, np.eye(4)))
        self.inv_t32 = np.ascontiguousarray(self.inv_linear.T, np.float32)
        self.inv_offset32 = self.inv_offset.astype(np.float32)
        b = self.scene.bounds
        self.bounds = None if b is None else (np.array(b[0]), np.array(b[1]))
        # The world box outside which no cone meets anything of it (`walk_bounds` of every
        # level); a render culls its rays with the tighter box of its own cones
        # (`_AggtoolLod._set_culls`).
        wb = self.scene.walk_bounds()
        self.reach = None if wb is None else _world_box(self.to_world, wb)

    def point_to_local(self, p):
        p = np.asarray(p, np.float32)
        if self.identity:
            return np.ascontiguousarray(p)
        return _times(p, self.inv_t32) + self.inv_offset32

    def dir_to_local(self, d):
        """Directions in the aggregate's frame, not normalised (the module normalises)."""
        d = np.asarray(d, np.float32)
        if self.identity:
            return np.ascontiguousarray(d)
        return _times(d, self.inv_t32)

    def dir_to_world(self, d):
        return _normalize(_times(d, self.linear.T))

    def t_to_local(self, t):
        """World distances along unit directions → local ones (inf stays inf)."""
        return (np.asarray(t, np.float64) / self.scale).astype(np.float32)

    def transmittance(self, p, d, aperture, tmax, skip=None, lod_bias=0.0):
        """What this aggregate lets through along world rays p + t d, t < tmax; `skip`
        (per ray, an assembly's instance or −1) leaves that instance out."""
        return self.scene.transmittance(self.point_to_local(p), self.dir_to_local(d),
                                        aperture, self.t_to_local(tmax), skip, lod_bias)


def _parse(props):
    aggs = []
    keys = list(props.keys())
    for k in sorted(keys):
        m = _KEY.match(k)
        if not m or k.endswith("_to_world"):
            continue
        path = props[k]
        if not isinstance(path, str):
            raise ValueError(f"aggtool_lod: {k} must be the path of an .agg file or manifest")
        tw = props[k + "_to_world"] if (k + "_to_world") in keys else None
        aggs.append(Aggregate(path, tw, k))
    for k in keys:
        if k.endswith("_to_world") and k[: -len("_to_world")] not in keys:
            raise ValueError(f"aggtool_lod: {k} has no {k[:-len('_to_world')]} path beside it")
        if not k.startswith("agg_") and k not in ("hide_emitters", "lod_bias",
                                                  "samples_per_walk"):
            raise ValueError(f"aggtool_lod: unknown property {k!r} (agg_<name>, "
                             f"agg_<name>_to_world, hide_emitters, lod_bias, "
                             f"samples_per_walk)")
    return aggs


class _AggtoolLod:
    """Direct illumination of meshes and aggtool aggregates (see the module's docstring).
    The methods of the integrator; [`integrator_class`] copies them into a subclass of the
    active variant's `mi.SamplingIntegrator` (nanobind types take one base)."""

    def __init__(self, props=None, aggregates=None):
        mi.SamplingIntegrator.__init__(self, props if props is not None else mi.Properties())
        self.aggregates = _parse(props) if props is not None else []
        self.aggregates += list(aggregates or [])
        self.hide_emitters = bool(props["hide_emitters"]) if (
            props is not None and "hide_emitters" in props.keys()) else False
        self.samples_per_walk = int(props["samples_per_walk"]) if (
            props is not None and "samples_per_walk" in props.keys()) else 0
        if self.samples_per_walk < 0:
            raise ValueError(f"aggtool_lod: samples_per_walk must be 0 (the runtime's choice) "
                             f"or more, not {self.samples_per_walk}")
        self.batch_rays = int(props["batch_rays"]) if (
            props is not None and "batch_rays" in props.keys()) else BATCH
        if self.batch_rays < 1:
            raise ValueError(f"aggtool_lod: batch_rays must be at least 1, not {self.batch_rays}")
        # Culling boxes (`_cull`): every level's until a render sets its own.
        self._culls = [a.reach for a in self.aggregates]
        self.lod_bias = float(props["lod_bias"]) if (
            props is not None and "lod_bias" in props.keys()) else 0.0
        if not (math.isfinite(self.lod_bias) and -8 <= self.lod_bias <= 8):
            raise ValueError(f"aggtool_lod: lod_bias must be between -8 and 8 levels, "
                             f"not {self.lod_bias}")

    # -- Mitsuba-side phases (written once for scalar and JIT variants) --------------------

    def _cull(self, o, d, tmax):
        """Bit j set where the ray o + t d, 0 ≤ t ≤ tmax, meets aggregate j's culling box
        (`_set_culls`; a slab test, fused into the phase's kernel): the rays to hand to the
        module for it. On bench.py's tree, 31% of the camera rays and 27% of the ground's
        shadow rays (the rest were a tenth of a render's time, in numpy and the module)."""
        mask = mi.UInt32(0)
        inv = dr.rcp(dr.select(dr.abs(d) < 1e-30, 1e-30, d))
        for j, box in enumerate(self._culls[:_MASK_BITS]):
            if box is None:
                continue
            t0 = (mi.Point3f(*box[0]) - o) * inv
            t1 = (mi.Point3f(*box[1]) - o) * inv
            lo, hi = dr.minimum(t0, t1), dr.maximum(t0, t1)
            near = dr.maximum(dr.maximum(lo.x, lo.y), lo.z)
            far = dr.minimum(dr.minimum(hi.x, hi.y), hi.z)
            hit = (near <= far) & (far >= 0) & (near <= tmax)
            mask = mask | dr.select(hit, mi.UInt32(1 << j), mi.UInt32(0))
        return mask

    def _camera(self, sensor):
        def fn(pos):
            ray, w = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
            return ray.o, ray.d, mi.Color3f(w)
        return fn

    def _mesh(self, scene, sensor):
        """The camera ray through film position `pos` and what it meets of Mitsuba's meshes,
        in one kernel: (o, d, weight, t, emitted, emitter sample's contribution, its
        direction and distance, BSDF sample's contribution, direction and distance, hit
        point, and the culling masks of the camera ray and the two shadow rays)."""
        jit = _jit()

        camera = self._camera(sensor)

        def fn(pos, u_e, u_b1, u_b2):
            o, d, w = camera(pos)
            d = dr.normalize(d)
            ray = mi.Ray3f(o, d)
            si = scene.ray_intersect(ray)
            valid = si.is_valid()
            le = _emit(si.emitter(scene), si)
            if self.hide_emitters:
                le = dr.select(valid, le, mi.Color3f(0.0))
            zero = mi.Color3f(0.0)
            if not jit and not valid:
                return (o, d, w, math.inf, le, zero, d, math.inf, zero, d, math.inf, o,
                        self._cull(o, d, math.inf), 0, 0)
            ctx = mi.BSDFContext()
            bsdf = si.bsdf(ray)
            # One emitter sample, shadow ray by Mitsuba (meshes).
            ds, em_w = scene.sample_emitter_direction(si, u_e, True, valid)
            f_e, pdf_b = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), valid)
            mis_e = dr.select(ds.delta, 1.0, _power(ds.pdf, pdf_b))
            c_e = dr.select(valid & (ds.pdf > 0), f_e * em_w * mis_e, zero)
            dist_e = dr.select(_infinite(ds.emitter) if not jit else
                               mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite),
                               math.inf, ds.dist)
            # One BSDF sample towards whatever emits (the environment, an area light).
            bs, w_b = bsdf.sample(ctx, si, u_b1, u_b2, valid)
            d_b = si.to_world(bs.wo)
            si_b = scene.ray_intersect(si.spawn_ray(d_b), valid)
            em_b = si_b.emitter(scene)
            le_b = _emit(em_b, si_b, valid)
            delta_b = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            if jit or em_b is not None:
                ds_b = mi.DirectionSample3f(scene, si_b, si)
                pdf_e = scene.pdf_emitter_direction(
                    si, ds_b, (valid & ~delta_b) if jit else bool(valid and not delta_b))
            else:
                pdf_e = 0.0
            mis_b = dr.select(delta_b, 1.0, _power(bs.pdf, pdf_e))
            c_b = dr.select(valid & (bs.pdf > 0), w_b * le_b * mis_b, zero)
            dist_b = dr.select(si_b.is_valid(), si_b.t, math.inf)
            t = dr.select(valid, si.t, math.inf)
            # Which aggregates the camera ray (in front of the mesh) and the two shadow rays
            # may meet.
            return (o, d, w, t, le, c_e, ds.d, dist_e, c_b, d_b, dist_b, si.p,
                    self._cull(o, d, t),
                    self._cull(si.p, ds.d, dist_e), self._cull(si.p, d_b, dist_b))
        return fn

    def _interaction(self, p):
        it = dr.zeros(mi.Interaction3f, dr.width(p)) if _jit() else dr.zeros(mi.Interaction3f)
        it.p = p
        return it

    def _agg_light(self, scene):
        jit = _jit()

        def fn(p, u_e):
            it = self._interaction(p)
            ds, em_w = scene.sample_emitter_direction(it, u_e, True)
            inf = (mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite) if jit
                   else _infinite(ds.emitter))
            dist = dr.select(inf, math.inf, ds.dist)
            return ds.d, em_w, ds.pdf, ds.delta, dist, self._cull(p, ds.d, dist)
        return fn

    def _agg_bsdf(self, scene):
        jit = _jit()

        def fn(p, d):
            it = self._interaction(p)
            si = scene.ray_intersect(mi.Ray3f(p, d))
            em = si.emitter(scene)
            le = _emit(em, si)
            if jit or em is not None:
                pdf_e = scene.pdf_emitter_direction(it, mi.DirectionSample3f(scene, si, it))
            else:
                pdf_e = 0.0
            dist = dr.select(si.is_valid(), si.t, math.inf)
            return le, pdf_e, dist, self._cull(p, d, dist)
        return fn

    # -- aggregates ---------------------------------------------------------------------------

    def _through_others(self, skip, p, d, tmax, aperture, mask, instance=None):
        """Transmittance of every aggregate but `skip` along world rays (shadow cones); of
        aggregate `skip`, when it is an assembly, every instance but `instance` (per ray).
        `mask`: the rays' culling bits (`_cull`): an aggregate sees only the rays that may
        meet it."""
        t = np.ones(len(p))
        for j, a in enumerate(self.aggregates):
            if a.bounds is None or not len(p):
                continue
            own = j == skip
            if own and not (a.assembly and a.scene.instances > 1):
                continue
            k = np.nonzero(_meets(mask, j))[0]
            if not len(k):
                continue
            t[k] *= a.transmittance(p[k], d[k], aperture, tmax[k],
                                    instance[k].astype(np.int64) if own else None,
                                    self.lod_bias)
        return t

    def _shade_hits(self, scene, rng, agg_of, inst, level, key, p, wo, aperture):
        """Reflected radiance of M aggregate hits (aggregate, instance, level, key) towards
        wo (world), lit by Mitsuba's emitters: one emitter sample and one ABSDF sample, MIS."""
        m = len(p)
        out = np.zeros((m, 3))
        if m == 0:
            return out
        u_e = rng.random((m, 2), dtype=np.float32)
        d_e, em_w, pdf_e, delta, dist_e, mask_e = _batch(self._agg_light(scene), m,
                                                         (p, "p3"), (u_e, "p2"))
        u_b = rng.random((m, 3), dtype=np.float32)
        lit = (em_w.max(axis=1) > 0) & (pdf_e > 0)
        for j, a in enumerate(self.aggregates):
            sel = np.nonzero(agg_of == j)[0]
            if len(sel) == 0:
                continue
            ins = inst[sel]
            # One call: the ABSDF towards the light sample, an ABSDF sample, and the interior
            # visibility of both directions (zero rows: no light sample).
            wi_e = np.where(lit[sel, None], a.dir_to_local(d_e[sel]), 0.0).astype(np.float32)
            r = a.scene.voxel_shade(level[sel], key[sel], a.dir_to_local(wo[sel]), wi_e,
                                    u_b[sel], ins)
            # Emitter sample.
            k = np.nonzero(lit[sel])[0]
            if len(k):
                s = sel[k]
                tr = self._through_others(j, p[s], d_e[s], dist_e[s], aperture, mask_e[s],
                                          ins[k])
                mis = np.where(delta[s].astype(bool), 1.0,
                               _power_np(pdf_e[s], r["light_pdf"][k]))
                out[s] += r["light_value"][k] * em_w[s] * (
                    r["light_visibility"][k] * tr * mis)[:, None]
            # ABSDF sample.
            k = np.nonzero(r["pdf"] > 0)[0]
            if len(k):
                s = sel[k]
                pdf = r["pdf"][k]
                d_w = a.dir_to_world(r["wi"][k]).astype(np.float32)
                le, pdf_l, dist, mask_b = _batch(self._agg_bsdf(scene), len(s), (p[s], "p3"),
                                                 (d_w, "v3"))
                tr = self._through_others(j, p[s], d_w, dist, aperture, mask_b, ins[k])
                mis = _power_np(pdf, pdf_l)
                out[s] += r["value"][k] * le * (r["visibility"][k] * tr * mis / pdf)[:, None]
        return out

    def _aggregate_layers(self, scene, rng, o, d, t_mesh, aperture, mask, groups=()):
        """Per aggregate: (entry distance, surfaces' radiance, transmittance) of every ray.
        The runtime picks one primitive per cone in proportion to its weight (`Scene.pick`:
        an assembly's instances composed into one layer) and gives the weights' sum, an
        unbiased estimate of Eq. 30's sum with the picked primitive's radiance. `mask`: the
        rays' culling bits (`_cull`; the others meet nothing of the aggregate). `groups`:
        arrays (G, k) of rows of ray indices with the same camera ray, one walk a row (its
        first ray's) and a pick for each; the rays in no row walk alone."""
        n = len(o)
        alone = np.ones(n, bool)
        for g in groups:
            alone[g.ravel()] = False
        one = np.nonzero(alone)[0]
        picks, layers = [], []
        for j, a in enumerate(self.aggregates):
            if a.bounds is None:
                continue
            meets = _meets(mask, j)
            weight = np.zeros(n, np.float32)
            trans = np.ones(n, np.float32)
            entry = np.full(n, np.inf)
            picked = np.zeros(n, bool)
            hit = {"instance": np.zeros(n, np.uint32), "level": np.zeros(n, np.uint32),
                   "key": np.zeros(n, np.uint64), "t": np.zeros(n, np.float32)}
            # The same numbers for every ray, culled or not: the culling changes no bits.
            calls = [(one, rng.random(len(one), dtype=np.float32))] if len(one) else []
            calls += [(g, rng.random(g.shape, dtype=np.float32)) for g in groups]
            for rows, u in calls:
                keep = meets[rows if rows.ndim == 1 else rows[:, 0]]
                rows, u = rows[keep], u[keep]
                if not len(rows):
                    continue
                w = rows if rows.ndim == 1 else rows[:, 0]
                got = a.scene.pick(a.point_to_local(o[w]), a.dir_to_local(d[w]), aperture, u,
                                   a.t_to_local(t_mesh[w]), self.lod_bias)
                rows = rows.ravel()
                wt = got["weight"].ravel()
                weight[rows] = wt
                trans[rows] = got["transmittance"].ravel()
                entry[rows] = got["entry"].ravel().astype(np.float64) * a.scale
                k = np.nonzero(wt > 0)[0]
                picked[rows[k]] = True
                for x, v in hit.items():
                    v[rows[k]] = got[x].ravel()[k]
            rays = np.nonzero(picked)[0]
            ins, lv, ky, t = (hit[x][rays] for x in ("instance", "level", "key", "t"))
            p = o[rays] + (t.astype(np.float64) * a.scale)[:, None] * d[rays]
            picks.append((j, rays, ins, lv, ky, p))
            layers.append([entry, np.zeros((n, 3), np.float32), trans, weight])
        if not picks:
            return []
        agg_of = np.concatenate([np.full(len(r), j) for j, r, *_ in picks])
        inst = np.concatenate([x[2] for x in picks])
        level = np.concatenate([x[3] for x in picks])
        key = np.concatenate([x[4] for x in picks])
        p = np.concatenate([x[5] for x in picks]).astype(np.float32)
        rays = np.concatenate([x[1] for x in picks])
        wo = (-d[rays]).astype(np.float32)
        lo = self._shade_hits(scene, rng, agg_of, inst, level, key, p, wo, aperture)
        start = 0
        for (j, r, *_), layer in zip(picks, layers):
            layer[1][r] = lo[start:start + len(r)] * layer[3][r][:, None]
            start += len(r)
        return [(e, s, t) for e, s, t, _ in layers]

    # -- the image ----------------------------------------------------------------------------

    def _pass(self, scene, sensor, rng, xy, full, aperture, blocks=1, share=None):
        """Radiance of the rays of `blocks` samples of every pixel (`xy`, block-major);
        pixel p's `share[p]` consecutive blocks share its camera ray and the aggregates' walk
        (each sample still draws its own pick, light and BSDF samples)."""
        n = len(xy)
        npix = n // blocks
        jitter = rng.random((n, 2), dtype=np.float32)
        groups = []
        if share is not None:
            for sh in np.unique(share):
                # The longest run that divides the pass's blocks (its last pass may be short).
                r = int(sh)
                while blocks % r:
                    r //= 2
                if r <= 1:
                    continue
                pix = np.nonzero(share == sh)[0]
                # Rows of r rays: one pixel's samples r·j … r·j + r − 1 of the pass.
                g = (np.arange(blocks).reshape(blocks // r, 1, r) * npix
                     + pix[None, :, None]).reshape(-1, r)
                jitter[g[:, 1:]] = jitter[g[:, :1]]
                groups.append(g)
        pos = (xy + jitter) / full
        u = rng.random((n, 5), dtype=np.float32)
        (o, d, w, t_mesh, le, c_e, d_e, dist_e, c_b, d_b, dist_b, p_m, mask, mask_e,
         mask_b) = _batch(self._mesh(scene, sensor), n, (pos, "p2"), (u[:, :2], "p2"),
                          (u[:, 2], "f"), (u[:, 3:], "p2"))
        # Aggregates shadow meshes: shadow cones from the mesh points towards the light (the
        # emitter sample's and the BSDF sample's, unit directions from Mitsuba, in one call).
        tr_e, tr_b = np.ones(n, np.float32), np.ones(n, np.float32)
        if self.aggregates:
            hit = np.isfinite(t_mesh)
            if len(self.aggregates) <= _MASK_BITS:  # only the rays that may meet one
                hit_e, hit_b = hit & (mask_e != 0), hit & (mask_b != 0)
            else:
                hit_e = hit_b = hit
            s_e = np.nonzero(hit_e & (c_e.max(axis=1) > 0))[0]
            s_b = np.nonzero(hit_b & (c_b.max(axis=1) > 0))[0]
            if len(s_e) + len(s_b):
                s = np.concatenate([s_e, s_b])
                tr = self._through_others(
                    -1, p_m[s], np.concatenate([d_e[s_e], d_b[s_b]]),
                    np.concatenate([dist_e[s_e], dist_b[s_b]]), aperture,
                    np.concatenate([mask_e[s_e], mask_b[s_b]]))
                tr_e[s_e], tr_b[s_b] = tr[:len(s_e)], tr[len(s_e):]
        radiance = le + c_e * tr_e[:, None] + c_b * tr_b[:, None]
        # Aggregates in front of the mesh (or the background), front to back.
        layers = self._aggregate_layers(scene, rng, o, d, t_mesh, aperture, mask, groups)
        if len(layers) == 1:
            radiance = layers[0][1] + layers[0][2][:, None] * radiance
        elif layers:
            entry = np.stack([e for e, _, _ in layers])
            order = np.argsort(-entry, axis=0)  # farthest first
            rows = np.arange(n)
            for k in range(len(layers)):
                idx = order[k]
                s = np.stack([l[1] for l in layers])[idx, rows]
                t = np.stack([l[2] for l in layers])[idx, rows]
                radiance = s + t[:, None] * radiance
        return radiance * w

    def _shares(self, sensor, xy, full, aperture, spp):
        """Samples of each pixel sharing one walk, as the runtime's image loop shares them
        (`aggtool.samples_per_walk`): by the least magnification (`Scene.magnification`) of
        the aggregates the pixel's centre ray meets."""
        npix = len(xy)
        if self.samples_per_walk:
            return np.full(npix, self.samples_per_walk, np.int64)
        m = np.full(npix, -1, np.int32)
        if self.aggregates and npix:
            o, d, _ = _batch(self._camera(sensor), npix,
                             (((xy + 0.5) / full).astype(np.float32), "p2"))
            d = _normalize(d)
            for a in self.aggregates:
                if a.bounds is None:
                    continue
                k = a.scene.magnification(a.point_to_local(o), a.dir_to_local(d), aperture,
                                          self.lod_bias)
                m = np.where((k >= 0) & ((m < 0) | (k < m)), k, m)
        return aggtool.samples_per_walk(spp, m)

    def _set_culls(self, scene, sensor, aperture):
        """Each aggregate's culling box for this render's cones (`_cull`): its `walk_bounds`
        for cones of the pixel's aperture whose ray parameter stays below the diagonal of the
        box around the scene's shapes, the camera's ray origins (the film's corners) and the
        aggregates, which bounds the length of any cone from a point in the scene to a point
        of an aggregate (world box, padded; None where nothing can be met)."""
        corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32)
        o, _, _ = _batch(self._camera(sensor), 4, (corners, "p2"))
        pts = [np.asarray(o, np.float64).reshape(-1, 3)]
        bb = scene.bbox()
        lo, hi = np.array(bb.min, np.float64), np.array(bb.max, np.float64)
        if np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all():
            pts.append(np.stack([lo, hi]))
        pts += [np.array(a.reach) for a in self.aggregates if a.reach is not None]
        pts = np.concatenate(pts)
        diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        self._culls = []
        for a in self.aggregates:
            wb = a.scene.walk_bounds(aperture, diag / a.scale, self.lod_bias) if (
                math.isfinite(diag)) else a.scene.walk_bounds()
            self._culls.append(None if wb is None else _world_box(a.to_world, wb))

    def render(self, scene, sensor, seed=0, spp=0, develop=True, evaluate=True):
        if not isinstance(sensor, mi.Sensor):
            sensor = scene.sensors()[sensor]
        film = sensor.film()
        film.prepare([])
        size = np.array(film.crop_size())
        offset = np.array(film.crop_offset())
        full = np.array(film.size(), dtype=np.float64)
        spp = int(spp) if spp else int(sensor.sampler().sample_count())
        ys, xs = np.mgrid[0:size[1], 0:size[0]]
        xy = np.stack([xs.ravel() + offset[0], ys.ravel() + offset[1]], axis=1).astype(np.float64)
        # The pixel's angle, from two neighbouring centre rays: the cones' aperture.
        c = (full / 2 + 0.5)
        mid = np.array([c, c + [1.0, 0.0]]) / full
        _, dd, _ = _batch(self._camera(sensor), 2, (mid.astype(np.float32), "p2"))
        dd = _normalize(dd)
        aperture = float(np.arccos(np.clip(np.dot(dd[0], dd[1]), -1.0, 1.0)))
        self._set_culls(scene, sensor, aperture)
        # Several samples per pixel in one batch, up to `batch_rays` rays.
        npix = len(xy)
        share = self._shares(sensor, xy, full, aperture, spp)
        top = int(share.max()) if npix else 1
        per = max(top, (self.batch_rays // max(npix, 1)) // top * top)
        acc = np.zeros((npix, 3))
        # Film positions in float32, as the phases take them.
        xy32, full32 = xy.astype(np.float32), full.astype(np.float32)
        done, b = 0, 0
        while done < spp:
            k = min(per, spp - done)
            rng = np.random.default_rng([int(seed), b])
            out = self._pass(scene, sensor, rng, np.tile(xy32, (k, 1)), full32, aperture, k,
                             share)
            acc += out.reshape(k, npix, 3).sum(axis=0)
            done, b = done + k, b + 1
        img = (acc / spp).reshape(size[1], size[0], 3)
        channels = np.array(film.develop()).shape[-1]
        if channels > 3:
            img = np.concatenate([img, np.ones(img.shape[:2] + (channels - 3,))], axis=-1)
        return mi.TensorXf(np.ascontiguousarray(img, np.float32))

    def sample(self, scene, sampler, ray, medium=None, active=True):
        raise RuntimeError("aggtool_lod renders whole images in batches (mi.render); "
                           "sample() per ray is not supported")

    def to_string(self):
        return "AggtoolLod[" + ", ".join(str(a.path) for a in self.aggregates) + "]"


_CLASSES = {}


def integrator_class():
    """The integrator's class for the active variant (each variant has its own
    `mi.SamplingIntegrator`, so a class made under one cannot serve another)."""
    v = mi.variant()
    if v not in _CLASSES:
        methods = {k: f for k, f in vars(_AggtoolLod).items()
                   if k not in ("__dict__", "__weakref__")}
        _CLASSES[v] = type("AggtoolLod", (mi.SamplingIntegrator,), methods)
    return _CLASSES[v]


def AggtoolLod(props=None, aggregates=None):  # noqa: N802 - reads as the class it makes
    """An `aggtool_lod` integrator for the active variant: from Mitsuba properties (what
    `mi.load_dict` passes) and/or a list of [`Aggregate`]s."""
    return integrator_class()(props, aggregates)


def register():
    """Registers `aggtool_lod` for the active Mitsuba variant (call after mi.set_variant;
    importing this module does it for the variant active then)."""
    mi.register_integrator("aggtool_lod", lambda props: AggtoolLod(props))


if mi.variant() is not None:
    register()
