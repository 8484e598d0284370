//! Voxel faces: a voxel and one of six axis directions. A level's boundary faces (paper §7.1)
//! carry the boundary visibility (Eq. 26); the runtime finds the face a ray entered the
//! aggregate by.

use glam::{UVec3, Vec3};

/// A voxel face: the voxel and the axis direction (0..6: −x, +x, −y, +y, −z, +z) it faces.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Face {
    /// The occupied voxel the face belongs to.
    pub voxel: UVec3Key,
    /// Its outward direction, an index into [`FACE_DIRS`].
    pub dir: u8,
}

/// A UVec3 usable as an ordered key (ordered by x, then y, then z).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct UVec3Key(pub u32, pub u32, pub u32);

impl From<UVec3> for UVec3Key {
    fn from(v: UVec3) -> Self {
        UVec3Key(v.x, v.y, v.z)
    }
}

impl From<UVec3Key> for UVec3 {
    fn from(k: UVec3Key) -> Self {
        UVec3::new(k.0, k.1, k.2)
    }
}

/// The six face directions as integer steps, in face-direction order (−x, +x, −y, +y, −z, +z).
pub const FACE_DIRS: [(i32, i32, i32); 6] = [
    (-1, 0, 0),
    (1, 0, 0),
    (0, -1, 0),
    (0, 1, 0),
    (0, 0, -1),
    (0, 0, 1),
];

/// The outward unit normal of a face direction (0..6: −x, +x, −y, +y, −z, +z).
#[inline]
pub fn face_normal(dir: u8) -> Vec3 {
    let axis = (dir / 2) as usize % 3;
    let mut n = Vec3::ZERO;
    n[axis] = if dir % 2 == 0 { -1.0 } else { 1.0 };
    n
}

/// The face a ray moving along `step` (±1 on `axis`) enters a voxel through: the −axis face
/// for a positive step, the +axis face for a negative one.
#[inline]
pub fn entry_face(axis: usize, step: i32) -> u8 {
    (2 * axis + (step < 0) as usize) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directions_agree() {
        for (d, s) in FACE_DIRS.iter().enumerate() {
            assert_eq!(
                face_normal(d as u8),
                Vec3::new(s.0 as f32, s.1 as f32, s.2 as f32)
            );
        }
        // Moving +x, a ray enters through the −x face, whose normal opposes the ray.
        assert_eq!(entry_face(0, 1), 0);
        assert_eq!(entry_face(2, -1), 5);
        assert!(face_normal(entry_face(1, 1)).dot(Vec3::Y) < 0.0);
    }
}
