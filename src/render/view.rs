//! The view file shared by every render command (JSON, `"version": 1`).
//!
//! ```json
//! {
//!   "version": 1,
//!   "camera": { "eye": [0, 1, 4], "target": [0, 0.5, 0], "up": [0, 1, 0],
//!               "fov_y_deg": 40, "width": 256, "height": 256 },
//!   "environment": { "path": "sky.exr", "intensity": 1.0, "rotation_deg": 0 },
//!   "sun": { "direction": [0.3, 1, 0.2], "irradiance": 3.0 },
//!   "spp": 64,
//!   "seed": 0
//! }
//! ```
//!
//! `environment` is either `{path, intensity, rotation_deg}` (equirectangular .exr or .hdr,
//! Mitsuba 3's convention, rotated by `rotation_deg` about +Y) or `{"constant": [r, g, b]}`.
//! `sun.direction` points towards the light; `irradiance` (a number or `[r, g, b]`) is in W/m² on
//! a surface facing it. No environment and no sun means a constant white environment. Relative
//! paths resolve against the view file's folder.

use std::path::{Path, PathBuf};

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Errors reading a view file.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    /// The view file could not be read.
    #[error("cannot read view file {path}: {source}")]
    Io {
        /// The view file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The view file is not a valid view (JSON, fields or values).
    #[error("{path}: {message}")]
    Invalid {
        /// The view file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// A colour given as one number or three.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum Rgb {
    /// Grey: the same value in the three channels.
    Scalar(f32),
    /// Linear red, green, blue.
    Rgb([f32; 3]),
}

impl Rgb {
    /// The colour as linear RGB.
    pub fn to_vec3(self) -> Vec3 {
        match self {
            Rgb::Scalar(s) => Vec3::splat(s),
            Rgb::Rgb(c) => Vec3::from(c),
        }
    }
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}
fn default_fov() -> f32 {
    40.0
}
fn default_size() -> u32 {
    256
}
fn default_one() -> f32 {
    1.0
}
fn default_spp() -> u32 {
    64
}

/// The view's pinhole camera, as the file states it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraDesc {
    /// Position of the camera.
    pub eye: [f32; 3],
    /// The point it looks at.
    pub target: [f32; 3],
    /// The up direction (default +Y).
    #[serde(default = "default_up")]
    pub up: [f32; 3],
    /// Vertical field of view in degrees (default 40).
    #[serde(default = "default_fov")]
    pub fov_y_deg: f32,
    /// Image width in pixels (default 256).
    #[serde(default = "default_size")]
    pub width: u32,
    /// Image height in pixels (default 256).
    #[serde(default = "default_size")]
    pub height: u32,
}

/// The view's environment, as the file states it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum EnvironmentDesc {
    /// The same radiance from every direction.
    Constant {
        /// The radiance.
        constant: Rgb,
    },
    /// An equirectangular map (Mitsuba 3's convention).
    Map {
        /// The .exr or .hdr file, relative to the view file's folder.
        path: PathBuf,
        /// Scale of the map's radiance (default 1).
        #[serde(default = "default_one")]
        intensity: f32,
        /// Rotation about +Y, degrees.
        #[serde(default)]
        rotation_deg: f32,
    },
}

/// The view's sun, as the file states it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SunDesc {
    /// Towards the light.
    pub direction: [f32; 3],
    /// W/m² on a surface facing the sun.
    pub irradiance: Rgb,
}

/// A parsed view file.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct View {
    /// Format version of the view file (1).
    pub version: u32,
    /// The camera.
    pub camera: CameraDesc,
    /// The environment; with no sun either, a constant white one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<EnvironmentDesc>,
    /// An optional sun.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun: Option<SunDesc>,
    /// Samples per pixel (default 64).
    #[serde(default = "default_spp")]
    pub spp: u32,
    /// Seed of the render's random numbers (default 0).
    #[serde(default)]
    pub seed: u64,
}

/// The view-file format version this build reads and writes.
pub const VIEW_VERSION: u32 = 1;

impl View {
    /// The camera the view describes.
    pub fn camera(&self) -> crate::film::Camera {
        let c = &self.camera;
        crate::film::Camera::look_at(
            Vec3::from(c.eye),
            Vec3::from(c.target),
            Vec3::from(c.up),
            c.fov_y_deg,
            c.width,
            c.height,
        )
    }

    /// The lights the view describes (environment maps are loaded from disk). No environment
    /// and no sun is a constant white sky; a sun alone has a black sky.
    pub fn lights(&self) -> Result<crate::lights::Lights, crate::film::ImageError> {
        use crate::lights::{EnvMap, Environment, Lights, Sun};
        let environment = match &self.environment {
            Some(EnvironmentDesc::Constant { constant }) => {
                Environment::Constant(constant.to_vec3())
            }
            Some(EnvironmentDesc::Map {
                path,
                intensity,
                rotation_deg,
            }) => Environment::Map(EnvMap::from_image(
                &crate::film::Image::read_any(path)?,
                *intensity,
                *rotation_deg,
            )),
            None if self.sun.is_some() => Environment::Constant(Vec3::ZERO),
            None => Environment::Constant(Vec3::ONE),
        };
        let sun = self.sun.as_ref().map(|s| Sun {
            direction: Vec3::from(s.direction).normalize(),
            irradiance: s.irradiance.to_vec3(),
        });
        Ok(Lights { environment, sun })
    }

    /// Reads and validates a view file; relative environment paths become absolute against its
    /// folder.
    pub fn load(path: &Path) -> Result<View, ViewError> {
        let text = std::fs::read_to_string(path).map_err(|source| ViewError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let invalid = |message: String| ViewError::Invalid {
            path: path.to_path_buf(),
            message,
        };
        let mut view: View = serde_json::from_str(&text)
            .map_err(|e| invalid(format!("not a valid view file: {e}")))?;
        view.validate().map_err(invalid)?;
        if let Some(EnvironmentDesc::Map { path: p, .. }) = &mut view.environment {
            if p.is_relative() {
                *p = path.parent().unwrap_or(Path::new(".")).join(&*p);
            }
        }
        Ok(view)
    }

    /// Checks ranges: version, finite vectors, sizes, fov, spp.
    pub fn validate(&self) -> Result<(), String> {
        if self.version != VIEW_VERSION {
            return Err(format!(
                "view file version {} is not supported (this build reads version {VIEW_VERSION})",
                self.version
            ));
        }
        let c = &self.camera;
        // The size first: a view framed for a zero-sized image (`View::framing`) has an
        // infinite eye, which is not what is wrong with it.
        if c.width == 0 || c.height == 0 || c.width > 16384 || c.height > 16384 {
            return Err(format!(
                "image size {}x{} must be 1 to 16384 per side",
                c.width, c.height
            ));
        }
        let eye = Vec3::from(c.eye);
        let target = Vec3::from(c.target);
        let up = Vec3::from(c.up);
        if !(eye.is_finite() && target.is_finite() && up.is_finite()) {
            return Err("camera eye, target and up must be finite".into());
        }
        let fwd = target - eye;
        if fwd.length() < 1e-12 {
            return Err("camera eye and target coincide".into());
        }
        if fwd.normalize().cross(up.normalize_or_zero()).length() < 1e-6 {
            return Err("camera up is parallel to the viewing direction".into());
        }
        if !(c.fov_y_deg > 0.0 && c.fov_y_deg < 179.0) {
            return Err(format!("fov_y_deg {} must be in (0, 179)", c.fov_y_deg));
        }
        if self.spp == 0 || self.spp > 1 << 20 {
            return Err(format!("spp {} must be 1 to 1048576", self.spp));
        }
        if let Some(s) = &self.sun {
            let d = Vec3::from(s.direction);
            if !d.is_finite() || d.length() < 1e-12 {
                return Err("sun direction must be a finite non-zero vector".into());
            }
            let e = s.irradiance.to_vec3();
            if !e.is_finite() || e.min_element() < 0.0 {
                return Err("sun irradiance must be finite and non-negative".into());
            }
        }
        match &self.environment {
            Some(EnvironmentDesc::Constant { constant }) => {
                let c = constant.to_vec3();
                if !c.is_finite() || c.min_element() < 0.0 {
                    return Err("constant environment must be finite and non-negative".into());
                }
            }
            Some(EnvironmentDesc::Map {
                intensity,
                rotation_deg,
                ..
            }) => {
                if !intensity.is_finite() || *intensity < 0.0 || !rotation_deg.is_finite() {
                    return Err(
                        "environment intensity must be finite and non-negative, rotation finite"
                            .into(),
                    );
                }
            }
            None => {}
        }
        Ok(())
    }

    /// A view that frames a bounding sphere: the camera looks at the centre from the front,
    /// a little right and above, far enough that the sphere fits the smaller image side.
    pub fn framing(center: Vec3, radius: f32, width: u32, height: u32, spp: u32) -> View {
        let fov_y_deg: f32 = 40.0;
        let aspect = width as f32 / height as f32;
        let half_fov_y = (fov_y_deg * 0.5).to_radians();
        let half_fov_x = (half_fov_y.tan() * aspect).atan();
        let half = half_fov_y.min(half_fov_x);
        let dist = radius / half.sin() * 1.02;
        let dir = Vec3::new(0.45, 0.35, 1.0).normalize();
        let eye = center + dir * dist;
        View {
            version: VIEW_VERSION,
            camera: CameraDesc {
                eye: eye.to_array(),
                target: center.to_array(),
                up: default_up(),
                fov_y_deg,
                width,
                height,
            },
            environment: None,
            sun: None,
            spp,
            seed: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_rejects() {
        let ok = r#"{"version":1,"camera":{"eye":[0,0,5],"target":[0,0,0]},
            "environment":{"constant":[1,0.5,0.25]},"sun":{"direction":[0,1,0],"irradiance":2}}"#;
        let v: View = serde_json::from_str(ok).unwrap();
        v.validate().unwrap();
        assert_eq!(v.camera.width, 256);
        assert_eq!(
            v.sun.as_ref().unwrap().irradiance.to_vec3(),
            Vec3::splat(2.0)
        );
        let map = r#"{"version":1,"camera":{"eye":[0,0,5],"target":[0,0,0]},
            "environment":{"path":"a.exr","rotation_deg":90}}"#;
        let v: View = serde_json::from_str(map).unwrap();
        assert!(
            matches!(v.environment, Some(EnvironmentDesc::Map { intensity, .. }) if intensity == 1.0)
        );
        for bad in [
            r#"{"version":2,"camera":{"eye":[0,0,5],"target":[0,0,0]}}"#,
            r#"{"version":1,"camera":{"eye":[0,0,0],"target":[0,0,0]}}"#,
            r#"{"version":1,"camera":{"eye":[0,5,0],"target":[0,0,0]}}"#,
            r#"{"version":1,"camera":{"eye":[0,0,5],"target":[0,0,0],"fov_y_deg":0}}"#,
            r#"{"version":1,"camera":{"eye":[0,0,5],"target":[0,0,0],"width":0}}"#,
        ] {
            let v: View = serde_json::from_str(bad).unwrap();
            assert!(v.validate().is_err(), "{bad}");
        }
        assert!(serde_json::from_str::<View>(
            r#"{"version":1,"camera":{"eye":[0,0,5],"target":[0,0,0]},"spam":1}"#
        )
        .is_err());
    }

    #[test]
    fn framing_contains_sphere() {
        let v = View::framing(Vec3::new(1.0, 2.0, 3.0), 2.0, 320, 200, 4);
        v.validate().unwrap();
        let d = (Vec3::from(v.camera.eye) - Vec3::new(1.0, 2.0, 3.0)).length();
        assert!(d > 2.0 / (20f32.to_radians().sin()));
    }
}

/// How a render command gets its view: a view file, or the scene framed (`--auto-view`), with
/// the sample count and seed overridden and the view used saved where asked.
#[derive(Clone, Debug)]
pub struct ViewRequest {
    /// A view file.
    pub view: Option<PathBuf>,
    /// Frame the scene's bounding sphere instead.
    pub auto_view: bool,
    /// Image width when framing.
    pub width: u32,
    /// Image height when framing.
    pub height: u32,
    /// Samples per pixel (overrides the view file; 64 when framing).
    pub spp: Option<u32>,
    /// Random seed (overrides the view file).
    pub seed: Option<u64>,
    /// Write the view used to this file.
    pub save_view: Option<PathBuf>,
}

impl Default for ViewRequest {
    /// No view file, not framing (one of the two must be chosen), 256×256 when framing.
    fn default() -> Self {
        ViewRequest {
            view: None,
            auto_view: false,
            width: 256,
            height: 256,
            spp: None,
            seed: None,
            save_view: None,
        }
    }
}

impl ViewRequest {
    /// The view: loaded, or framing the sphere `sphere` gives (centre, radius); with the
    /// overrides applied, validated, and saved where asked.
    pub fn resolve(
        &self,
        sphere: impl FnOnce() -> anyhow::Result<(Vec3, f32)>,
    ) -> anyhow::Result<View> {
        use anyhow::Context;
        let mut view = match (&self.view, self.auto_view) {
            (Some(v), _) => View::load(v)?,
            (None, true) => {
                let (c, r) = sphere()?;
                View::framing(c, r, self.width, self.height, self.spp.unwrap_or(64))
            }
            (None, false) => {
                return Err(crate::report::usage(
                    "give a view file with --view, or --auto-view",
                ))
            }
        };
        if let Some(s) = self.spp {
            view.spp = s;
        }
        if let Some(s) = self.seed {
            view.seed = s;
        }
        view.validate().map_err(crate::report::usage)?;
        if let Some(p) = &self.save_view {
            std::fs::write(p, serde_json::to_string_pretty(&view)?)
                .map_err(|e| crate::report::output(format!("cannot write {}: {e}", p.display())))
                .context("--save-view")?;
        }
        Ok(view)
    }
}

/// The two files a render writes for `-o OUTPUT`: the linear EXR and a tonemapped PNG beside
/// it. OUTPUT names the EXR, or the PNG (the EXR then goes beside it with `.exr`, so that the
/// picture is not overwritten by EXR data).
#[derive(Clone, Debug, Serialize)]
pub struct ImageFiles {
    /// The EXR.
    pub exr: PathBuf,
    /// The PNG.
    pub png: PathBuf,
}

impl ImageFiles {
    /// The files for `-o output`.
    pub fn for_output(output: &Path) -> ImageFiles {
        let png = output
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("png"));
        let exr = if png {
            output.with_extension("exr")
        } else {
            output.to_path_buf()
        };
        ImageFiles {
            png: exr.with_extension("png"),
            exr,
        }
    }

    /// Writes `img` to both, the PNG at `exposure` stops.
    pub fn write(
        &self,
        img: &crate::film::Image,
        exposure: f32,
    ) -> Result<(), crate::film::ImageError> {
        img.write_exr(&self.exr)?;
        img.write_png(&self.png, exposure)
    }
}

impl std::fmt::Display for ImageFiles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "output: {} and {}",
            self.exr.display(),
            self.png.display()
        )
    }
}
