//! Pure math shared by every stage: colour, frames, random numbers, sampling warps, spherical
//! parameterisations and microfacet distributions. Nothing here knows about scenes or files.

pub mod beta;
pub mod color;
pub mod cpca;
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

pub use glam::{Vec2, Vec3};

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
