//! Image comparison with the paper's metric.
//!
//! - RMSE = sqrt(mean over pixels and RGB channels of (a − b)²), on linear values; best 0.
//! - relMSE = mean over pixels and channels of (a − b)² / (b² + 0.01), with `b` the second
//!   (reference) image; best 0. The 0.01 keeps black reference pixels from dominating.

use glam::Vec3;
use serde::Serialize;

use crate::film::Image;

/// Comparison figures.
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct Comparison {
    /// Root-mean-square error over all pixels and channels.
    pub rmse: f64,
    /// Mean relative squared error, (a − b)² / (b² + 0.01) per channel, b the reference.
    pub relmse: f64,
    /// Width of both images.
    pub width: u32,
    /// Height of both images.
    pub height: u32,
}

/// Compares `a` against reference `b`. Errors when the sizes differ.
pub fn compare(a: &Image, b: &Image) -> Result<Comparison, String> {
    if a.width != b.width || a.height != b.height {
        return Err(format!(
            "image sizes differ: {}x{} against {}x{}",
            a.width, a.height, b.width, b.height
        ));
    }
    let mut se = 0f64;
    let mut rel = 0f64;
    for (p, q) in a.pixels.iter().zip(&b.pixels) {
        for c in 0..3 {
            let d = (p[c] - q[c]) as f64;
            se += d * d;
            rel += d * d / ((q[c] as f64).powi(2) + 0.01);
        }
    }
    let n = (a.pixels.len() * 3).max(1) as f64;
    Ok(Comparison {
        rmse: (se / n).sqrt(),
        relmse: rel / n,
        width: a.width,
        height: a.height,
    })
}

/// The error on an object's own pixels: those at least half covered by it (a coverage such as
/// [`crate::render::reference::coverage`] gives), so that a wrong object cannot hide in the
/// sky around it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ObjectComparison {
    /// Pixels counted.
    pub pixels: usize,
    /// Σ a / Σ b over those pixels and the three channels: 1.03 is 3% too bright.
    pub mean_ratio: f64,
    /// RMSE over those pixels and channels divided by the mean of b there.
    pub relative_rmse: f64,
}

/// Compares `a` against reference `b` on the pixels whose `coverage` is at least 1/2 (one value
/// per pixel, row by row). Errors when the sizes differ; NaN ratios when no pixel counts.
pub fn compare_on_object(
    a: &Image,
    b: &Image,
    coverage: &[f32],
) -> Result<ObjectComparison, String> {
    if a.width != b.width || a.height != b.height || coverage.len() != b.pixels.len() {
        return Err(format!(
            "image sizes differ: {}x{} against {}x{} with a coverage of {} pixels",
            a.width,
            a.height,
            b.width,
            b.height,
            coverage.len()
        ));
    }
    let (mut sa, mut sb, mut se, mut n) = (0f64, 0f64, 0f64, 0usize);
    for ((p, q), &c) in a.pixels.iter().zip(&b.pixels).zip(coverage) {
        if !(c >= 0.5) {
            continue;
        }
        n += 1;
        for k in 0..3 {
            let (x, y) = (p[k] as f64, q[k] as f64);
            sa += x;
            sb += y;
            se += (x - y) * (x - y);
        }
    }
    let m = (3 * n) as f64;
    Ok(ObjectComparison {
        pixels: n,
        mean_ratio: sa / sb,
        relative_rmse: (se / m).sqrt() / (sb / m),
    })
}

/// A false-colour image of the per-pixel absolute difference (mean over channels), black for
/// zero through blue, magenta and yellow to white at `scale`. Returns the image and the scale
/// (the 99th percentile of the difference unless given).
pub fn difference_image(a: &Image, b: &Image, scale: Option<f32>) -> (Image, f32) {
    let diffs: Vec<f32> = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(p, q)| {
            let d = (*p - *q).abs();
            let m = (d.x + d.y + d.z) / 3.0;
            if m.is_finite() {
                m
            } else {
                f32::MAX
            }
        })
        .collect();
    let scale = scale.unwrap_or_else(|| {
        let mut s = diffs.clone();
        s.sort_by(|x, y| x.total_cmp(y));
        s.get(((s.len() as f32 * 0.99) as usize).min(s.len().saturating_sub(1)))
            .copied()
            .unwrap_or(1.0)
            .max(1e-6)
    });
    let pixels = diffs
        .iter()
        .map(|&d| {
            let t = (d / scale).clamp(0.0, 1.0);
            // A small "inferno"-like ramp.
            let stops = [
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(0.2, 0.05, 0.5),
                Vec3::new(0.8, 0.15, 0.4),
                Vec3::new(1.0, 0.6, 0.1),
                Vec3::new(1.0, 1.0, 0.9),
            ];
            let x = t * 4.0;
            let i = (x as usize).min(3);
            let f = x - i as f32;
            let c = stops[i] * (1.0 - f) + stops[i + 1] * f;
            // Stored linear so that the sRGB PNG shows the ramp as designed.
            c.powf(2.2)
        })
        .collect();
    (
        Image {
            width: a.width,
            height: a.height,
            pixels,
        },
        scale,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        let a = Image {
            width: 2,
            height: 1,
            pixels: vec![Vec3::ZERO, Vec3::ONE],
        };
        let mut b = a.clone();
        assert_eq!(compare(&a, &b).unwrap().rmse, 0.0);
        b.pixels[1] = Vec3::new(1.0, 1.0, 3.0);
        // One of six channel values differs by 2: sqrt(4/6).
        let c = compare(&a, &b).unwrap();
        assert!((c.rmse - (4.0f64 / 6.0).sqrt()).abs() < 1e-12);
        assert!((c.relmse - 4.0 / 9.01 / 6.0).abs() < 1e-9);
        assert!(compare(&a, &Image::new(1, 2)).is_err());
        let (d, s) = difference_image(&a, &b, None);
        assert!(s > 0.0 && d.pixels[0] == Vec3::ZERO && d.pixels[1].max_element() > 0.0);
    }
}

/// What `aggtool compare` reports: the [`Comparison`] of two image files and the difference
/// image written, if asked for.
#[derive(Clone, Debug, Serialize)]
pub struct CompareReport {
    /// The figures.
    #[serde(flatten)]
    pub comparison: Comparison,
    /// The false-colour difference image written (PNG), if any.
    pub diff: Option<String>,
    /// The difference the diff image's white stands for.
    pub diff_white: Option<f32>,
}

/// Reads two linear images (EXR, PFM, HDR; 8-bit formats are refused), compares `a` against
/// the reference `b`, and writes the difference image to `diff` if given.
pub fn compare_files(
    a: &std::path::Path,
    b: &std::path::Path,
    diff: Option<&std::path::Path>,
) -> anyhow::Result<CompareReport> {
    let ia = Image::read_linear(a)?;
    let ib = Image::read_linear(b)?;
    let comparison = compare(&ia, &ib).map_err(anyhow::Error::msg)?;
    let mut report = CompareReport {
        comparison,
        diff: None,
        diff_white: None,
    };
    if let Some(d) = diff {
        let (img, scale) = difference_image(&ia, &ib, None);
        img.write_png(d, 0.0)?;
        report.diff = Some(d.display().to_string());
        report.diff_white = Some(scale);
    }
    Ok(report)
}

impl std::fmt::Display for CompareReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if let (Some(d), Some(s)) = (&self.diff, self.diff_white) {
            writeln!(f, "diff: {d} (white = {s:.4})")?;
        }
        let c = &self.comparison;
        write!(
            f,
            "rmse {:.6}  relmse {:.6}  ({}x{})",
            c.rmse, c.relmse, c.width, c.height
        )
    }
}
