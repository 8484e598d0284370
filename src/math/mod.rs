//! Pure math shared by every stage: colour, frames, random numbers, sampling warps, spherical
//! parameterisations and microfacet distributions. Nothing here knows about scenes or files.

pub mod beta;
pub mod color;
pub mod distribution;
pub mod frame;
pub mod haar;
pub mod lowdiscrepancy;
pub mod microfacet;
pub mod numerics;
pub mod rng;
pub mod sampling;
pub mod sg;
pub mod sggx;
pub mod special;
pub mod sphere_maps;
pub mod spherical;

use glam::Vec3;

pub use numerics::{finite_or_zero, finite_vec_or_zero};

/// `sqrt(max(x, 0))`.
#[inline]
pub fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

/// `acos` with its argument clamped to [-1, 1].
#[inline]
pub fn safe_acos(x: f32) -> f32 {
    x.clamp(-1.0, 1.0).acos()
}

/// `v` scaled to unit length, or zero when it has none (zero, non-finite). Unlike
/// `normalize_or_zero` it is idempotent: a vector within a few ulps of unit length comes back
/// unchanged, so a direction one function returned (a sampled ω_i) gives the same bits when
/// another normalises it again (the ABSDF's directional moments are looked up by cell, where
/// one ulp can cross a cell's edge).
#[inline]
pub fn unit_or_zero(v: Vec3) -> Vec3 {
    if (v.length_squared() - 1.0).abs() <= 4.0 * f32::EPSILON {
        v
    } else {
        v.normalize_or_zero()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Idempotent where normalize_or_zero is not, and zero for what has no direction.
    #[test]
    fn unit_or_zero_is_idempotent() {
        let mut rng = rng::Pcg32::new(3, 7);
        let mut moved = 0;
        for _ in 0..100_000 {
            let v = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 1.0;
            let u = unit_or_zero(v);
            assert_eq!(unit_or_zero(u), u);
            assert!(u == Vec3::ZERO || (u.length() - 1.0).abs() < 1e-6);
            moved += (u.normalize_or_zero() != u) as u32;
        }
        assert!(
            moved > 0,
            "normalize_or_zero was idempotent on every vector here"
        );
        for v in [
            Vec3::ZERO,
            Vec3::NAN,
            Vec3::INFINITY,
            Vec3::new(f32::NAN, 0.0, 1.0),
        ] {
            assert_eq!(unit_or_zero(v), Vec3::ZERO);
        }
    }
}
