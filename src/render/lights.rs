//! Lights of the view file: an environment (constant or equirectangular map, importance
//! sampled) and an optional sun (a directional light given by its irradiance).
//!
//! The map is evaluated exactly as Mitsuba 3's `envmap` does, so that renders can be checked
//! against Mitsuba: texel centres sit on integer positions of a grid of `(W + 1) × H` samples
//! whose last column repeats the first, `x = u · W`, `y = v · (H − 1)`, bilinear in between. It
//! is sampled from a piecewise-constant density over the `W × (H − 1)` cells of that grid,
//! weighted by the mean luminance of each cell's corners times sin θ; a cell whose corners are
//! all black has zero radiance inside and zero density, any other cell has both positive.

use std::f32::consts::PI;
use std::path::Path;

use glam::{Mat3, Vec2, Vec3};

use super::image::{Image, ImageError};
use super::view::{EnvironmentDesc, View};
use crate::math::color::luminance;
use crate::math::distribution::Distribution2D;
use crate::math::sampling::{square_to_uniform_sphere, uniform_sphere_pdf};
use crate::math::spherical::{dir_to_equirect, equirect_to_dir};

/// A sample of a light.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// World direction towards the light.
    pub wi: Vec3,
    /// Radiance arriving from `wi`.
    pub radiance: Vec3,
    /// Solid-angle density.
    pub pdf: f32,
}

/// Environment lighting.
#[derive(Clone, Debug)]
pub enum Environment {
    Constant(Vec3),
    Map(EnvMap),
}

/// An equirectangular environment map.
#[derive(Clone, Debug)]
pub struct EnvMap {
    width: usize,
    height: usize,
    /// `height × width` texels, already scaled by the intensity.
    texels: Vec<Vec3>,
    /// World to map rotation.
    world_to_map: Mat3,
    map_to_world: Mat3,
    dist: Distribution2D,
}

impl EnvMap {
    /// From an image, intensity and rotation about +Y in degrees. Negative and non-finite texels
    /// become zero.
    pub fn new(image: &Image, intensity: f32, rotation_deg: f32) -> Self {
        let mut width = image.width as usize;
        let mut height = image.height as usize;
        let mut texels: Vec<Vec3> = image
            .pixels
            .iter()
            .map(|p| {
                let q = *p * intensity;
                if q.is_finite() {
                    q.max(Vec3::ZERO)
                } else {
                    Vec3::ZERO
                }
            })
            .collect();
        if width == 0 || height == 0 {
            texels = vec![Vec3::ZERO; 2];
            width = 1;
            height = 2;
        } else if height == 1 {
            texels.extend_from_within(..);
            height = 2;
        }
        let lum: Vec<f32> = texels.iter().map(|&c| luminance(c)).collect();
        let cells_y = height - 1;
        let mut weights = vec![0.0f32; width * cells_y];
        for j in 0..cells_y {
            let sin_theta = (PI * (j as f32 + 0.5) / cells_y as f32).sin();
            for i in 0..width {
                let i1 = (i + 1) % width;
                let l = lum[j * width + i]
                    + lum[j * width + i1]
                    + lum[(j + 1) * width + i]
                    + lum[(j + 1) * width + i1];
                weights[j * width + i] = 0.25 * l * sin_theta;
            }
        }
        let rot = Mat3::from_rotation_y(rotation_deg.to_radians());
        EnvMap {
            width,
            height,
            texels,
            world_to_map: rot.transpose(),
            map_to_world: rot,
            dist: Distribution2D::new(&weights, width, cells_y),
        }
    }

    #[inline]
    fn lookup(&self, uv: Vec2) -> Vec3 {
        let x = (uv.x * self.width as f32).clamp(0.0, self.width as f32);
        let y = (uv.y * (self.height - 1) as f32).clamp(0.0, (self.height - 1) as f32);
        let x0 = (x as usize).min(self.width - 1);
        let y0 = (y as usize).min(self.height - 2);
        let fx = x - x0 as f32;
        let fy = y - y0 as f32;
        let x1 = (x0 + 1) % self.width;
        let t = |xx: usize, yy: usize| self.texels[yy * self.width + xx];
        (t(x0, y0) * (1.0 - fx) + t(x1, y0) * fx) * (1.0 - fy)
            + (t(x0, y0 + 1) * (1.0 - fx) + t(x1, y0 + 1) * fx) * fy
    }

    #[inline]
    pub fn eval(&self, dir: Vec3) -> Vec3 {
        self.lookup(dir_to_equirect(self.world_to_map * dir))
    }

    pub fn sample(&self, u: Vec2) -> Option<LightSample> {
        let (uv, pdf_uv) = self.dist.sample(u);
        let _ = pdf_uv;
        let sin_theta = (PI * uv.y).sin();
        if !(pdf_uv > 0.0) || !(sin_theta > 0.0) {
            return None;
        }
        let wi = self.map_to_world * equirect_to_dir(uv);
        // The density as `pdf` will recompute it from the direction (at the poles the round
        // trip through a direction can lose the last bits of sin θ).
        let pdf = self.pdf(wi);
        if !(pdf > 0.0) {
            return None;
        }
        Some(LightSample {
            wi,
            radiance: self.lookup(uv),
            pdf,
        })
    }

    pub fn pdf(&self, dir: Vec3) -> f32 {
        let d = self.world_to_map * dir;
        let uv = dir_to_equirect(d);
        // sin θ from the direction itself (exact near the poles, where sin(acos(y)) is not);
        // the floor keeps the density positive on the pole's measure-zero set.
        let sin_theta = (d.x * d.x + d.z * d.z).sqrt().max(1e-7);
        crate::math::finite_or_zero(self.dist.pdf(uv) / (2.0 * PI * PI * sin_theta))
    }
}

impl Environment {
    #[inline]
    pub fn eval(&self, dir: Vec3) -> Vec3 {
        match self {
            Environment::Constant(c) => *c,
            Environment::Map(m) => m.eval(dir),
        }
    }

    pub fn sample(&self, u: Vec2) -> Option<LightSample> {
        match self {
            Environment::Constant(c) => Some(LightSample {
                wi: square_to_uniform_sphere(u),
                radiance: *c,
                pdf: uniform_sphere_pdf(),
            }),
            Environment::Map(m) => m.sample(u),
        }
    }

    pub fn pdf(&self, dir: Vec3) -> f32 {
        match self {
            Environment::Constant(_) => uniform_sphere_pdf(),
            Environment::Map(m) => m.pdf(dir),
        }
    }

    /// Whether it emits nothing at all.
    pub fn is_black(&self) -> bool {
        match self {
            Environment::Constant(c) => c.max_element() <= 0.0,
            Environment::Map(m) => m.texels.iter().all(|t| t.max_element() <= 0.0),
        }
    }
}

/// A directional light.
#[derive(Clone, Copy, Debug)]
pub struct Sun {
    /// Unit direction towards the light.
    pub direction: Vec3,
    /// W/m² on a surface facing it.
    pub irradiance: Vec3,
}

/// All lights of a view.
#[derive(Clone, Debug)]
pub struct Lights {
    pub environment: Environment,
    pub sun: Option<Sun>,
}

impl Lights {
    /// Lights described by a view file (environment maps are loaded from disk).
    pub fn from_view(view: &View) -> Result<Lights, ImageError> {
        let environment = match &view.environment {
            Some(EnvironmentDesc::Constant { constant }) => {
                Environment::Constant(constant.to_vec3())
            }
            Some(EnvironmentDesc::Map {
                path,
                intensity,
                rotation_deg,
            }) => Environment::Map(EnvMap::new(
                &Image::read_any(Path::new(path))?,
                *intensity,
                *rotation_deg,
            )),
            None if view.sun.is_some() => Environment::Constant(Vec3::ZERO),
            None => Environment::Constant(Vec3::ONE),
        };
        let sun = view.sun.as_ref().map(|s| Sun {
            direction: Vec3::from(s.direction).normalize(),
            irradiance: s.irradiance.to_vec3(),
        });
        Ok(Lights { environment, sun })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::validation::chi2::{chi2_test, Chi2Settings};

    fn test_map() -> EnvMap {
        let mut img = Image::new(16, 8);
        for y in 0..8 {
            for x in 0..16 {
                img.pixels[y * 16 + x] = Vec3::splat(if (x + y) % 5 == 0 {
                    20.0
                } else {
                    0.5 * (x as f32) / 16.0
                });
            }
        }
        EnvMap::new(&img, 1.0, 30.0)
    }

    #[test]
    fn sampling_matches_pdf() {
        let m = test_map();
        // The density is piecewise constant with jumps of 1000:1 between map cells: the
        // midpoint rule needs fine sub-cells to integrate it to ~0.1% (at 12 it is off by a
        // few percent and the test rejects a correct sampler at large sample counts).
        let settings = Chi2Settings {
            integration_res: 128,
            ..Chi2Settings::default()
        };
        let r = chi2_test(settings, |u| m.sample(u).map(|s| s.wi), |d| m.pdf(d));
        assert!(r.passed(0.01), "{r:?}");
        assert!((r.pdf_integral - 1.0).abs() < 0.01, "{r:?}");
    }

    #[test]
    fn sample_radiance_matches_eval() {
        let m = test_map();
        for i in 0..100 {
            let u = Vec2::new((i as f32 * 0.618).fract(), (i as f32 + 0.5) / 100.0);
            if let Some(s) = m.sample(u) {
                assert!((s.radiance - m.eval(s.wi)).length() < 1e-3 * (1.0 + s.radiance.length()));
                assert!((s.pdf - m.pdf(s.wi)).abs() < 1e-3 * s.pdf.max(1.0));
            }
        }
    }

    #[test]
    fn mitsuba_lookup_convention() {
        // A 4x3 map: the texel at column 1 (u = 1/4) of the middle row is seen from +X.
        let mut img = Image::new(4, 3);
        img.pixels[4 + 1] = Vec3::ONE;
        let m = EnvMap::new(&img, 2.0, 0.0);
        assert!((m.eval(Vec3::X) - Vec3::splat(2.0)).length() < 1e-5);
        assert_eq!(m.eval(-Vec3::X), Vec3::ZERO);
        // Rotating the map by 90° about +Y moves that texel to -Z... (R_y(90°) maps +X to -Z).
        let r = EnvMap::new(&img, 1.0, 90.0);
        assert!(
            (r.eval(-Vec3::Z) - Vec3::ONE).length() < 1e-5,
            "{}",
            r.eval(-Vec3::Z)
        );
    }
}
