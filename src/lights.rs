//! Lights: an environment (constant or equirectangular map, importance sampled) and an
//! optional sun (a directional light given by its irradiance). The reference renderer and the
//! LoD runtime light with this one implementation; it depends
//! on [`crate::math`] alone (and [`crate::film::Image`] for the convenience constructor).
//!
//! The map is evaluated exactly as Mitsuba 3's `envmap` does (probed with Mitsuba 3.9: texel
//! column `i` peaks at `u = (i + ½) / W`, row `j` at `v = j / (H − 1)`), so that renders can be
//! checked against Mitsuba: in grid coordinates `x = u · W − ½` (wrapped around) and
//! `y = v · (H − 1)` texel centres sit on integers and values are bilinear in between. It is
//! sampled from a piecewise-constant density over the `W × (H − 1)` cells of that grid,
//! weighted by the mean luminance of each cell's corners times sin θ; a cell whose corners are
//! all black has zero radiance inside and zero density, any other cell has both positive.

use glam::{Mat3, Vec2, Vec3};
use std::f32::consts::PI;

use crate::film::Image;
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
    /// Uniform radiance from every direction.
    Constant(Vec3),
    /// An equirectangular map, importance sampled.
    Map(EnvMap),
}

/// An equirectangular environment map.
#[derive(Clone, Debug)]
pub struct EnvMap {
    /// Texel columns and rows. u32, not usize: the compiler hoists `width as f32` out of the
    /// shading loops above the [`Environment`] tag check, so it also runs on the unused (and
    /// uninitialised) payload of [`Environment::Constant`]; usize → f32 branches on the sign
    /// bit on x86-64, which valgrind reports as a jump on uninitialised memory (CI, C host),
    /// while u32 → f32 converts without a branch.
    width: u32,
    height: u32,
    /// `height × width` texels, already scaled by the intensity.
    texels: Vec<Vec3>,
    /// World to map rotation.
    world_to_map: Mat3,
    map_to_world: Mat3,
    dist: Distribution2D,
}

impl EnvMap {
    /// From an image, intensity and rotation about +Y in degrees (see [`EnvMap::new`]).
    pub fn from_image(image: &Image, intensity: f32, rotation_deg: f32) -> Self {
        Self::new(
            image.width,
            image.height,
            &image.pixels,
            intensity,
            rotation_deg,
        )
    }

    /// From `width × height` texels (row 0 at the top, +Y up; fewer texels than that are taken
    /// as black), intensity and rotation about +Y in degrees. Negative and non-finite texels
    /// become zero.
    pub fn new(
        width: u32,
        height: u32,
        pixels: &[Vec3],
        intensity: f32,
        rotation_deg: f32,
    ) -> Self {
        let mut width = width as usize;
        let mut height = height as usize;
        let n = width.saturating_mul(height);
        let mut texels: Vec<Vec3> = pixels
            .iter()
            .copied()
            .chain(std::iter::repeat(Vec3::ZERO))
            .take(n)
            .map(|p| {
                let q = p * intensity;
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
        let rot = if rotation_deg.is_finite() {
            Mat3::from_rotation_y(rotation_deg.to_radians())
        } else {
            Mat3::IDENTITY
        };
        EnvMap {
            width: width as u32,
            height: height as u32,
            texels,
            world_to_map: rot.transpose(),
            map_to_world: rot,
            dist: Distribution2D::new(&weights, width, cells_y),
        }
    }

    /// Map coordinate u to grid coordinate (cells start at texel centres), both in [0, 1).
    #[inline]
    fn u_to_grid(&self, u: f32) -> f32 {
        let g = u - 0.5 / self.width as f32;
        if g < 0.0 {
            g + 1.0
        } else {
            g
        }
    }

    #[inline]
    fn grid_to_u(&self, g: f32) -> f32 {
        let u = g + 0.5 / self.width as f32;
        if u >= 1.0 {
            u - 1.0
        } else {
            u
        }
    }

    /// Bilinear lookup at grid coordinates (x in [0,1) of the width, y = v).
    #[inline]
    fn lookup(&self, g: Vec2) -> Vec3 {
        let (w, h) = (self.width as usize, self.height as usize);
        let x = (g.x * self.width as f32).clamp(0.0, self.width as f32);
        let y = (g.y * (self.height - 1) as f32).clamp(0.0, (self.height - 1) as f32);
        let x0 = (x as usize).min(w - 1);
        let y0 = (y as usize).min(h - 2);
        let fx = x - x0 as f32;
        let fy = y - y0 as f32;
        let x1 = (x0 + 1) % w;
        let t = |xx: usize, yy: usize| self.texels[yy * w + xx];
        (t(x0, y0) * (1.0 - fx) + t(x1, y0) * fx) * (1.0 - fy)
            + (t(x0, y0 + 1) * (1.0 - fx) + t(x1, y0 + 1) * fx) * fy
    }

    /// Radiance arriving from direction `dir` (towards the light), bilinear as Mitsuba's `envmap`.
    #[inline]
    pub fn eval(&self, dir: Vec3) -> Vec3 {
        let uv = dir_to_equirect(self.world_to_map * dir);
        self.lookup(Vec2::new(self.u_to_grid(uv.x), uv.y))
    }

    /// A direction drawn from the map's piecewise-constant density (cells weighted by luminance
    /// times sin θ), with its radiance and solid-angle pdf; `None` where the density is zero.
    pub fn sample(&self, u: Vec2) -> Option<LightSample> {
        let (g, _) = self.dist.sample(u);
        let uv = Vec2::new(self.grid_to_u(g.x), g.y);
        let wi = self.map_to_world * equirect_to_dir(uv);
        // The density as `pdf` will recompute it from the direction (at the poles the round
        // trip through a direction can lose the last bits of sin θ).
        let pdf = self.pdf(wi);
        if !(pdf > 0.0) {
            return None;
        }
        Some(LightSample {
            wi,
            radiance: self.lookup(g),
            pdf,
        })
    }

    /// Solid-angle density of [`EnvMap::sample`] towards `dir`.
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let d = self.world_to_map * dir;
        let uv = dir_to_equirect(d);
        // sin θ from the direction itself (exact near the poles, where sin(acos(y)) is not);
        // the floor keeps the density positive on the pole's measure-zero set.
        let sin_theta = (d.x * d.x + d.z * d.z).sqrt().max(1e-7);
        let g = Vec2::new(self.u_to_grid(uv.x), uv.y);
        crate::math::finite_or_zero(self.dist.pdf(g) / (2.0 * PI * PI * sin_theta))
    }
}

impl Environment {
    /// Radiance arriving from direction `dir`.
    #[inline]
    pub fn eval(&self, dir: Vec3) -> Vec3 {
        match self {
            Environment::Constant(c) => *c,
            Environment::Map(m) => m.eval(dir),
        }
    }

    /// A direction to the environment: uniform for a constant one, by the map's density
    /// otherwise.
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

    /// Solid-angle density of [`Environment::sample`] towards `dir`.
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
    /// The environment around the scene.
    pub environment: Environment,
    /// An optional sun.
    pub sun: Option<Sun>,
}

impl Lights {
    /// A constant environment of radiance `rgb` and no sun.
    pub fn constant(rgb: Vec3) -> Lights {
        Lights {
            environment: Environment::Constant(rgb),
            sun: None,
        }
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
        EnvMap::from_image(&img, 1.0, 30.0)
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
        // A 4x3 map with one lit texel, column 1 of the middle row: as in Mitsuba 3.9 (see
        // the module documentation) it peaks at u = 1.5/4 on the horizon, falls off linearly to
        // u = 0.5/4 and 2.5/4, and linearly in v to the poles.
        let mut img = Image::new(4, 3);
        img.pixels[4 + 1] = Vec3::ONE;
        let m = EnvMap::from_image(&img, 2.0, 0.0);
        let at = |u: f32, v: f32| m.eval(equirect_to_dir(Vec2::new(u, v))).x;
        assert!((at(0.375, 0.5) - 2.0).abs() < 1e-4);
        assert!((at(0.25, 0.5) - 1.0).abs() < 1e-4);
        assert!((at(0.45, 0.5) - 1.4).abs() < 1e-3);
        assert!((at(0.375, 0.25) - 1.0).abs() < 1e-3);
        assert!(at(0.125, 0.5).abs() < 1e-5 && at(0.9, 0.5).abs() < 1e-5);
        // Rotating the map about +Y by 90° turns the peak's direction by R_y(90°).
        let r = EnvMap::from_image(&img, 1.0, 90.0);
        let peak =
            Mat3::from_rotation_y(90f32.to_radians()) * equirect_to_dir(Vec2::new(0.375, 0.5));
        assert!(
            (r.eval(peak) - Vec3::ONE).length() < 1e-4,
            "{}",
            r.eval(peak)
        );
    }
}
