//! `aggtool._native`: the Python module of the aggtool LoD runtime (PyO3, abi3 for CPython
//! 3.11 and later). Re-exported by `aggtool/__init__.py`:
//!
//! - `aggtool.open(path)` → `Scene` with `.bounds`, `.levels`, `.inspect()` and
//!   `.trace(origins, directions, aperture, lights=None, seed=0)` → (N, 4) float32 (radiance
//!   RGB and background transmittance per cone), which releases the GIL while it traces;
//!   `tmax` clips each cone at a host's own surface and `background=False` leaves the
//!   environment out, for compositing over what lies behind;
//! - the traversal layer for hosts that shade aggregate hits themselves (as the Mitsuba host
//!   does): `.pick(...)` (one primitive per cone picked by weight, with the layer's weight sum
//!   and transmittance; an assembly's instances composed into one layer), `.hits(...)` (every
//!   primitive each cone meets: level, Morton key, t, coverage weight, and the
//!   transmittance), `.transmittance(...)` (shadow cones, optionally leaving an instance out),
//!   `.voxel_eval(...)`, `.voxel_sample(...)` and `.voxel_visibility(...)` (by instance for an
//!   assembly), all batched over numpy arrays with the GIL released;
//! - `aggtool.Lights(constant=(1, 1, 1), sun_direction=None, sun_irradiance=None)` and
//!   `.set_environment(pixels (H, W, 3) float32, intensity=1, rotation_deg=0)`;
//! - `aggtool.convert(source, output=None, preset="default", progress=None, **overrides)` →
//!   output path; `aggtool.presets()` → {name: {setting: value}}, `aggtool.preset_table()`
//!   (what `aggtool presets --json` prints) and
//!   `aggtool.bake_settings(preset="default", **overrides)` → {setting: value}, from the
//!   library's one preset table and settings mapping (`aggtool::bake`).
//!
//! Errors are `aggtool.AggError` (a `ValueError`) naming the file and the reason; wrong
//! dtypes and shapes are `TypeError`/`ValueError` from the argument checks.

use std::path::PathBuf;

use aggtool::assembly::{Opened, VoxelShade};
use aggtool::bsdf::Bsdf;
use aggtool::lights::{EnvMap, Environment, Lights as RtLights, Sun};
use aggtool::runtime::{Cone, LayerHit, LodScene, TraceSettings, VoxelHandle};
use glam::Vec2;
use glam::Vec3;
use numpy::{
    PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArrayMethods,
};
use pyo3::create_exception;
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;

create_exception!(
    _native,
    AggError,
    PyValueError,
    "A file could not be read, verified or written."
);

/// A float32 numpy vector and any numpy array handed back to Python.
type F32s<'py> = Bound<'py, PyArray1<f32>>;
type Array<'py> = Bound<'py, PyAny>;

fn agg_err(msg: impl std::fmt::Display) -> PyErr {
    AggError::new_err(msg.to_string())
}

/// An opened `.agg` aggregate or assembly manifest: levels are read and verified when cones
/// first need them.
#[pyclass(frozen, module = "aggtool")]
struct Scene {
    scene: Opened,
    path: PathBuf,
}

/// Lights for `Scene.trace`: a constant or equirectangular environment and an optional sun.
#[pyclass(module = "aggtool")]
#[derive(Clone)]
struct Lights {
    lights: RtLights,
}

fn vec3(v: Option<[f32; 3]>, what: &str) -> PyResult<Option<Vec3>> {
    match v {
        None => Ok(None),
        Some(a) => {
            let v = Vec3::from(a);
            if !v.is_finite() {
                return Err(PyValueError::new_err(format!("{what} must be finite")));
            }
            Ok(Some(v))
        }
    }
}

#[pymethods]
impl Lights {
    #[new]
    #[pyo3(signature = (constant = [1.0, 1.0, 1.0], sun_direction = None, sun_irradiance = None))]
    fn new(
        constant: [f32; 3],
        sun_direction: Option<[f32; 3]>,
        sun_irradiance: Option<[f32; 3]>,
    ) -> PyResult<Self> {
        let c = vec3(Some(constant), "constant")?.unwrap_or(Vec3::ONE);
        if c.min_element() < 0.0 {
            return Err(PyValueError::new_err("constant must be non-negative"));
        }
        let mut lights = RtLights::constant(c);
        match (
            vec3(sun_direction, "sun_direction")?,
            vec3(sun_irradiance, "sun_irradiance")?,
        ) {
            (Some(d), Some(e)) => {
                let d = d
                    .try_normalize()
                    .ok_or_else(|| PyValueError::new_err("sun_direction has zero length"))?;
                if e.min_element() < 0.0 {
                    return Err(PyValueError::new_err("sun_irradiance must be non-negative"));
                }
                lights.sun = Some(Sun {
                    direction: d,
                    irradiance: e,
                });
            }
            (None, None) => {}
            _ => {
                return Err(PyValueError::new_err(
                    "give both sun_direction and sun_irradiance, or neither",
                ))
            }
        }
        Ok(Lights { lights })
    }

    /// Sets an equirectangular environment map from an (H, W, 3) float32 array (row 0 at the
    /// top, linear RGB), scaled by `intensity` and rotated by `rotation_deg` about +y, as view
    /// files have it.
    #[pyo3(signature = (pixels, intensity = 1.0, rotation_deg = 0.0))]
    fn set_environment(
        &mut self,
        pixels: PyReadonlyArray3<'_, f32>,
        intensity: f32,
        rotation_deg: f32,
    ) -> PyResult<()> {
        let shape = pixels.shape();
        if shape[2] != 3 || shape[0] == 0 || shape[1] == 0 {
            return Err(PyValueError::new_err(format!(
                "pixels must have shape (H, W, 3), not {shape:?}"
            )));
        }
        if !intensity.is_finite() || intensity < 0.0 || !rotation_deg.is_finite() {
            return Err(PyValueError::new_err(
                "intensity and rotation_deg must be finite",
            ));
        }
        let a = pixels.as_array();
        let mut px = Vec::with_capacity(shape[0] * shape[1]);
        for y in 0..shape[0] {
            for x in 0..shape[1] {
                let v = Vec3::new(a[[y, x, 0]], a[[y, x, 1]], a[[y, x, 2]]);
                if !v.is_finite() || v.min_element() < 0.0 {
                    return Err(PyValueError::new_err(
                        "environment pixels must be finite and non-negative",
                    ));
                }
                px.push(v);
            }
        }
        self.lights.environment = Environment::Map(EnvMap::new(
            shape[1] as u32,
            shape[0] as u32,
            &px,
            intensity,
            rotation_deg,
        ));
        Ok(())
    }
}

/// A 1-D array as a slice: C-contiguous, and with `n` elements when `n` is given.
fn column<'a, T: numpy::Element>(
    a: &'a PyReadonlyArray1<'_, T>,
    what: &str,
    n: Option<usize>,
) -> PyResult<&'a [T]> {
    let s = a
        .as_slice()
        .map_err(|_| PyValueError::new_err(format!("{what} must be C-contiguous")))?;
    match n {
        Some(n) if s.len() != n => Err(PyValueError::new_err(format!(
            "{what} must have shape ({n},), not ({},)",
            s.len()
        ))),
        _ => Ok(s),
    }
}

fn rows3<'a>(a: &'a PyReadonlyArray2<'_, f32>, what: &str) -> PyResult<(usize, &'a [f32])> {
    let shape = a.shape();
    if shape[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "{what} must have shape (N, 3), not {shape:?}"
        )));
    }
    let s = a
        .as_slice()
        .map_err(|_| PyValueError::new_err(format!("{what} must be C-contiguous")))?;
    Ok((shape[0], s))
}

impl Scene {
    /// The single aggregate the traversal layer works on.
    fn lod(&self) -> PyResult<&LodScene> {
        self.scene.aggregate().ok_or_else(|| {
            agg_err(format!(
                "{}: an assembly: hits takes one aggregate (open an asset's .agg); pick, \
                 voxel_*, trace and transmittance take either",
                self.path.display()
            ))
        })
    }

    /// A level that failed verification while tracing, as an `AggError` naming the file.
    fn check(&self) -> PyResult<()> {
        match self.scene.first_error() {
            Some(e) => Err(agg_err(format!("{}: {e}", self.path.display()))),
            None => Ok(()),
        }
    }

    /// The instances of M voxels: `instance` (M,) uint32 as `pick` gives them, checked
    /// against the instance count; all 0 for an aggregate when omitted (an assembly needs
    /// them).
    fn instance_ids(
        &self,
        instance: Option<&PyReadonlyArray1<'_, u32>>,
        m: usize,
    ) -> PyResult<Vec<u32>> {
        let Some(a) = instance else {
            return match self.scene {
                Opened::Aggregate(_) => Ok(vec![0; m]),
                Opened::Assembly(_) => Err(PyValueError::new_err(
                    "an assembly's voxels need `instance` (as `pick` gives it)",
                )),
            };
        };
        let s = column(a, "instance", Some(m))?;
        let count = self.scene.instance_count();
        if let Some(i) = s.iter().position(|&x| x as usize >= count) {
            return Err(PyValueError::new_err(format!(
                "instance {i}: {} is out of range ({count} instances)",
                s[i]
            )));
        }
        Ok(s.to_vec())
    }

    /// The per-voxel results, or an error naming the first voxel that does not exist.
    fn found<T>(&self, r: Vec<Option<T>>, lv: &[u32], ky: &[u64]) -> PyResult<Vec<T>> {
        self.check()?;
        if let Some(i) = r.iter().position(|x| x.is_none()) {
            return Err(agg_err(format!(
                "{}: voxel {i}: no voxel with key {} at level {}",
                self.path.display(),
                ky[i],
                lv[i]
            )));
        }
        Ok(r.into_iter().flatten().collect())
    }
}

/// Cones of a batch: `origins` and `directions` (N, 3), one full `aperture`, and optionally
/// `tmax` (N,) (non-negative; inf for no limit).
/// `trace`'s pixel ids: (n,) uint64, or int64 (numpy's default integers) without negatives.
fn pixel_ids(p: &Bound<'_, PyAny>, n: usize) -> PyResult<Vec<u64>> {
    let ids: Vec<u64> = if let Ok(a) = p.extract::<PyReadonlyArray1<'_, u64>>() {
        a.as_array().to_vec()
    } else if let Ok(a) = p.extract::<PyReadonlyArray1<'_, i64>>() {
        let a = a.as_array();
        if a.iter().any(|&x| x < 0) {
            return Err(PyValueError::new_err("pixels must not be negative"));
        }
        a.iter().map(|&x| x as u64).collect()
    } else {
        return Err(PyTypeError::new_err(
            "pixels must be a 1-D numpy array of int64 or uint64",
        ));
    };
    if ids.len() != n {
        return Err(PyValueError::new_err(format!(
            "pixels must have shape ({n},), not ({},)",
            ids.len()
        )));
    }
    Ok(ids)
}

fn cones(
    origins: &PyReadonlyArray2<'_, f32>,
    directions: &PyReadonlyArray2<'_, f32>,
    aperture: f32,
    tmax: Option<&PyReadonlyArray1<'_, f32>>,
) -> PyResult<Vec<Cone>> {
    let (n, o) = rows3(origins, "origins")?;
    let (m, d) = rows3(directions, "directions")?;
    if n != m {
        return Err(PyValueError::new_err(format!(
            "{n} origins but {m} directions"
        )));
    }
    check_aperture(aperture)?;
    let tmax = tmax.map(|t| column(t, "tmax", Some(n))).transpose()?;
    let mut cones = Vec::with_capacity(n);
    for i in 0..n {
        let (oi, di) = (Vec3::from_slice(&o[3 * i..]), Vec3::from_slice(&d[3 * i..]));
        let di = di
            .try_normalize()
            .filter(|_| oi.is_finite())
            .ok_or_else(|| {
                PyValueError::new_err(format!("cone {i}: non-finite or zero-length ray"))
            })?;
        let mut c = Cone::new(oi, di, aperture);
        if let Some(t) = tmax {
            if !(t[i] >= 0.0) {
                return Err(PyValueError::new_err(format!(
                    "cone {i}: tmax must be non-negative (inf for no limit), not {}",
                    t[i]
                )));
            }
            c.tmax = t[i];
        }
        cones.push(c);
    }
    Ok(cones)
}

/// A cone's full aperture: finite and non-negative.
fn check_aperture(aperture: f32) -> PyResult<()> {
    if aperture.is_finite() && aperture >= 0.0 {
        Ok(())
    } else {
        Err(PyValueError::new_err(
            "aperture must be finite and non-negative",
        ))
    }
}

/// The runtime's settings with `lod_bias` (levels in [-8, 8]).
fn trace_settings(lod_bias: f32) -> PyResult<TraceSettings> {
    if !(lod_bias.is_finite() && (-8.0..=8.0).contains(&lod_bias)) {
        return Err(PyValueError::new_err(format!(
            "lod_bias must be a number of levels between -8 and 8, not {lod_bias}"
        )));
    }
    Ok(TraceSettings {
        lod_bias,
        ..TraceSettings::default()
    })
}

/// Voxel (`level`, `key`) of the aggregate `instance` draws (checked by `instance_ids`).
fn voxel_of(scene: &Opened, instance: u32, level: u32, key: u64) -> Option<VoxelHandle<'_>> {
    scene
        .instance_scene(instance as usize)?
        .voxel(level as usize, key)
}

/// A voxel's ABSDF sample for local `wo` from the first three of `u` (clamped into [0, 1)):
/// (local ω_i, f̂, pdf), `None` where no direction was drawn.
fn absdf_sample(v: &VoxelHandle<'_>, wo: Vec3, u: &[f32]) -> Option<(Vec3, Vec3, f32)> {
    let x = Vec3::from_slice(u).clamp(Vec3::ZERO, Vec3::splat(1.0 - f32::EPSILON));
    match v.sample(wo, x.x, Vec2::new(x.y, x.z)) {
        Some(s) if s.pdf > 0.0 && s.pdf.is_finite() => Some((s.wi, s.value, s.pdf)),
        _ => None,
    }
}

/// The voxels of a batch: `level` (M,) uint32 and `key` (M,) uint64 of the same length.
fn voxel_ids<'a>(
    level: &'a PyReadonlyArray1<'_, u32>,
    key: &'a PyReadonlyArray1<'_, u64>,
) -> PyResult<(&'a [u32], &'a [u64])> {
    let lv = column(level, "level", None)?;
    let ky = column(key, "key", None)?;
    if lv.len() != ky.len() {
        return Err(PyValueError::new_err(format!(
            "{} levels but {} keys",
            lv.len(),
            ky.len()
        )));
    }
    Ok((lv, ky))
}

/// M unit directions from an (M, 3) array (normalised; non-finite or zero rows refused).
fn unit_rows(a: &PyReadonlyArray2<'_, f32>, what: &str, m: usize) -> PyResult<Vec<Vec3>> {
    let (n, s) = rows3(a, what)?;
    if n != m {
        return Err(PyValueError::new_err(format!(
            "{m} voxels but {n} rows of {what}"
        )));
    }
    (0..n)
        .map(|i| {
            // Idempotent: a direction `voxel_sample` returned evaluates to the same bits in
            // `voxel_eval` (the ABSDF's directional moments are looked up by cell).
            let v = aggtool::math::unit_or_zero(Vec3::from_slice(&s[3 * i..]));
            if v == Vec3::ZERO {
                return Err(PyValueError::new_err(format!(
                    "{what} {i}: non-finite or zero-length"
                )));
            }
            Ok(v)
        })
        .collect()
}

#[pymethods]
impl Scene {
    /// The bounds of the asset the aggregate was baked from, ((x, y, z), (x, y, z)), or None
    /// when it is empty.
    #[getter]
    fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        self.scene
            .bounds()
            .map(|(a, b)| (a.to_array(), b.to_array()))
    }

    /// The box outside which cones meet nothing, ((x, y, z), (x, y, z)), or None when nothing
    /// can be met: for cones of full `aperture` (radians) whose ray parameter stays below
    /// `tmax` (both given: a host bounds tmax by its scene's size), the union of the clip
    /// boxes of the levels their footprints can choose there (`LodScene::walk_bounds`);
    /// without them, every level's (a little larger than `bounds`). An assembly's: its
    /// instances' cubes. Cones whose rays miss it get no hits, weight 0 and transmittance 1
    /// from every call, so a host may skip them (the Mitsuba host culls its rays with it).
    /// `lod_bias` as for `trace`.
    #[pyo3(signature = (aperture = None, tmax = None, lod_bias = 0.0))]
    fn walk_bounds(
        &self,
        aperture: Option<f32>,
        tmax: Option<f32>,
        lod_bias: f32,
    ) -> PyResult<Option<([f32; 3], [f32; 3])>> {
        let settings = trace_settings(lod_bias)?;
        let (aperture, tmax) = match (aperture, tmax) {
            (Some(a), Some(t)) => {
                check_aperture(a)?;
                if !(t >= 0.0) {
                    return Err(PyValueError::new_err(format!(
                        "tmax must be non-negative (inf for no limit), not {t}"
                    )));
                }
                (a, t)
            }
            _ => (0.0, f32::INFINITY),
        };
        Ok(self
            .scene
            .walk_bounds(aperture, tmax, &settings)
            .map(|(a, b)| (a.to_array(), b.to_array())))
    }

    /// Instances: an assembly's, 1 for an aggregate (`pick`'s `instance` indexes them).
    #[getter]
    fn instances(&self) -> usize {
        self.scene.instance_count()
    }

    /// The levels' resolutions, finest first.
    #[getter]
    fn levels(&self) -> Vec<u32> {
        self.scene.level_resolutions()
    }

    /// What `aggtool inspect --json` prints, as a dict; for an assembly, per asset its id,
    /// aggregate, instance count and that summary of its aggregate.
    fn inspect<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let summary = |p: &std::path::Path| -> PyResult<serde_json::Value> {
            let agg = aggtool::format::Aggregate::open(p)
                .map_err(|e| agg_err(format!("{}: {e}", p.display())))?;
            aggtool::report::json_value(&aggtool::inspect::summary(&agg, p)).map_err(agg_err)
        };
        let json = match &self.scene {
            Opened::Aggregate(_) => summary(&self.path)?,
            Opened::Assembly(a) => {
                let m = a.manifest();
                let counts = m.instances_per_asset();
                let assets = m
                    .assets
                    .iter()
                    .zip(&counts)
                    .map(|(x, n)| {
                        Ok(serde_json::json!({
                            "id": x.id,
                            "aggregate": x.aggregate.display().to_string(),
                            "instances": n,
                            "summary": summary(&x.aggregate)?,
                        }))
                    })
                    .collect::<PyResult<Vec<_>>>()?;
                serde_json::json!({
                    "manifest": self.path.display().to_string(),
                    "instances": m.instance_count(),
                    "assets": assets,
                })
            }
        };
        let text = serde_json::to_string(&json).map_err(agg_err)?;
        py.import("json")?.call_method1("loads", (text,))
    }

    /// Traces N cones: `origins` and `directions` (N, 3) float32, one full `aperture` angle
    /// in radians for all; returns (N, 4) float32: radiance RGB and the background's
    /// transmittance. Cone i draws stream i of `seed`. Releases the GIL while tracing.
    /// `tmax`, (N,) float32, clips each cone at that distance along its (unit) direction (a
    /// host's own surface; inf for none); `background=False` leaves the environment's
    /// radiance out of the RGB, so that a host composites: RGB + transmittance · (what lies
    /// behind). `pixels`, (N,) int64 or uint64, distinct within a call (cones with the same
    /// id draw the same numbers), makes cone i sample `sample` of the host's pixel `pixels[i]`, its random numbers stratified over the pixel's samples as the
    /// runtime's own image loop's (call once a pass with the same ids and `sample` = 0, 1,
    /// 2, …: a pixel's mean over passes has about a quarter of the variance of a new `seed`
    /// a pass; C ABI `agg_trace_cones_stratified`).
    /// `lod_bias` (levels, in [-8, 8]) walks coarser levels than the footprint asks for
    /// (`TraceSettings::lod_bias`: 1 is about twice as fast where cones cross many voxels,
    /// and blurrier).
    #[pyo3(signature = (origins, directions, aperture, lights = None, seed = 0, tmax = None, background = true, pixels = None, sample = 0, lod_bias = 0.0))]
    #[allow(clippy::too_many_arguments)]
    fn trace<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f32>,
        directions: PyReadonlyArray2<'py, f32>,
        aperture: f32,
        lights: Option<PyRef<'py, Lights>>,
        seed: u64,
        tmax: Option<PyReadonlyArray1<'py, f32>>,
        background: bool,
        pixels: Option<Bound<'py, PyAny>>,
        sample: u32,
        lod_bias: f32,
    ) -> PyResult<Bound<'py, PyAny>> {
        let settings = trace_settings(lod_bias)?;
        let cones = cones(&origins, &directions, aperture, tmax.as_ref())?;
        let n = cones.len();
        let pixels = pixels.map(|p| pixel_ids(&p, n)).transpose()?;
        let lights = lights
            .map(|l| l.lights.clone())
            .unwrap_or_else(|| RtLights::constant(Vec3::ONE));
        let scene = &self.scene;
        let out: Vec<f32> = py.detach(|| {
            let mut out = vec![0f32; 4 * n];
            match &pixels {
                Some(p) => {
                    let at = aggtool::runtime::PixelSamples { pixels: p, sample };
                    scene.trace_batch_stratified(&cones, at, &lights, &settings, seed, &mut out)
                }
                None => scene.trace_batch(&cones, &lights, &settings, seed, &mut out),
            }
            if !background {
                // The runtime composes surfaces + environment · T; take the environment back
                // out (relative rounding of f32, far below the estimate's noise).
                for (o, c) in out.chunks_mut(4).zip(&cones) {
                    let e = lights.environment.eval(c.dir) * o[3];
                    for k in 0..3 {
                        o[k] = (o[k] - e[k]).max(0.0);
                    }
                }
            }
            out
        });
        self.check()?;
        let a = PyArray1::from_vec(py, out);
        Ok(a.reshape([n, 4])?.into_any())
    }

    /// The traversal layer, for hosts that shade aggregate hits themselves: every primitive
    /// each cone meets, in order (`LodScene::hits`, the C ABI's `agg_hits`). Cones as for
    /// `trace` (`tmax` clips them). Returns a dict of numpy arrays: `offsets` (N + 1,) int64
    /// (cone i's hits are rows offsets[i]:offsets[i+1]), per hit `level` uint32 (0 = finest),
    /// `key` uint64 (Morton key in the level), `t` float32 (where the centre ray enters the
    /// primitive), `weight` float32 (the coverage V̂(ω_o)·|A|_ω/|B|_ω of Eq. 30, attenuated
    /// by the surfaces in front as the runtime's shading does), and per cone `transmittance`
    /// float32 (the background's weight: the ABV of the entry face, attenuated likewise; 1
    /// when the cone met nothing). Divided by their sum they are the runtime's normalised
    /// weights. Releases the GIL.
    #[pyo3(signature = (origins, directions, aperture, tmax = None))]
    fn hits<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f32>,
        directions: PyReadonlyArray2<'py, f32>,
        aperture: f32,
        tmax: Option<PyReadonlyArray1<'py, f32>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let cones = cones(&origins, &directions, aperture, tmax.as_ref())?;
        let scene = self.lod()?;
        type ConeHits = (Vec<(u32, u64, f32, f32)>, f32);
        let per: Vec<ConeHits> = py.detach(|| {
            let settings = TraceSettings::default();
            cones
                .par_iter()
                .map(|c| {
                    let mut h = scene.hits(c, &settings);
                    let v = (&mut h)
                        .map(|x| (x.voxel.level() as u32, x.voxel.key(), x.t, x.weight))
                        .collect();
                    (v, h.transmittance())
                })
                .collect()
        });
        self.check()?;
        let m: usize = per.iter().map(|p| p.0.len()).sum();
        let mut offsets = Vec::with_capacity(per.len() + 1);
        let (mut level, mut key, mut t, mut weight, mut tr) = (
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(per.len()),
        );
        offsets.push(0i64);
        for (hs, trans) in per {
            for (l, k, ht, w) in hs {
                level.push(l);
                key.push(k);
                t.push(ht);
                weight.push(w);
            }
            offsets.push(level.len() as i64);
            tr.push(trans);
        }
        let d = PyDict::new(py);
        d.set_item("offsets", PyArray1::from_vec(py, offsets))?;
        d.set_item("level", PyArray1::from_vec(py, level))?;
        d.set_item("key", PyArray1::from_vec(py, key))?;
        d.set_item("t", PyArray1::from_vec(py, t))?;
        d.set_item("weight", PyArray1::from_vec(py, weight))?;
        d.set_item("transmittance", PyArray1::from_vec(py, tr))?;
        Ok(d)
    }

    /// What the aggregate lets through along each cone (`LodScene::transmittance`): the ABV
    /// of the face a cone enters by, 1 when it meets no primitive before `tmax`. For a host's
    /// shadow cones from its own surfaces towards its lights. (N,) float32; releases the GIL.
    ///
    /// `skip`, (N,) int64, leaves instance skip[i] of an assembly out of cone i (a shadow cone
    /// from a hit on that instance: its own occlusion is in the hit's `voxel_visibility`);
    /// negative for none. `lod_bias` as for `trace`.
    #[pyo3(signature = (origins, directions, aperture, tmax = None, skip = None, lod_bias = 0.0))]
    #[allow(clippy::too_many_arguments)]
    fn transmittance<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f32>,
        directions: PyReadonlyArray2<'py, f32>,
        aperture: f32,
        tmax: Option<PyReadonlyArray1<'py, f32>>,
        skip: Option<PyReadonlyArray1<'py, i64>>,
        lod_bias: f32,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let settings = trace_settings(lod_bias)?;
        let cones = cones(&origins, &directions, aperture, tmax.as_ref())?;
        let skip = skip
            .as_ref()
            .map(|a| column(a, "skip", Some(cones.len())))
            .transpose()?;
        let scene = &self.scene;
        let out: Vec<f32> = py.detach(|| {
            cones
                .par_iter()
                .enumerate()
                .map(|(i, c)| {
                    let skip = skip.and_then(|s| usize::try_from(s[i]).ok());
                    scene.transmittance_skipping(c, &settings, skip)
                })
                .collect()
        });
        self.check()?;
        Ok(PyArray1::from_vec(py, out))
    }

    /// By how many levels the aggregate's finest voxels are wider than each cone
    /// (`LodScene::magnification`): (N,) int32, -1 where the cone misses the aggregate, 0
    /// where it is as wide as the voxels it meets (and for an assembly). The runtime's image
    /// loop shares the walks of a pixel whose cone is m levels narrower among more samples
    /// (`aggtool.samples_per_walk(spp, m)` gives how many); a host that shares walks (`pick`
    /// with `u` of shape (N, k)) can do the same. `lod_bias` as for `trace`.
    #[pyo3(signature = (origins, directions, aperture, lod_bias = 0.0))]
    fn magnification<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f32>,
        directions: PyReadonlyArray2<'py, f32>,
        aperture: f32,
        lod_bias: f32,
    ) -> PyResult<Bound<'py, PyArray1<i32>>> {
        let settings = trace_settings(lod_bias)?;
        let cones = cones(&origins, &directions, aperture, None)?;
        let out: Vec<i32> = cones
            .iter()
            .map(|c| {
                self.scene
                    .magnification(c, &settings)
                    .map_or(-1, |m| m.min(i32::MAX as u32) as i32)
            })
            .collect();
        Ok(PyArray1::from_vec(py, out))
    }

    /// One primitive per cone for a host that shades one hit a cone and composites the
    /// aggregate (or the assembly: every instance in one layer) over what lies behind it, as
    /// the Mitsuba host does. Cones as for `trace` (`tmax` clips them at the host's surface);
    /// `u` (N,) float32 in [0, 1) picks each cone's primitive in proportion to its weight;
    /// `u` (N, k) picks k from each cone's one walk (a pixel's samples sharing a walk, as the
    /// runtime's image loop shares them), and every returned array is then (N, k).
    /// Returns a dict of (N,) numpy arrays:
    /// - `weight` float32: the sum of the layer's weights, the share of the pixel its
    ///   surfaces cover: the picked primitive's radiance times it estimates the layer's
    ///   (`LodScene::layer_into`: the runtime's normalised weights, or unnormalised where the
    ///   cone ends inside the bounds);
    /// - `transmittance` float32: what the layer lets through to what lies behind;
    /// - `entry` float32: where the cone meets its first primitive (inf for none);
    /// - `instance` uint32 (0 for an aggregate), `level` uint32, `key` uint64 and `t` float32:
    ///   the picked primitive (zeros and t = inf where `weight` is 0).
    ///
    /// Distances are the cone's (world units of the opened frame). `lod_bias` as for
    /// `trace`. Releases the GIL.
    #[pyo3(signature = (origins, directions, aperture, u, tmax = None, lod_bias = 0.0))]
    #[allow(clippy::too_many_arguments)]
    fn pick<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f32>,
        directions: PyReadonlyArray2<'py, f32>,
        aperture: f32,
        u: Bound<'py, PyAny>,
        tmax: Option<PyReadonlyArray1<'py, f32>>,
        lod_bias: f32,
    ) -> PyResult<Bound<'py, PyDict>> {
        let settings = trace_settings(lod_bias)?;
        let cones = cones(&origins, &directions, aperture, tmax.as_ref())?;
        let n = cones.len();
        // (N,) one pick a cone, or (N, k) k picks from each cone's walk.
        let (u, k): (Vec<f32>, Option<usize>) =
            if let Ok(a) = u.extract::<PyReadonlyArray1<'_, f32>>() {
                (a.as_array().to_vec(), None)
            } else if let Ok(a) = u.extract::<PyReadonlyArray2<'_, f32>>() {
                let k = a.shape()[1];
                (a.as_array().iter().copied().collect(), Some(k))
            } else {
                return Err(PyTypeError::new_err(
                    "u must be a float32 numpy array of shape (N,) or (N, k)",
                ));
            };
        if u.len() != n * k.unwrap_or(1) || k == Some(0) {
            return Err(PyValueError::new_err(format!(
                "u must have shape ({n},) or ({n}, k) with k ≥ 1, not {} numbers",
                u.len()
            )));
        }
        if let Some(i) = u.iter().position(|x| !x.is_finite()) {
            return Err(PyValueError::new_err(format!("u {i}: not finite")));
        }
        let u = &u[..];
        let scene = &self.scene;
        let picks = py.detach(|| scene.pick_batch(&cones, u, &settings));
        self.check()?;
        let m = picks.len();
        let mut cols = (
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
        );
        for p in picks {
            let h = p.hit.unwrap_or(LayerHit {
                t: f32::INFINITY,
                ..LayerHit::default()
            });
            cols.0.push(p.weight);
            cols.1.push(p.transmittance);
            cols.2.push(p.entry);
            cols.3.push(h.instance);
            cols.4.push(h.level);
            cols.5.push(h.key);
            cols.6.push(h.t);
        }
        let d = PyDict::new(py);
        let shaped = |a: Bound<'py, PyAny>| -> PyResult<Bound<'py, PyAny>> {
            match k {
                Some(k) => Ok(a.call_method1("reshape", ((n, k),))?),
                None => Ok(a),
            }
        };
        d.set_item("weight", shaped(PyArray1::from_vec(py, cols.0).into_any())?)?;
        d.set_item(
            "transmittance",
            shaped(PyArray1::from_vec(py, cols.1).into_any())?,
        )?;
        d.set_item("entry", shaped(PyArray1::from_vec(py, cols.2).into_any())?)?;
        d.set_item(
            "instance",
            shaped(PyArray1::from_vec(py, cols.3).into_any())?,
        )?;
        d.set_item("level", shaped(PyArray1::from_vec(py, cols.4).into_any())?)?;
        d.set_item("key", shaped(PyArray1::from_vec(py, cols.5).into_any())?)?;
        d.set_item("t", shaped(PyArray1::from_vec(py, cols.6).into_any())?)?;
        Ok(d)
    }

    /// The ABSDF of M voxels (`level` (M,) uint32 and `key` (M,) uint64, as `hits` gives
    /// them) for incident `wi` and outgoing `wo` (M, 3) float32 (towards the light and the
    /// viewer, in the aggregate's frame; normalised here): returns (value (M, 3), pdf (M,))
    /// float32, f̂(ω_i, ω_o) (it carries its own cosines: reflected radiance is
    /// ∫ f̂ L_i V̂ dω_i) and the solid-angle pdf of `voxel_sample` drawing ω_i.
    #[pyo3(signature = (level, key, wi, wo, instance = None))]
    fn voxel_eval<'py>(
        &self,
        py: Python<'py>,
        level: PyReadonlyArray1<'py, u32>,
        key: PyReadonlyArray1<'py, u64>,
        wi: PyReadonlyArray2<'py, f32>,
        wo: PyReadonlyArray2<'py, f32>,
        instance: Option<PyReadonlyArray1<'py, u32>>,
    ) -> PyResult<(Array<'py>, F32s<'py>)> {
        let (lv, ky) = voxel_ids(&level, &key)?;
        let wi = unit_rows(&wi, "wi", lv.len())?;
        let wo = unit_rows(&wo, "wo", lv.len())?;
        let inst = self.instance_ids(instance.as_ref(), lv.len())?;
        let scene = &self.scene;
        let r: Vec<Option<(Vec3, f32)>> = py.detach(|| {
            (0..lv.len())
                .into_par_iter()
                .map(|i| {
                    let v = voxel_of(scene, inst[i], lv[i], ky[i])?;
                    let j = inst[i] as usize;
                    let (wi, wo) = (
                        scene.direction_to_local(j, wi[i]),
                        scene.direction_to_local(j, wo[i]),
                    );
                    Some(v.eval_pdf(wi, wo))
                })
                .collect()
        });
        let r = self.found(r, lv, ky)?;
        let m = r.len();
        let (mut value, mut pdf) = (Vec::with_capacity(3 * m), Vec::with_capacity(m));
        for (f, p) in r {
            value.extend_from_slice(&f.to_array());
            pdf.push(p);
        }
        Ok((
            PyArray1::from_vec(py, value).reshape([m, 3])?.into_any(),
            PyArray1::from_vec(py, pdf),
        ))
    }

    /// Samples an incident direction of M voxels' ABSDFs for outgoing `wo` (M, 3) from
    /// uniform numbers `u` (M, 3) in [0, 1): returns (wi (M, 3), value (M, 3), pdf (M,))
    /// float32: the direction, f̂(ω_i, ω_o) for it (as `voxel_eval` gives it, not divided by
    /// the pdf) and its solid-angle pdf; pdf 0 (and zeros) where no direction was drawn.
    #[pyo3(signature = (level, key, wo, u, instance = None))]
    fn voxel_sample<'py>(
        &self,
        py: Python<'py>,
        level: PyReadonlyArray1<'py, u32>,
        key: PyReadonlyArray1<'py, u64>,
        wo: PyReadonlyArray2<'py, f32>,
        u: PyReadonlyArray2<'py, f32>,
        instance: Option<PyReadonlyArray1<'py, u32>>,
    ) -> PyResult<(Array<'py>, Array<'py>, F32s<'py>)> {
        let (lv, ky) = voxel_ids(&level, &key)?;
        let wo = unit_rows(&wo, "wo", lv.len())?;
        let (mu, us) = rows3(&u, "u")?;
        if mu != lv.len() {
            return Err(PyValueError::new_err(format!(
                "{} voxels but {mu} rows of u",
                lv.len()
            )));
        }
        if let Some(i) = us.iter().position(|x| !x.is_finite()) {
            return Err(PyValueError::new_err(format!("u {}: not finite", i / 3)));
        }
        let inst = self.instance_ids(instance.as_ref(), lv.len())?;
        let scene = &self.scene;
        let r: Vec<Option<(Vec3, Vec3, f32)>> = py.detach(|| {
            (0..lv.len())
                .into_par_iter()
                .map(|i| {
                    let v = voxel_of(scene, inst[i], lv[i], ky[i])?;
                    let j = inst[i] as usize;
                    let wo = scene.direction_to_local(j, wo[i]);
                    let s = absdf_sample(&v, wo, &us[3 * i..]);
                    Some(match s {
                        Some((wi, value, pdf)) => (scene.direction_to_world(j, wi), value, pdf),
                        None => (Vec3::ZERO, Vec3::ZERO, 0.0),
                    })
                })
                .collect()
        });
        let r = self.found(r, lv, ky)?;
        let m = r.len();
        let (mut wi, mut value, mut pdf) = (
            Vec::with_capacity(3 * m),
            Vec::with_capacity(3 * m),
            Vec::with_capacity(m),
        );
        for (w, f, p) in r {
            wi.extend_from_slice(&w.to_array());
            value.extend_from_slice(&f.to_array());
            pdf.push(p);
        }
        Ok((
            PyArray1::from_vec(py, wi).reshape([m, 3])?.into_any(),
            PyArray1::from_vec(py, value).reshape([m, 3])?.into_any(),
            PyArray1::from_vec(py, pdf),
        ))
    }

    /// The interior visibility of M voxels towards `d` (M, 3) float32: returns (aiv (M,),
    /// incident (M,)) float32, the AIV V̂(d) (Eq. 25) and the visibility the runtime uses for
    /// light arriving from d, min(1, V̂(d)/η): what stands in for a shadow ray inside the
    /// aggregate (a host multiplies it with its own shadow rays outside).
    #[pyo3(signature = (level, key, d, instance = None))]
    fn voxel_visibility<'py>(
        &self,
        py: Python<'py>,
        level: PyReadonlyArray1<'py, u32>,
        key: PyReadonlyArray1<'py, u64>,
        d: PyReadonlyArray2<'py, f32>,
        instance: Option<PyReadonlyArray1<'py, u32>>,
    ) -> PyResult<(F32s<'py>, F32s<'py>)> {
        let (lv, ky) = voxel_ids(&level, &key)?;
        let d = unit_rows(&d, "d", lv.len())?;
        let inst = self.instance_ids(instance.as_ref(), lv.len())?;
        let scene = &self.scene;
        let r: Vec<Option<(f32, f32)>> = py.detach(|| {
            (0..lv.len())
                .into_par_iter()
                .map(|i| {
                    let v = voxel_of(scene, inst[i], lv[i], ky[i])?;
                    let d = scene.direction_to_local(inst[i] as usize, d[i]);
                    Some((v.aiv(d), v.incident_visibility(d)))
                })
                .collect()
        });
        let r = self.found(r, lv, ky)?;
        let (aiv, inc): (Vec<f32>, Vec<f32>) = r.into_iter().unzip();
        Ok((PyArray1::from_vec(py, aiv), PyArray1::from_vec(py, inc)))
    }

    /// What a host needs to shade M picked voxels with one light sample and one ABSDF sample
    /// each (multiple importance sampling), in one pass over the voxels: `voxel_eval` towards
    /// the light, `voxel_sample` for `u`, and `voxel_visibility` of both directions, each
    /// voxel looked up once. `wo` (M, 3) towards the viewer; `wi_light` (M, 3) towards each
    /// voxel's light sample, a zero row where there is none (its outputs are then 0); `u`
    /// (M, 3) uniform numbers in [0, 1) for the ABSDF sample. Directions in the aggregate's
    /// frame, as for the other `voxel_*` calls. Returns a dict of float32 arrays:
    /// - `light_value` (M, 3), `light_pdf` (M,): f̂(ω_light, ω_o) and the pdf of
    ///   `voxel_sample` drawing ω_light (`voxel_eval`);
    /// - `light_visibility` (M,): the incident visibility towards the light (`voxel_visibility`'s
    ///   second output);
    /// - `wi` (M, 3), `value` (M, 3), `pdf` (M,): the ABSDF sample (`voxel_sample`; pdf 0 and
    ///   zeros where no direction was drawn);
    /// - `visibility` (M,): the incident visibility towards `wi`.
    ///
    /// Releases the GIL. The Mitsuba host's per-hit work is this one call between its own
    /// light sampling and its rays towards the sampled directions.
    #[pyo3(signature = (level, key, wo, wi_light, u, instance = None))]
    #[allow(clippy::too_many_arguments)]
    fn voxel_shade<'py>(
        &self,
        py: Python<'py>,
        level: PyReadonlyArray1<'py, u32>,
        key: PyReadonlyArray1<'py, u64>,
        wo: PyReadonlyArray2<'py, f32>,
        wi_light: PyReadonlyArray2<'py, f32>,
        u: PyReadonlyArray2<'py, f32>,
        instance: Option<PyReadonlyArray1<'py, u32>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let (lv, ky) = voxel_ids(&level, &key)?;
        let m = lv.len();
        let wo = unit_rows(&wo, "wo", m)?;
        let (ml, ls) = rows3(&wi_light, "wi_light")?;
        let (mu, us) = rows3(&u, "u")?;
        for (what, rows) in [("wi_light", ml), ("u", mu)] {
            if rows != m {
                return Err(PyValueError::new_err(format!(
                    "{m} voxels but {rows} rows of {what}"
                )));
            }
        }
        for (what, s) in [("wi_light", ls), ("u", us)] {
            if let Some(i) = s.iter().position(|x| !x.is_finite()) {
                return Err(PyValueError::new_err(format!(
                    "{what} {}: not finite",
                    i / 3
                )));
            }
        }
        let inst = self.instance_ids(instance.as_ref(), m)?;
        let scene = &self.scene;
        let r: Vec<Option<VoxelShade>> = py.detach(|| {
            (0..m)
                .into_par_iter()
                .map(|i| {
                    let v = voxel_of(scene, inst[i], lv[i], ky[i])?;
                    let wl = aggtool::math::unit_or_zero(Vec3::from_slice(&ls[3 * i..]));
                    let wl = (wl != Vec3::ZERO).then_some(wl);
                    let u = Vec3::from_slice(&us[3 * i..]);
                    Some(scene.shade_voxel(inst[i] as usize, &v, wo[i], wl, u))
                })
                .collect()
        });
        let r = self.found(r, lv, ky)?;
        let mut cols = (
            Vec::with_capacity(3 * m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(3 * m),
            Vec::with_capacity(3 * m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
        );
        for x in r {
            cols.0.extend_from_slice(&x.light_value.to_array());
            cols.1.push(x.light_pdf);
            cols.2.push(x.light_visibility);
            cols.3.extend_from_slice(&x.wi.to_array());
            cols.4.extend_from_slice(&x.value.to_array());
            cols.5.push(x.pdf);
            cols.6.push(x.visibility);
        }
        let d = PyDict::new(py);
        d.set_item(
            "light_value",
            PyArray1::from_vec(py, cols.0).reshape([m, 3])?,
        )?;
        d.set_item("light_pdf", PyArray1::from_vec(py, cols.1))?;
        d.set_item("light_visibility", PyArray1::from_vec(py, cols.2))?;
        d.set_item("wi", PyArray1::from_vec(py, cols.3).reshape([m, 3])?)?;
        d.set_item("value", PyArray1::from_vec(py, cols.4).reshape([m, 3])?)?;
        d.set_item("pdf", PyArray1::from_vec(py, cols.5))?;
        d.set_item("visibility", PyArray1::from_vec(py, cols.6))?;
        Ok(d)
    }

    fn __repr__(&self) -> String {
        format!(
            "aggtool.Scene({:?}, levels={:?})",
            self.path.display().to_string(),
            self.levels()
        )
    }
}

/// Opens an `.agg` file, or an assembly manifest (`.json`, each aggregate mapped once), lazily:
/// the header and index are verified now, levels on first use.
#[pyfunction]
fn open(path: PathBuf) -> PyResult<Scene> {
    let scene = Opened::open(&path).map_err(|e| agg_err(format!("{}: {e}", path.display())))?;
    Ok(Scene { scene, path })
}

/// The samples each walk of a pixel serves at `spp` samples a pixel, for pixels whose cones
/// `Scene.magnification` gives (`magnification`, (N,) int32; -1, a cone that misses, counts
/// as 0): the runtime image loop's default (`runtime::magnified_reuse`), for a host that
/// shares walks as it does (`Scene.pick` with `u` of shape (N, k)). (N,) int64.
#[pyfunction]
fn samples_per_walk<'py>(
    py: Python<'py>,
    spp: u32,
    magnification: PyReadonlyArray1<'py, i32>,
) -> Bound<'py, PyArray1<i64>> {
    let reuse = TraceSettings::default().walk_reuse(spp);
    let out: Vec<i64> = magnification
        .as_array()
        .iter()
        .map(|&m| aggtool::runtime::magnified_reuse(reuse, spp, m.max(0) as u32) as i64)
        .collect();
    PyArray1::from_vec(py, out)
}

/// Sets the memory budget of the block cache every scene of the process shares, in MiB (the
/// CLI's `render --cache-mib`): prepared blocks of every aggregate stay within it, the least
/// recently used evicted; a smaller budget gives the same results, only slower. The default
/// is a quarter of the machine's memory.
#[pyfunction]
fn set_cache_mib(mib: u64) -> PyResult<()> {
    if mib == 0 {
        return Err(agg_err(
            "the cache budget must be at least 1 MiB".to_string(),
        ));
    }
    aggtool::runtime::BlockCache::global().set_budget(mib.saturating_mul(1 << 20));
    Ok(())
}

/// The block cache's statistics: a dict of budget, loaded, distinct (blocks prepared at least
/// once), evicted, bytes, peak and working_set (about the budget under which each block would
/// be prepared once): bytes and block counts.
#[pyfunction]
fn cache_stats(py: Python<'_>) -> PyResult<Bound<'_, pyo3::types::PyDict>> {
    let c = aggtool::runtime::BlockCache::global().stats();
    let d = pyo3::types::PyDict::new(py);
    d.set_item("budget", c.budget)?;
    d.set_item("loaded", c.loaded)?;
    d.set_item("distinct", c.distinct)?;
    d.set_item("evicted", c.evicted)?;
    d.set_item("bytes", c.bytes)?;
    d.set_item("peak", c.peak)?;
    d.set_item("working_set", c.working_set())?;
    Ok(d)
}

/// A keyword argument of `convert` or `bake_settings` as the typed value
/// `BakeSettings::with_value` takes: a bool, an integer (Python's or numpy's), a float, or a
/// string read as `aggtool convert`'s flags are ("1%").
fn setting_value(name: &str, v: &Bound<'_, PyAny>) -> PyResult<serde_json::Value> {
    use pyo3::types::{PyBool, PyFloat, PyString};
    use serde_json::Value;
    // numpy's bool is not a subclass of Python's.
    let numpy_bool = matches!(v.get_type().name()?.to_string().as_str(), "bool" | "bool_");
    if v.is_instance_of::<PyBool>() || numpy_bool {
        return Ok(Value::Bool(v.extract()?));
    }
    if v.is_instance_of::<PyFloat>() {
        let f: f64 = v.extract()?;
        return serde_json::Number::from_f64(f)
            .map(Value::Number)
            .ok_or_else(|| PyValueError::new_err(format!("{name}={f}: not a finite number")));
    }
    if v.is_instance_of::<PyString>() {
        return Ok(Value::String(v.extract()?));
    }
    // Integers, numpy's among them (through __index__).
    if let Ok(i) = v.extract::<i64>() {
        return Ok(Value::from(i));
    }
    if let Ok(u) = v.extract::<u64>() {
        return Ok(Value::from(u));
    }
    if v.hasattr("__index__")? {
        return Err(PyValueError::new_err(format!("{name}={v}: out of range")));
    }
    Err(PyTypeError::new_err(format!(
        "{name}: expected a bool, an integer, a float or a string, got {}",
        v.get_type().name()?
    )))
}

/// The settings of `preset` with the keyword arguments applied over them, through the one
/// by-name mapping the command line's sweeps also use (`BakeSettings::from_preset`, which
/// validates them together once all are set): an unknown name or a
/// value of the wrong kind is a `TypeError`, an unknown preset or a value out of range a
/// `ValueError`; each names what is valid.
fn settings_of(
    preset: &str,
    overrides: Option<&Bound<'_, PyDict>>,
) -> PyResult<aggtool::bake::BakeSettings> {
    use aggtool::bake::{BakeSettings, SettingError};
    let mut values = Vec::new();
    if let Some(kw) = overrides {
        for (k, v) in kw.iter() {
            let name: String = k.extract()?;
            let value = setting_value(&name, &v)?;
            values.push((name, value));
        }
    }
    BakeSettings::from_preset(preset, &values).map_err(|e| match e {
        SettingError::Unknown { .. } | SettingError::Type { .. } => {
            PyTypeError::new_err(e.to_string())
        }
        _ => PyValueError::new_err(e.to_string()),
    })
}

/// A serialisable value as the Python object `json.loads` makes of it (dicts keep their
/// order).
fn to_python<'py>(py: Python<'py>, v: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(|e| PyValueError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// The bake presets, cheapest first: {name: {setting: value}}, every setting of every preset
/// (the names `convert` takes as keywords). The same table as `aggtool presets --json`.
#[pyfunction]
fn presets<'py>(py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
    let table = aggtool::bake::PresetTable::new();
    let d = PyDict::new(py);
    for p in &table.presets {
        d.set_item(p.name, to_python(py, &p.settings)?)?;
    }
    Ok(d.into_any())
}

/// The whole preset table, as `aggtool presets --json` prints it: {"default": name,
/// "fields": [setting, ...], "presets": [{"name", "summary", "settings"}, ...]}, cheapest
/// first (what the Blender extension's preset menu reads).
#[pyfunction]
fn preset_table(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    to_python(py, &aggtool::bake::PresetTable::new())
}

/// The settings `convert(source, preset=preset, **overrides)` would bake with, as a dict,
/// checked as `convert` checks them (without baking anything).
#[pyfunction]
#[pyo3(signature = (preset = "default", **overrides))]
fn bake_settings<'py>(
    py: Python<'py>,
    preset: &str,
    overrides: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    to_python(py, &settings_of(preset, overrides)?)
}

/// Bakes `source` (.gltf, .glb or .obj) into an aggregate at `output` (default: the source's
/// path with `.agg`) and returns the output path: the same file `aggtool convert source -o
/// output --preset PRESET` writes with the same settings. `preset` is one of `presets()`'s
/// names; every other keyword overrides one setting of it, named as `presets()` names them
/// (max_res, samples, aiv_rays, keep, lossless, compression, ...; see `bake_settings`).
/// `progress`, if given, is called as progress(stage, done, total).
#[pyfunction]
#[pyo3(signature = (source, output = None, preset = "default", progress = None, **overrides))]
fn convert(
    py: Python<'_>,
    source: PathBuf,
    output: Option<PathBuf>,
    preset: &str,
    progress: Option<Py<PyAny>>,
    overrides: Option<&Bound<'_, PyDict>>,
) -> PyResult<PathBuf> {
    let s = settings_of(preset, overrides)?;
    let output = output.unwrap_or_else(|| source.with_extension("agg"));
    let scene = aggtool::import::load(&source, Default::default())
        .map_err(|e| agg_err(format!("{}: {e}", source.display())))?;
    // The file records its source's file name, as `aggtool convert` records it.
    let name = source
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let report = |stage: &str, done: u64, total: u64| {
        if let Some(cb) = &progress {
            Python::attach(|py| {
                if let Err(e) = cb.call1(py, (stage, done, total)) {
                    e.print(py);
                }
            });
        }
    };
    py.detach(|| aggtool::bake::bake_to_file(&scene, &name, &s, &output, &report))
        .map_err(|e| agg_err(format!("{}: {e}", output.display())))?;
    Ok(output)
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(open, m)?)?;
    m.add_function(wrap_pyfunction!(convert, m)?)?;
    m.add_function(wrap_pyfunction!(presets, m)?)?;
    m.add_function(wrap_pyfunction!(preset_table, m)?)?;
    m.add_function(wrap_pyfunction!(bake_settings, m)?)?;
    m.add_function(wrap_pyfunction!(set_cache_mib, m)?)?;
    m.add_function(wrap_pyfunction!(samples_per_walk, m)?)?;
    m.add_function(wrap_pyfunction!(cache_stats, m)?)?;
    m.add_class::<Scene>()?;
    m.add_class::<Lights>()?;
    m.add("AggError", m.py().get_type::<AggError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
