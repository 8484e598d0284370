//! Pure math shared by every stage: colour, frames, random numbers, sampling warps, spherical
//! parameterisations and microfacet distributions. Nothing here knows about scenes or files.

pub mod beta;
pub mod color;
pub mod distribution;
pub mod frame;
pub mod haar;
pub mod lowdiscrepancy;
pub mod microfacet;
pub mod rng;
pub mod sampling;
pub mod sg;
pub mod sggx;
pub mod special;
pub mod sphere_maps;
pub mod spherical;

pub use glam::{Vec2, Vec3};

/// Replace NaN and infinities by zero: the last line of defence before a value leaves a
/// function that promises finite output.
#[inline]
pub fn finite_or_zero(x: f32) -> f32 {
    if x.is_finite() {
        x
    } else {
        0.0
    }
}

/// Component-wise [`finite_or_zero`].
#[inline]
pub fn finite_vec_or_zero(v: Vec3) -> Vec3 {
    if v.is_finite() {
        v
    } else {
        Vec3::ZERO
    }
}

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
