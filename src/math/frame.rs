//! Orthonormal frames.

use glam::Vec3;

/// An orthonormal basis whose `z` axis is a given unit normal.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    /// First tangent.
    pub x: Vec3,
    /// Second tangent (`z × x`).
    pub y: Vec3,
    /// The normal.
    pub z: Vec3,
}

impl Frame {
    /// Branchless construction of Duff et al. 2017, "Building an Orthonormal Basis, Revisited".
    #[inline]
    pub fn from_z(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let x = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let y = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { x, y, z: n }
    }

    /// World direction to local coordinates.
    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.x), v.dot(self.y), v.dot(self.z))
    }

    /// Local coordinates to world direction.
    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.x * v.x + self.y * v.y + self.z * v.z
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn orthonormal_for_all_axes() {
        for n in [
            Vec3::X,
            Vec3::Y,
            Vec3::Z,
            -Vec3::Z,
            -Vec3::X,
            Vec3::new(1.0, 2.0, -3.0).normalize(),
            Vec3::new(0.0, 1e-8, -1.0).normalize(),
        ] {
            let f = Frame::from_z(n);
            assert!(f.x.dot(f.y).abs() < 1e-5 && f.x.dot(f.z).abs() < 1e-5);
            assert!((f.x.length() - 1.0).abs() < 1e-5 && (f.y.length() - 1.0).abs() < 1e-5);
            assert!(f.x.cross(f.y).dot(f.z) > 0.99);
            let v = Vec3::new(0.3, -0.4, 0.5);
            assert!((f.to_local(f.to_world(v)) - v).length() < 1e-5);
        }
    }
}
