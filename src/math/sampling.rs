//! Sampling warps from the unit square, each with its pdf and its inverse (pbrt's triples).
//! Round-trip tests sit at the bottom; chi-square tests against the pdfs are in
//! [`crate::validation::chi2`]'s users. [`Sampler`] is the source of the uniform numbers the
//! warps take.

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};

use glam::{Vec2, Vec3};

use super::rng::Pcg32;
use super::safe_sqrt;

/// A source of uniform random numbers, the one interface every estimator in the crate draws
/// from: the reference path tracer, the LoD runtime (a host passes its own sampler) and the
/// image loop's stratified sampler (`film::Stratified`).
pub trait Sampler {
    /// A number in [0, 1).
    fn next_1d(&mut self) -> f32;
    /// Two numbers in [0, 1)².
    fn next_2d(&mut self) -> Vec2 {
        Vec2::new(self.next_1d(), self.next_1d())
    }
}

impl Sampler for Pcg32 {
    #[inline]
    fn next_1d(&mut self) -> f32 {
        self.next_f32()
    }
    #[inline]
    fn next_2d(&mut self) -> Vec2 {
        Pcg32::next_2d(self)
    }
}

/// Shirley–Chiu concentric map from [0,1)² to the unit disk.
#[inline]
pub fn square_to_concentric_disk(u: Vec2) -> Vec2 {
    let o = 2.0 * u - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, FRAC_PI_4 * (o.y / o.x))
    } else {
        (o.y, FRAC_PI_2 - FRAC_PI_4 * (o.x / o.y))
    };
    r * Vec2::new(theta.cos(), theta.sin())
}

/// Inverse of [`square_to_concentric_disk`].
#[inline]
pub fn concentric_disk_to_square(p: Vec2) -> Vec2 {
    let r = p.length();
    if r == 0.0 {
        return Vec2::splat(0.5);
    }
    let mut phi = p.y.atan2(p.x);
    if phi < -FRAC_PI_4 {
        phi += 2.0 * PI;
    }
    let (a, b) = if phi < FRAC_PI_4 {
        (r, phi * r / FRAC_PI_4)
    } else if phi < 3.0 * FRAC_PI_4 {
        (-(phi - FRAC_PI_2) * r / FRAC_PI_4, r)
    } else if phi < 5.0 * FRAC_PI_4 {
        (-r, -(phi - PI) * r / FRAC_PI_4)
    } else {
        ((phi - 3.0 * FRAC_PI_2) * r / FRAC_PI_4, -r)
    };
    Vec2::new((a + 1.0) * 0.5, (b + 1.0) * 0.5)
}

/// Cosine-weighted direction on the +z hemisphere (Malley's method on the concentric disk).
#[inline]
pub fn square_to_cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = square_to_concentric_disk(u);
    Vec3::new(d.x, d.y, safe_sqrt(1.0 - d.length_squared()))
}

/// Solid-angle density of [`square_to_cosine_hemisphere`].
#[inline]
pub fn cosine_hemisphere_pdf(v: Vec3) -> f32 {
    if v.z > 0.0 {
        v.z / PI
    } else {
        0.0
    }
}

/// Inverse of [`square_to_cosine_hemisphere`].
#[inline]
pub fn cosine_hemisphere_to_square(v: Vec3) -> Vec2 {
    concentric_disk_to_square(Vec2::new(v.x, v.y))
}

/// Uniform direction on the unit sphere.
#[inline]
pub fn square_to_uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = safe_sqrt(1.0 - z * z);
    let phi = 2.0 * PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Density of [`square_to_uniform_sphere`].
#[inline]
pub fn uniform_sphere_pdf() -> f32 {
    1.0 / (4.0 * PI)
}

/// Inverse of [`square_to_uniform_sphere`].
#[inline]
pub fn uniform_sphere_to_square(v: Vec3) -> Vec2 {
    let mut phi = v.y.atan2(v.x) / (2.0 * PI);
    if phi < 0.0 {
        phi += 1.0;
    }
    Vec2::new((1.0 - v.z) * 0.5, phi)
}

/// Uniform point on a triangle as barycentrics (b1, b2) (Heitz 2019 low-distortion map is not
/// needed here; the square-root map is exact and simple).
#[inline]
pub fn square_to_triangle(u: Vec2) -> Vec2 {
    let s = u.x.sqrt();
    Vec2::new(1.0 - s, u.y * s)
}

/// Power heuristic with exponent 2 for multiple importance sampling (Veach 1997).
#[inline]
pub fn power_heuristic(pdf_a: f32, pdf_b: f32) -> f32 {
    let a = pdf_a * pdf_a;
    let b = pdf_b * pdf_b;
    if a + b > 0.0 && (a + b).is_finite() {
        a / (a + b)
    } else if pdf_a.is_infinite() {
        1.0
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> impl Iterator<Item = Vec2> {
        (0..41).flat_map(|i| {
            (0..41).map(move |j| Vec2::new(i as f32 / 40.5 + 0.01, j as f32 / 40.5 + 0.01))
        })
    }

    #[test]
    fn concentric_round_trip() {
        for u in grid() {
            let back = concentric_disk_to_square(square_to_concentric_disk(u));
            assert!((back - u).length() < 1e-4, "{u} -> {back}");
        }
    }

    #[test]
    fn cosine_round_trip_and_pdf() {
        for u in grid() {
            let v = square_to_cosine_hemisphere(u);
            assert!((v.length() - 1.0).abs() < 1e-4);
            assert!((cosine_hemisphere_to_square(v) - u).length() < 1e-3);
            assert!(cosine_hemisphere_pdf(v) >= 0.0);
        }
    }

    #[test]
    fn sphere_round_trip() {
        for u in grid() {
            let v = square_to_uniform_sphere(u);
            assert!((uniform_sphere_to_square(v) - u).length() < 1e-3);
        }
    }

    #[test]
    fn power_heuristic_is_finite() {
        assert_eq!(power_heuristic(0.0, 0.0), 0.0);
        assert_eq!(power_heuristic(f32::INFINITY, 1.0), 1.0);
        assert!((power_heuristic(1.0, 1.0) - 0.5).abs() < 1e-6);
    }
}
