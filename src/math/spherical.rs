//! Spherical parameterisations.
//!
//! The environment convention is Mitsuba 3's, so that images can be checked against it:
//! equirectangular, +Y up; a direction `d` is looked up at `u = atan2(d.x, -d.z) / 2π` wrapped to
//! [0, 1) and `v = acos(d.y) / π`, with `v = 0` the top row of the image.

use std::f32::consts::PI;

use glam::{Vec2, Vec3};

use super::safe_acos;

/// Direction to equirectangular (u, v) in [0, 1)×[0, 1].
#[inline]
pub fn dir_to_equirect(d: Vec3) -> Vec2 {
    let mut u = d.x.atan2(-d.z) * (0.5 / PI);
    if u < 0.0 {
        u += 1.0;
    }
    if u >= 1.0 {
        u -= 1.0;
    }
    Vec2::new(u, safe_acos(d.y) / PI)
}

/// Equirectangular (u, v) to unit direction; inverse of [`dir_to_equirect`].
#[inline]
pub fn equirect_to_dir(uv: Vec2) -> Vec3 {
    let phi = 2.0 * PI * uv.x;
    let theta = PI * uv.y;
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    Vec3::new(st * sp, ct, -st * cp)
}

/// Jacobian |dω / d(u,v)| of [`equirect_to_dir`]: 2π² sin θ.
#[inline]
pub fn equirect_jacobian(v: f32) -> f32 {
    2.0 * PI * PI * (PI * v).sin()
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn round_trip_and_convention() {
        // Up is the top row; -Z is the centre column's left edge (u = 0).
        assert!(dir_to_equirect(Vec3::Y).y.abs() < 1e-6);
        assert!((dir_to_equirect(-Vec3::Y).y - 1.0).abs() < 1e-6);
        assert!(dir_to_equirect(-Vec3::Z).x.abs() < 1e-6);
        assert!((dir_to_equirect(Vec3::X).x - 0.25).abs() < 1e-6);
        assert!((dir_to_equirect(Vec3::Z).x - 0.5).abs() < 1e-6);
        for i in 1..20 {
            for j in 0..20 {
                let uv = Vec2::new(j as f32 / 20.0 + 0.01, i as f32 / 20.0);
                let back = dir_to_equirect(equirect_to_dir(uv));
                assert!((back - uv).length() < 1e-4, "{uv} {back}");
            }
        }
    }
}
