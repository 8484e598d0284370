//! Linear RGB images: EXR in and out (the `exr` crate), tonemapped sRGB PNG out, all writes
//! atomic (temporary file in the destination folder, then rename).

use std::path::{Path, PathBuf};

use glam::Vec3;

use crate::math::color::linear_to_srgb;
use crate::util::write_atomic;

/// Errors reading or writing images.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The file could not be read or decoded.
    #[error("cannot read image {path}: {message}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// The file could not be encoded or written.
    #[error("cannot write image {path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// A linear RGB image, row-major, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Linear RGB radiance, `width × height`, row by row.
    pub pixels: Vec<Vec3>,
}

impl Image {
    /// A black image of `width × height` pixels.
    pub fn new(width: u32, height: u32) -> Self {
        Image {
            width,
            height,
            pixels: vec![Vec3::ZERO; width as usize * height as usize],
        }
    }

    /// The pixel at column `x`, row `y` (from the top).
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> Vec3 {
        self.pixels[(y * self.width + x) as usize]
    }

    /// Mean of all pixels.
    pub fn mean(&self) -> Vec3 {
        let s: glam::DVec3 = self.pixels.iter().map(|p| p.as_dvec3()).sum();
        (s / self.pixels.len().max(1) as f64).as_vec3()
    }

    /// Writes a linear float EXR.
    pub fn write_exr(&self, path: &Path) -> Result<(), ImageError> {
        let w = self.width as usize;
        write_atomic(path, |tmp| {
            exr::prelude::write_rgb_file(tmp, w, self.height as usize, |x, y| {
                let p = self.pixels[y * w + x];
                (p.x, p.y, p.z)
            })
            .map_err(|e| e.to_string())
        })
        .map_err(|message| ImageError::Write {
            path: path.to_path_buf(),
            message,
        })
    }

    /// Reads the first RGB(A) layer of an EXR file.
    pub fn read_exr(path: &Path) -> Result<Image, ImageError> {
        let err = |message: String| ImageError::Read {
            path: path.to_path_buf(),
            message,
        };
        let img = exr::prelude::read_first_rgba_layer_from_file(
            path,
            |res, _| {
                (
                    res.width(),
                    res.height(),
                    vec![Vec3::ZERO; res.width() * res.height()],
                )
            },
            |(w, _, px): &mut (usize, usize, Vec<Vec3>),
             pos,
             (r, g, b, _a): (f32, f32, f32, f32)| {
                px[pos.y() * *w + pos.x()] = Vec3::new(r, g, b);
            },
        )
        .map_err(|e| err(e.to_string()))?;
        let (w, h, pixels) = img.layer_data.channel_data.pixels;
        Ok(Image {
            width: w as u32,
            height: h as u32,
            pixels,
        })
    }

    /// Reads a colour PFM (`PF`, linear floats, rows bottom to top; either byte order), as C
    /// hosts write them.
    pub fn read_pfm(path: &Path) -> Result<Image, ImageError> {
        let err = |message: &str| ImageError::Read {
            path: path.to_path_buf(),
            message: message.to_string(),
        };
        let bytes = std::fs::read(path).map_err(|e| err(&e.to_string()))?;
        // Three whitespace-separated header lines: "PF", "W H", scale (negative: little-endian).
        let mut fields = Vec::new();
        let mut at = 0;
        while fields.len() < 4 && at < bytes.len() {
            while at < bytes.len() && bytes[at].is_ascii_whitespace() {
                at += 1;
            }
            let start = at;
            while at < bytes.len() && !bytes[at].is_ascii_whitespace() {
                at += 1;
            }
            fields.push(String::from_utf8_lossy(&bytes[start..at]).into_owned());
        }
        at += 1; // the single whitespace byte after the scale
        if fields.len() < 4 || fields[0] != "PF" {
            return Err(err("not a colour PFM (PF)"));
        }
        let parse = |s: &str| s.parse::<u32>().map_err(|_| err("bad PFM size"));
        let (width, height) = (parse(&fields[1])?, parse(&fields[2])?);
        let scale: f32 = fields[3].parse().map_err(|_| err("bad PFM scale"))?;
        let n = width as usize * height as usize;
        if width == 0 || height == 0 || bytes.len() < at || bytes.len() - at < 12 * n {
            return Err(err("truncated PFM"));
        }
        let little = scale < 0.0;
        let f = |i: usize| {
            let b: [u8; 4] = bytes[at + 4 * i..at + 4 * i + 4]
                .try_into()
                .expect("4 bytes");
            if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            }
        };
        let mut pixels = vec![Vec3::ZERO; n];
        for y in 0..height as usize {
            let row = height as usize - 1 - y;
            for x in 0..width as usize {
                let i = 3 * (row * width as usize + x);
                pixels[y * width as usize + x] = Vec3::new(f(i), f(i + 1), f(i + 2));
            }
        }
        Ok(Image {
            width,
            height,
            pixels,
        })
    }

    /// Reads an environment or image file: `.exr`, `.hdr` (linear), `.pfm`, or an 8-bit format
    /// (sRGB-decoded).
    pub fn read_any(path: &Path) -> Result<Image, ImageError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .unwrap_or_default();
        if ext == "exr" {
            return Image::read_exr(path);
        }
        if ext == "pfm" {
            return Image::read_pfm(path);
        }
        let err = |message: String| ImageError::Read {
            path: path.to_path_buf(),
            message,
        };
        let img = ::image::open(path).map_err(|e| err(e.to_string()))?;
        let srgb = !matches!(ext.as_str(), "hdr");
        let rgb = img.to_rgb32f();
        let lut = |v: f32| {
            if srgb {
                crate::math::color::srgb_to_linear(v)
            } else {
                v
            }
        };
        Ok(Image {
            width: rgb.width(),
            height: rgb.height(),
            pixels: rgb
                .pixels()
                .map(|p| Vec3::new(lut(p[0]), lut(p[1]), lut(p[2])))
                .collect(),
        })
    }

    /// Reads an image of linear radiance for measuring: `.exr`, `.pfm` or `.hdr`. Any other
    /// format (PNG, JPEG, …) is refused, not decoded: its values went through a tonemap (the
    /// PNG `render` and `reference` write beside their EXR is exposed, clamped to [0, 1] and
    /// sRGB-encoded), so errors measured on them are not errors in radiance.
    pub fn read_linear(path: &Path) -> Result<Image, ImageError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .unwrap_or_default();
        if !matches!(ext.as_str(), "exr" | "pfm" | "hdr") {
            let what = if ext.is_empty() {
                "a file without an extension".to_string()
            } else {
                format!("a .{ext} file")
            };
            return Err(ImageError::Read {
                path: path.to_path_buf(),
                message: format!(
                    "{what} is not linear: give an EXR, PFM or HDR image (an 8-bit image such as \
                     a PNG or JPEG holds tonemapped, clamped, sRGB-encoded values, not radiance; \
                     `render` and `reference` write the EXR beside their PNG)"
                ),
            });
        }
        Image::read_any(path)
    }

    /// 8-bit sRGB bytes after exposure `2^stops`, clamped.
    pub fn to_srgb8(&self, stops: f32) -> Vec<u8> {
        let k = 2f32.powf(stops);
        self.pixels
            .iter()
            .flat_map(|p| {
                let q = *p * k;
                [q.x, q.y, q.z].map(|c| (linear_to_srgb(c) * 255.0 + 0.5) as u8)
            })
            .collect()
    }

    /// Writes a tonemapped sRGB PNG (clamp after exposure).
    pub fn write_png(&self, path: &Path, stops: f32) -> Result<(), ImageError> {
        write_rgb8_png(path, self.width, self.height, &self.to_srgb8(stops))
    }
}

/// Writes 8-bit RGB bytes as a PNG, atomically.
pub fn write_rgb8_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), ImageError> {
    write_atomic(path, |tmp| {
        ::image::save_buffer_with_format(
            tmp,
            rgb,
            width,
            height,
            ::image::ColorType::Rgb8,
            ::image::ImageFormat::Png,
        )
        .map_err(|e| e.to_string())
    })
    .map_err(|message| ImageError::Write {
        path: path.to_path_buf(),
        message,
    })
}

/// Places equally sized sRGB8 images (`w × h` pixels each) side by side, left to right, and
/// writes them as one PNG, atomically: the demo's and `absdf-plot`'s pictures.
pub fn side_by_side(path: &Path, images: &[&[u8]], w: u32, h: u32) -> Result<(), ImageError> {
    let n = images.len() as u32;
    let mut rgb = vec![0u8; (n * w * h * 3) as usize];
    for (k, img) in images.iter().enumerate() {
        for y in 0..h {
            let src = &img[(y * w * 3) as usize..((y + 1) * w * 3) as usize];
            let dst = ((y * n * w + k as u32 * w) * 3) as usize;
            rgb[dst..dst + src.len()].copy_from_slice(src);
        }
    }
    write_rgb8_png(path, n * w, h, &rgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_round_trip_is_exact() {
        let dir = tempfile::tempdir().unwrap();
        let mut img = Image::new(7, 5);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            *p = Vec3::new(i as f32 * 0.1, 1e4, 1e-6 * i as f32);
        }
        let path = dir.path().join("a.exr");
        img.write_exr(&path).unwrap();
        assert_eq!(Image::read_exr(&path).unwrap(), img);
        img.write_png(&dir.path().join("a.png"), 0.0).unwrap();
        // Only the two outputs remain: no temporary files.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
        assert!(Image::read_exr(&dir.path().join("missing.exr")).is_err());
    }

    /// Two 2×1 images side by side: the first fills columns 0–1 of each row, the second 2–3.
    #[test]
    fn side_by_side_places_images_left_to_right() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = ([10u8; 2 * 3], [200u8; 2 * 3]);
        let path = dir.path().join("s.png");
        side_by_side(&path, &[&a, &b], 2, 1).unwrap();
        let img = ::image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (4, 1));
        let row: Vec<u8> = img.pixels().map(|p| p[0]).collect();
        assert_eq!(row, [10, 10, 200, 200]);
    }
}
