//! Pinhole camera.

use glam::{Vec2, Vec3};

/// A pinhole camera: right = forward × up, image row 0 at the top (Mitsuba's convention for
/// `look_at`, so that images line up with Mitsuba's).
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    /// The eye.
    pub eye: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    tan_half_y: f32,
    aspect: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// A camera at `eye` looking at `target`, `fov_y_deg` the vertical field of view.
    pub fn look_at(
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        fov_y_deg: f32,
        width: u32,
        height: u32,
    ) -> Self {
        let forward = (target - eye).normalize_or(-Vec3::Z);
        let right = forward.cross(up).normalize_or(Vec3::X);
        let up = right.cross(forward);
        Camera {
            eye,
            forward,
            right,
            up,
            tan_half_y: (fov_y_deg.to_radians() * 0.5).tan(),
            aspect: width.max(1) as f32 / height.max(1) as f32,
            width,
            height,
        }
    }

    /// The primary ray through film position `p` in pixels ((0,0) top-left corner): origin and
    /// unit direction.
    #[inline]
    pub fn ray(&self, p: Vec2) -> (Vec3, Vec3) {
        let x = (2.0 * p.x / self.width as f32 - 1.0) * self.tan_half_y * self.aspect;
        let y = (1.0 - 2.0 * p.y / self.height as f32) * self.tan_half_y;
        let dir = (self.forward + x * self.right + y * self.up).normalize();
        (self.eye, dir)
    }

    /// The angle a pixel subtends at the image centre: the full aperture of a pixel's cone.
    pub fn pixel_angle(&self) -> f32 {
        2.0 * self.tan_half_y / self.height.max(1) as f32
    }
}
