//! Decoded textures, stored as linear RGBA f32 and sampled bilinearly.

use glam::{Vec2, Vec4};

/// glTF sampler wrap modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum WrapMode {
    /// Coordinates wrap around (the glTF default).
    #[default]
    Repeat,
    /// Coordinates wrap around, every other repeat mirrored.
    MirroredRepeat,
    /// Coordinates clamp to the edge texels.
    ClampToEdge,
}

/// A texture: `width × height` texels, row 0 at the top (v = 0), linear values.
#[derive(Clone, Debug)]
pub struct Texture {
    /// The image's name or URI in the asset, for messages.
    pub name: String,
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// Linear RGBA texels, row by row.
    pub texels: Vec<Vec4>,
    /// Wrap mode along u.
    pub wrap_s: WrapMode,
    /// Wrap mode along v.
    pub wrap_t: WrapMode,
}

#[inline]
fn wrap(i: i64, n: u32, mode: WrapMode) -> usize {
    let n = n as i64;
    (match mode {
        WrapMode::Repeat => i.rem_euclid(n),
        WrapMode::ClampToEdge => i.clamp(0, n - 1),
        WrapMode::MirroredRepeat => {
            let p = i.rem_euclid(2 * n);
            if p < n {
                p
            } else {
                2 * n - 1 - p
            }
        }
    }) as usize
}

impl Texture {
    /// A 1×1 texture of one value.
    pub fn constant(v: Vec4) -> Self {
        Texture {
            name: "constant".into(),
            width: 1,
            height: 1,
            texels: vec![v],
            wrap_s: WrapMode::Repeat,
            wrap_t: WrapMode::Repeat,
        }
    }

    #[inline]
    fn texel(&self, x: i64, y: i64) -> Vec4 {
        let xi = wrap(x, self.width, self.wrap_s);
        let yi = wrap(y, self.height, self.wrap_t);
        self.texels[yi * self.width as usize + xi]
    }

    /// Bilinear lookup at texture coordinate `uv` (texel centres at half-integers, as in GPUs).
    /// Non-finite coordinates read texel (0, 0).
    #[inline]
    pub fn sample(&self, uv: Vec2) -> Vec4 {
        if !uv.is_finite() {
            return self.texels[0];
        }
        // Keep far-away coordinates in a range where f32 still resolves texels (the period
        // of both repeat modes divides 2).
        let reduce = |c: f32, mode: WrapMode| {
            if c.abs() > 4096.0 && mode != WrapMode::ClampToEdge {
                c - 2.0 * (0.5 * c).floor()
            } else {
                c.clamp(-8192.0, 8192.0)
            }
        };
        let uv = Vec2::new(reduce(uv.x, self.wrap_s), reduce(uv.y, self.wrap_t));
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let x0 = x.floor();
        let y0 = y.floor();
        let fx = x - x0;
        let fy = y - y0;
        let (x0, y0) = (x0 as i64, y0 as i64);
        let a = self.texel(x0, y0);
        let b = self.texel(x0 + 1, y0);
        let c = self.texel(x0, y0 + 1);
        let d = self.texel(x0 + 1, y0 + 1);
        (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy
    }

    /// Bytes of texel storage.
    pub fn memory_bytes(&self) -> usize {
        self.texels.len() * std::mem::size_of::<Vec4>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checker() -> Texture {
        Texture {
            name: "c".into(),
            width: 2,
            height: 2,
            texels: vec![Vec4::ZERO, Vec4::ONE, Vec4::ONE, Vec4::ZERO],
            wrap_s: WrapMode::Repeat,
            wrap_t: WrapMode::ClampToEdge,
        }
    }

    #[test]
    fn texel_centres_and_wrap() {
        let t = checker();
        assert_eq!(t.sample(Vec2::new(0.25, 0.25)), Vec4::ZERO);
        assert_eq!(t.sample(Vec2::new(0.75, 0.25)), Vec4::ONE);
        assert_eq!(t.sample(Vec2::new(1.25, 0.25)), Vec4::ZERO);
        assert_eq!(t.sample(Vec2::new(0.25, 5.0)), Vec4::ONE);
        assert_eq!(t.sample(Vec2::new(f32::NAN, 0.0)), Vec4::ZERO);
        assert!(t.sample(Vec2::new(1e9, -1e9)).is_finite());
        assert_eq!(wrap(-1, 4, WrapMode::MirroredRepeat), 0);
        assert_eq!(wrap(4, 4, WrapMode::MirroredRepeat), 3);
    }
}
