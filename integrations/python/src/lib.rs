//! `aggtool._native`: the Python module of the aggtool LoD runtime (PyO3, abi3 for CPython
//! 3.11 and later). Re-exported by `aggtool/__init__.py`:
//!
//! - `aggtool.open(path)` → `Scene` with `.bounds`, `.levels`, `.inspect()` and
//!   `.trace(origins, directions, aperture, lights=None, seed=0)` → (N, 4) float32 (radiance
//!   RGB and background transmittance per cone), which releases the GIL while it traces;
//! - `aggtool.Lights(constant=(1, 1, 1), sun_direction=None, sun_irradiance=None)` and
//!   `.set_environment(pixels (H, W, 3) float32, intensity=1, rotation_deg=0)`;
//! - `aggtool.convert(source, output=None, progress=None, **settings)` → output path.
//!
//! Errors are `aggtool.AggError` (a `ValueError`) naming the file and the reason; wrong
//! dtypes and shapes are `TypeError`/`ValueError` from the argument checks.

use std::path::PathBuf;

use aggtool::runtime::{
    Cone, EnvMap, Environment, Lights as RtLights, LodScene, Sun, TraceSettings,
};
use glam::Vec3;
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

create_exception!(
    _native,
    AggError,
    PyValueError,
    "A file could not be read, verified or written."
);

fn agg_err(msg: impl std::fmt::Display) -> PyErr {
    AggError::new_err(msg.to_string())
}

/// An opened `.agg` aggregate: levels are read and verified when cones first need them.
#[pyclass(frozen, module = "aggtool")]
struct Scene {
    scene: LodScene,
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

#[pymethods]
impl Scene {
    /// The bounds of the asset the aggregate was baked from, ((x, y, z), (x, y, z)), or None
    /// when it is empty.
    #[getter]
    fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        (self.scene.level_count() > 0).then(|| {
            let (a, b) = self.scene.aggregate().bounds();
            (a.to_array(), b.to_array())
        })
    }

    /// The levels' resolutions, finest first.
    #[getter]
    fn levels(&self) -> Vec<u32> {
        (0..self.scene.level_count())
            .map(|l| self.scene.grid(l).res)
            .collect()
    }

    /// What `aggtool inspect --json` prints, as a dict.
    fn inspect<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let agg = aggtool::format::Aggregate::open(&self.path)
            .map_err(|e| agg_err(format!("{}: {e}", self.path.display())))?;
        let json = aggtool::format::summary(&agg, &self.path);
        let text = serde_json::to_string(&json).map_err(agg_err)?;
        py.import("json")?.call_method1("loads", (text,))
    }

    /// Traces N cones: `origins` and `directions` (N, 3) float32, one full `aperture` angle
    /// in radians for all; returns (N, 4) float32: radiance RGB and the background's
    /// transmittance. Cone i draws stream i of `seed`. Releases the GIL while tracing.
    #[pyo3(signature = (origins, directions, aperture, lights = None, seed = 0))]
    fn trace<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f32>,
        directions: PyReadonlyArray2<'py, f32>,
        aperture: f32,
        lights: Option<PyRef<'py, Lights>>,
        seed: u64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (n, o) = rows3(&origins, "origins")?;
        let (m, d) = rows3(&directions, "directions")?;
        if n != m {
            return Err(PyValueError::new_err(format!(
                "{n} origins but {m} directions"
            )));
        }
        if !aperture.is_finite() || aperture < 0.0 {
            return Err(PyValueError::new_err(
                "aperture must be finite and non-negative",
            ));
        }
        let mut cones = Vec::with_capacity(n);
        for i in 0..n {
            let (oi, di) = (Vec3::from_slice(&o[3 * i..]), Vec3::from_slice(&d[3 * i..]));
            let di = di
                .try_normalize()
                .filter(|_| oi.is_finite())
                .ok_or_else(|| {
                    PyValueError::new_err(format!("cone {i}: non-finite or zero-length ray"))
                })?;
            cones.push(Cone::new(oi, di, aperture));
        }
        let lights = lights
            .map(|l| l.lights.clone())
            .unwrap_or_else(|| RtLights::constant(Vec3::ONE));
        let scene = &self.scene;
        let out: Vec<f32> = py.detach(|| {
            let mut out = vec![0f32; 4 * n];
            scene.trace_batch(&cones, &lights, &TraceSettings::default(), seed, &mut out);
            out
        });
        if let Some(e) = self.scene.first_error() {
            return Err(agg_err(format!("{}: {e}", self.path.display())));
        }
        let a = PyArray1::from_vec(py, out);
        Ok(a.reshape([n, 4])?.into_any())
    }

    fn __repr__(&self) -> String {
        format!(
            "aggtool.Scene({:?}, levels={:?})",
            self.path.display().to_string(),
            self.levels()
        )
    }
}

/// Opens an `.agg` file (lazily: the header and index are verified now, levels on first use).
#[pyfunction]
fn open(path: PathBuf) -> PyResult<Scene> {
    if path.extension().is_some_and(|e| e == "json") {
        return Err(agg_err(format!(
            "{}: assembly manifests are not supported by this version",
            path.display()
        )));
    }
    let scene = LodScene::open(&path).map_err(|e| agg_err(format!("{}: {e}", path.display())))?;
    Ok(Scene { scene, path })
}

/// Bakes `source` (.gltf, .glb or .obj) into an aggregate at `output` (default: the source's
/// path with `.agg`) and returns the output path. Settings as keyword arguments, named as
/// `aggtool convert`'s flags with underscores (max_res, min_res, samples, aiv_res, aiv_rays,
/// abv_res, abv_rays, abv_full_res, ndf_lobes, keep, energy, lossless). `progress`, if given,
/// is called as progress(stage, done, total).
#[pyfunction]
#[pyo3(signature = (source, output = None, progress = None, **settings))]
fn convert(
    py: Python<'_>,
    source: PathBuf,
    output: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    settings: Option<&Bound<'_, PyDict>>,
) -> PyResult<PathBuf> {
    let mut s = aggtool::bake::BakeSettings::default();
    if let Some(kw) = settings {
        for (k, v) in kw.iter() {
            let key: String = k.extract()?;
            match key.as_str() {
                "max_res" => s.max_res = v.extract()?,
                "min_res" => s.min_res = v.extract()?,
                "samples" => s.samples = v.extract()?,
                "aiv_res" => s.aiv_res = v.extract()?,
                "aiv_rays" => s.aiv_rays = v.extract()?,
                "abv_res" => s.abv_res = v.extract()?,
                "abv_rays" => s.abv_rays = v.extract()?,
                "abv_full_res" => s.abv_full_res = v.extract()?,
                "ndf_lobes" => s.ndf_lobes = v.extract()?,
                "keep" => s.keep = v.extract()?,
                "energy" => s.energy = v.extract()?,
                "lossless" => s.lossless = v.extract()?,
                other => {
                    return Err(PyTypeError::new_err(format!(
                        "convert() got an unexpected setting {other:?}"
                    )))
                }
            }
        }
    }
    s.validate().map_err(agg_err)?;
    let output = output.unwrap_or_else(|| source.with_extension("agg"));
    let scene = aggtool::import::load(&source, Default::default())
        .map_err(|e| agg_err(format!("{}: {e}", source.display())))?;
    let name = source
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "asset".into());
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
    m.add_class::<Scene>()?;
    m.add_class::<Lights>()?;
    m.add("AggError", m.py().get_type::<AggError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
