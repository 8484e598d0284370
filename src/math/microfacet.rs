//! Microfacet toolkit: the GGX (Trowbridge–Reitz) distribution, Smith shadowing–masking and
//! Schlick's Fresnel with an explicit F90, all in a local frame where the normal is +z.
//!
//! Roughness is GGX `α` (glTF perceptual roughness squared). `α` is clamped to
//! [`ALPHA_MIN`]: roughness 0 is a mirror, which a microfacet model only reaches in the
//! limit; 1e-3 keeps `D` below 3.2e5 so that f32 sums stay exact to a few ulps while the lobe is
//! still far narrower than any pixel footprint we render.

use std::f32::consts::PI;

use glam::{Vec2, Vec3};

use super::safe_sqrt;

/// Smallest GGX roughness used anywhere (see the module documentation).
pub const ALPHA_MIN: f32 = 1e-3;

/// Clamp a roughness to [`ALPHA_MIN`, 1]; NaN becomes 1.
#[inline]
pub fn clamp_alpha(alpha: f32) -> f32 {
    if alpha.is_nan() {
        1.0
    } else {
        alpha.clamp(ALPHA_MIN, 1.0)
    }
}

/// Anisotropic GGX normal distribution D(m) with roughness (αx, αy), zero below the horizon.
#[inline]
pub fn ggx_d(m: Vec3, ax: f32, ay: f32) -> f32 {
    if m.z <= 0.0 {
        return 0.0;
    }
    let x = m.x / ax;
    let y = m.y / ay;
    let t = x * x + y * y + m.z * m.z;
    1.0 / (PI * ax * ay * t * t)
}

/// Smith Λ for GGX.
#[inline]
pub fn ggx_lambda(w: Vec3, ax: f32, ay: f32) -> f32 {
    let z2 = w.z * w.z;
    if z2 <= 0.0 {
        return f32::MAX;
    }
    let a2t2 = (ax * ax * w.x * w.x + ay * ay * w.y * w.y) / z2;
    0.5 * (-1.0 + (1.0 + a2t2).sqrt())
}

/// Λ of an isotropic GGX of roughness α for a direction at cosine `c` to the normal:
/// (−1 + √(1 + α² tan²θ)) / 2; `f32::MAX` at or below the horizon.
#[inline]
pub fn ggx_lambda_iso(c: f32, alpha: f32) -> f32 {
    let c2 = c * c;
    if !(c > 0.0) {
        return f32::MAX;
    }
    let a2t2 = alpha * alpha * (1.0 - c2).max(0.0) / c2;
    0.5 * (-1.0 + (1.0 + a2t2).sqrt())
}

/// Smith masking G1(w).
#[inline]
pub fn ggx_g1(w: Vec3, ax: f32, ay: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(w, ax, ay))
}

/// Height-correlated Smith shadowing–masking G2(wi, wo) = 1 / (1 + Λ(wi) + Λ(wo)) (Heitz 2014,
/// "Understanding the Masking-Shadowing Function", Eq. 99). This is the form used throughout.
#[inline]
pub fn ggx_g2(wi: Vec3, wo: Vec3, ax: f32, ay: f32) -> f32 {
    let l = ggx_lambda(wi, ax, ay) + ggx_lambda(wo, ax, ay);
    if l >= f32::MAX {
        0.0
    } else {
        1.0 / (1.0 + l)
    }
}

/// Samples a visible normal for a view direction `wo` (wo.z > 0) from the GGX distribution of
/// visible normals (Heitz 2018, "Sampling the GGX Distribution of Visible Normals").
#[inline]
pub fn ggx_sample_vndf(wo: Vec3, ax: f32, ay: f32, u: Vec2) -> Vec3 {
    // Stretch the view direction to the hemisphere configuration.
    let vh = Vec3::new(ax * wo.x, ay * wo.y, wo.z).normalize_or(Vec3::Z);
    // Orthonormal basis around vh.
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    // Sample the projected area.
    let r = u.x.sqrt();
    let phi = 2.0 * PI * u.y;
    let p1 = r * phi.cos();
    let mut p2 = r * phi.sin();
    let s = 0.5 * (1.0 + vh.z);
    p2 = (1.0 - s) * safe_sqrt(1.0 - p1 * p1) + s * p2;
    // Reproject onto the hemisphere and unstretch.
    let nh = t1 * p1 + t2 * p2 + vh * safe_sqrt(1.0 - p1 * p1 - p2 * p2);
    Vec3::new(ax * nh.x, ay * nh.y, nh.z.max(1e-7)).normalize_or(Vec3::Z)
}

/// Density of the visible normal `m` for view `wo`: G1(wo) max(0, wo·m) D(m) / wo.z.
#[inline]
pub fn ggx_vndf_pdf(wo: Vec3, m: Vec3, ax: f32, ay: f32) -> f32 {
    if wo.z <= 0.0 {
        return 0.0;
    }
    ggx_g1(wo, ax, ay) * wo.dot(m).max(0.0) * ggx_d(m, ax, ay) / wo.z
}

/// Schlick weight F_c = (1 - |h·o|)^5.
#[inline]
pub fn schlick_weight(cos_theta: f32) -> f32 {
    let m = (1.0 - cos_theta.abs()).clamp(0.0, 1.0);
    let m2 = m * m;
    m2 * m2 * m
}

/// Schlick's Fresnel F = r0 (1 - F_c) + f90 F_c. The paper's Eq. 11 has f90 = 1;
/// KHR_materials_specular sets f90 = specularFactor for dielectrics.
#[inline]
pub fn schlick(r0: Vec3, f90: f32, cos_theta: f32) -> Vec3 {
    let fc = schlick_weight(cos_theta);
    r0 * (1.0 - fc) + Vec3::splat(f90 * fc)
}

/// Mirror reflection of `w` about `n`.
#[inline]
pub fn reflect(w: Vec3, n: Vec3) -> Vec3 {
    2.0 * w.dot(n) * n - w
}

/// ∫ D_ggx over the hemisphere in closed form: M5(α) = 1 + α² atanh(q)/q, q = sqrt(1 − α²)
/// (from ∫₀¹ dt / (1 + k t²)² with k = α² − 1).
pub fn m5_exact(alpha: f32) -> f32 {
    let a = alpha.clamp(ALPHA_MIN, 1.0) as f64;
    let q = (1.0 - a * a).max(0.0).sqrt();
    let r = if q < 1e-6 {
        1.0 + q * q / 3.0
    } else {
        q.atanh() / q
    };
    (1.0 + a * a * r) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;
    use crate::math::sampling::square_to_uniform_sphere;

    /// ∫ D(m) (m·z) dm = 1 over the hemisphere, estimated with 200k uniform sphere samples:
    /// relative standard error below 1% for α ≥ 0.2; checked at 3%.
    #[test]
    fn ggx_projected_area_is_one() {
        for (ax, ay) in [(0.2, 0.2), (0.5, 0.5), (1.0, 1.0), (0.3, 0.8)] {
            let mut rng = Pcg32::new(1, 2);
            let n = 200_000;
            let mut sum = 0.0f64;
            for _ in 0..n {
                let m = square_to_uniform_sphere(rng.next_2d());
                sum += (ggx_d(m, ax, ay) * m.z.max(0.0)) as f64 * 4.0 * PI as f64;
            }
            let est = sum / n as f64;
            assert!((est - 1.0).abs() < 0.03, "α=({ax},{ay}): {est}");
        }
    }

    /// The visible normal distribution integrates to one: ∫ G1(o) max(0,o·m) D(m)/o.z dm = 1.
    #[test]
    fn vndf_normalised() {
        let mut rng = Pcg32::new(3, 4);
        for (ax, ay, theta) in [(0.3f32, 0.3f32, 0.3f32), (0.6, 0.2, 1.2), (1.0, 1.0, 1.5)] {
            let wo = Vec3::new(theta.sin(), 0.0, theta.cos());
            let n = 200_000;
            let mut sum = 0.0f64;
            for _ in 0..n {
                let m = square_to_uniform_sphere(rng.next_2d());
                sum += ggx_vndf_pdf(wo, m, ax, ay) as f64 * 4.0 * PI as f64;
            }
            let est = sum / n as f64;
            assert!((est - 1.0).abs() < 0.03, "{est}");
        }
    }

    #[test]
    fn degenerate_inputs_are_finite() {
        let a = ALPHA_MIN;
        for w in [
            Vec3::Z,
            Vec3::X,
            Vec3::new(0.0, 0.0, 1e-9),
            Vec3::new(1.0, 0.0, 1e-7).normalize(),
        ] {
            assert!(ggx_g1(w, a, a).is_finite());
            assert!(ggx_g2(w, w, a, a).is_finite());
            let m = ggx_sample_vndf(w, a, a, Vec2::new(0.999, 0.5));
            assert!(m.is_finite() && m.z > 0.0);
            assert!(ggx_d(m, a, a).is_finite());
        }
        assert_eq!(clamp_alpha(0.0), ALPHA_MIN);
        assert_eq!(clamp_alpha(f32::NAN), 1.0);
    }
}
