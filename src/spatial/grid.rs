//! The grid of one level: `res³` cubic voxels over a cube, and the two box computations every
//! voxel test uses (the ray's interval inside a box, a box's projected area).

use glam::{UVec3, Vec3};

/// The grid of one level: `res³` cubic voxels over a cube.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// The cube's minimum corner.
    pub origin: Vec3,
    /// Edge length of the whole cube.
    pub size: f32,
    /// Voxels per axis.
    pub res: u32,
}

impl Grid {
    /// A cube around the scene's bounds (the largest extent, centred, padded by 0.1%).
    pub fn around(lo: Vec3, hi: Vec3, res: u32) -> Grid {
        let ext = (hi - lo).max_element().max(1e-6) * 1.001;
        let c = 0.5 * (lo + hi);
        Grid {
            origin: c - Vec3::splat(0.5 * ext),
            size: ext,
            res,
        }
    }

    /// Edge length of one voxel.
    #[inline]
    pub fn voxel_size(&self) -> f32 {
        self.size / self.res as f32
    }

    /// World-space bounds of voxel `v`.
    #[inline]
    pub fn voxel_bounds(&self, v: UVec3) -> (Vec3, Vec3) {
        let s = self.voxel_size();
        let lo = self.origin + v.as_vec3() * s;
        (lo, lo + Vec3::splat(s))
    }

    /// The cube's corners.
    #[inline]
    pub fn bounds(&self) -> (Vec3, Vec3) {
        (self.origin, self.origin + Vec3::splat(self.size))
    }

    /// The same cube at another resolution.
    pub fn with_res(&self, res: u32) -> Grid {
        Grid { res, ..*self }
    }
}

/// Parameter interval of `o + t d` inside the box (may be empty: t0 > t1). A ray parallel to
/// a slab is inside it for every t or for none, including a ray lying in a slab's plane (where
/// the usual (lo − o)·(1/d) gives 0·∞ = NaN).
#[inline]
pub fn box_interval(lo: Vec3, hi: Vec3, o: Vec3, inv_d: Vec3) -> (f32, f32) {
    let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
    for a in 0..3 {
        if inv_d[a].is_infinite() {
            if o[a] < lo[a] || o[a] > hi[a] {
                return (f32::INFINITY, f32::NEG_INFINITY);
            }
            continue;
        }
        let (x, y) = ((lo[a] - o[a]) * inv_d[a], (hi[a] - o[a]) * inv_d[a]);
        t0 = t0.max(x.min(y));
        t1 = t1.min(x.max(y));
    }
    (t0, t1)
}

/// Projected area of an axis-aligned box of extents `e` along unit `w`.
#[inline]
pub fn box_projected_area(e: Vec3, w: Vec3) -> f32 {
    w.x.abs() * e.y * e.z + w.y.abs() * e.x * e.z + w.z.abs() * e.x * e.y
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_interval_in_a_slab_plane() {
        // A ray lying in the plane x = 0 of the unit box's face is inside that slab.
        let (t0, t1) = box_interval(
            Vec3::ZERO,
            Vec3::ONE,
            Vec3::new(0.0, 0.5, -1.0),
            Vec3::Z.recip(),
        );
        assert!((t0 - 1.0).abs() < 1e-6 && (t1 - 2.0).abs() < 1e-6);
        let (t0, t1) = box_interval(
            Vec3::ZERO,
            Vec3::ONE,
            Vec3::new(-0.1, 0.5, -1.0),
            Vec3::Z.recip(),
        );
        assert!(t0 > t1);
        assert!((box_projected_area(Vec3::ONE, Vec3::Z) - 1.0).abs() < 1e-6);
    }
}
