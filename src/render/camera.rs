//! Pinhole camera.

use glam::{Vec2, Vec3};

use super::view::CameraDesc;
use crate::trace::Ray;

/// A pinhole camera: right = forward × up, image row 0 at the top (Mitsuba's convention for
/// `look_at`, so that images line up with Mitsuba's).
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub eye: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    tan_half_y: f32,
    aspect: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    pub fn new(desc: &CameraDesc) -> Self {
        let eye = Vec3::from(desc.eye);
        let forward = (Vec3::from(desc.target) - eye).normalize_or(-Vec3::Z);
        let right = forward.cross(Vec3::from(desc.up)).normalize_or(Vec3::X);
        let up = right.cross(forward);
        Camera {
            eye,
            forward,
            right,
            up,
            tan_half_y: (desc.fov_y_deg.to_radians() * 0.5).tan(),
            aspect: desc.width as f32 / desc.height as f32,
            width: desc.width,
            height: desc.height,
        }
    }

    /// The primary ray through film position `p` in pixels ((0,0) top-left corner).
    #[inline]
    pub fn ray(&self, p: Vec2) -> Ray {
        let x = (2.0 * p.x / self.width as f32 - 1.0) * self.tan_half_y * self.aspect;
        let y = (1.0 - 2.0 * p.y / self.height as f32) * self.tan_half_y;
        let dir = (self.forward + x * self.right + y * self.up).normalize();
        Ray::new(self.eye, dir)
    }

    /// Solid angle of the pixel footprint at the image centre (for cone tracing later).
    pub fn pixel_angle(&self) -> f32 {
        2.0 * self.tan_half_y / self.height as f32
    }
}
