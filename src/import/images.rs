//! Texture decoding with the `image` crate.

use glam::Vec4;

use crate::math::color::srgb8_table;
use crate::scene::{Texture, WrapMode};

/// Decodes an encoded image (PNG, JPEG, …). `srgb` linearises the colour channels (base colour);
/// data textures (metallic-roughness) keep their values. Alpha is always linear.
pub fn decode_texture(
    bytes: &[u8],
    name: &str,
    srgb: bool,
    wrap: (WrapMode, WrapMode),
) -> Result<Texture, String> {
    let img = image::load_from_memory(bytes).map_err(|e| format!("cannot decode image: {e}"))?;
    let rgba = img.to_rgba8();
    let (w, h) = rgba.dimensions();
    if w == 0 || h == 0 {
        return Err("image has zero size".into());
    }
    let lut = srgb8_table();
    let texels = rgba
        .pixels()
        .map(|p| {
            let c = |v: u8| {
                if srgb {
                    lut[v as usize]
                } else {
                    v as f32 / 255.0
                }
            };
            Vec4::new(c(p[0]), c(p[1]), c(p[2]), p[3] as f32 / 255.0)
        })
        .collect();
    Ok(Texture {
        name: name.to_string(),
        width: w,
        height: h,
        texels,
        wrap_s: wrap.0,
        wrap_t: wrap.1,
    })
}
