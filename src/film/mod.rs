//! Images and the one image loop every renderer uses: the pinhole [`Camera`], linear RGB
//! [`Image`]s with EXR and PNG I/O, and [`render_image`], which the reference path tracer and
//! the LoD runtime both render through, with the LoD's [`Stratified`] sampler over a pixel's
//! samples. The same stratified pixel sampling, the same seed scheme (one random stream per
//! pixel, so images do not depend on the thread count), the same progress reports and the same
//! [`ImageStats`], so that equal-spp figures compare like with like.

mod camera;
mod image;
mod stratified;

pub use camera::Camera;
pub use image::{side_by_side, write_rgb8_png, Image, ImageError};
pub use stratified::{Stratified, STRATIFIED_DIMENSIONS};

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::math::numerics::non_finite_count;
use crate::math::rng::{mix64, Pcg32};
use crate::util::{Progress, StageCounter};

/// Tile edge of the parallel loop.
const TILE: u32 = 16;

/// Figures of a finished render.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct ImageStats {
    /// Wall-clock seconds of the loop.
    pub seconds: f64,
    /// Samples (camera rays or cones) rendered.
    pub samples: u64,
    /// Rays traced, as the renderer counts them (camera, shadow and BSDF rays for the
    /// reference; cones for the LoD).
    pub rays: u64,
    /// Samples whose value was NaN or infinite, left out of their pixel.
    pub invalid_samples: u64,
    /// Non-finite values that functions replaced by zero on the way
    /// ([`crate::math::numerics`]): zero in a healthy render.
    pub non_finite: u64,
}

impl ImageStats {
    /// Rays per second.
    pub fn rays_per_second(&self) -> f64 {
        self.rays as f64 / self.seconds.max(1e-9)
    }

    /// The `stats:` line both renderers print.
    pub fn line(&self, what: &str) -> String {
        format!(
            "stats: {what} render {:.2} s, {} samples, {} rays ({:.2} Mrays/s), {} invalid samples, {} non-finite values",
            self.seconds,
            self.samples,
            self.rays,
            self.rays_per_second() / 1e6,
            self.invalid_samples,
            self.non_finite
        )
    }
}

/// Jittered position of sample `s` of `spp` inside a pixel: stratified on a √spp grid when spp
/// is a perfect square, uniform otherwise.
#[inline]
pub fn jitter(s: u32, spp: u32, rng: &mut Pcg32) -> Vec2 {
    let n = (spp as f32).sqrt() as u32;
    let u = rng.next_2d();
    if n * n == spp && n > 1 {
        Vec2::new(
            ((s % n) as f32 + u.x) / n as f32,
            ((s / n) as f32 + u.y) / n as f32,
        )
    } else {
        u
    }
}

/// What a renderer's per-sample function gets: the sample's film position and its camera ray
/// ([`Sample::ray`]), the cone aperture of a pixel, the pixel's random stream, and a counter
/// of rays it traced.
pub struct Sample<'a> {
    /// The film position (pixels, [`Camera::ray`]'s coordinates): the pixel plus its jitter.
    pub film: Vec2,
    /// The camera the image is seen through.
    pub camera: &'a Camera,
    /// Full aperture of the pixel's cone (radians).
    pub aperture: f32,
    /// The pixel's random stream (seeded by the render seed and the pixel index).
    pub rng: &'a mut Pcg32,
    /// Rays traced for this sample (the renderer adds to it).
    pub rays: &'a mut u64,
    /// The sample's index in its pixel, 0..spp: with `pixel_seed`, what a sampler stratified
    /// over the pixel's samples draws from ([`Stratified`]); the reference
    /// renderer draws everything from `rng`.
    pub index: u32,
    /// A seed of the pixel's own (from the render seed and the pixel index, not from `rng`).
    pub pixel_seed: u32,
    /// The pixel (column, row); its area is [x, x + 1) × [y, y + 1) in [`Camera::ray`]'s
    /// coordinates.
    pub pixel: glam::UVec2,
}

impl Sample<'_> {
    /// The camera ray through the sample's film position: origin and unit direction. Made
    /// when asked: a LoD pixel's shared walks trace cones of their own
    /// ([`crate::runtime::TraceSettings::samples_per_walk`]), and making every sample's ray
    /// anyway was 4% of such a render (the maple's 128³ bake at 256², 64 spp: 1.35 against
    /// 1.41 CPU s, the same bits).
    #[inline]
    pub fn ray(&self) -> (Vec3, Vec3) {
        self.camera.ray(self.film)
    }
}

/// The seed of pixel `pixel`'s own stratification under render seed `seed`
/// ([`Sample::pixel_seed`]): one hash of both, independent of the pixel's random stream. The
/// image loop and a host's stratified batch ([`crate::runtime::trace_batch_stratified_with`])
/// seed a pixel alike.
#[inline]
pub fn pixel_seed(seed: u64, pixel: u64) -> u32 {
    (mix64(seed ^ mix64(pixel)) >> 32) as u32
}

/// Renders `camera`'s image with `spp` samples per pixel: `radiance(sample)` for each, over
/// 16×16 tiles in parallel. Pixel (x, y) draws from `Pcg32::new(seed, y·width + x)`, so the
/// image is the same for every thread count. Non-finite sample values are left out and
/// counted. `progress` hears of every tile, as stage `stage`.
pub fn render_image(
    camera: &Camera,
    spp: u32,
    seed: u64,
    stage: &str,
    progress: Progress,
    radiance: impl Fn(Sample) -> Vec3 + Sync,
) -> (Image, ImageStats) {
    render_image_with(
        camera,
        spp,
        seed,
        stage,
        progress,
        || (),
        |s, _| radiance(s),
    )
}

/// [`render_image`] with a state of the renderer's own, made by `state` once for each tile
/// and passed to every sample of the tile in order (a pixel's samples one after another,
/// sample 0 first): what a renderer keeps from one sample of a pixel to the next (the LoD's
/// shared walks, [`crate::runtime::TraceSettings::walks_per_pixel`]).
pub fn render_image_with<T>(
    camera: &Camera,
    spp: u32,
    seed: u64,
    stage: &str,
    progress: Progress,
    state: impl Fn() -> T + Sync,
    radiance: impl Fn(Sample, &mut T) -> Vec3 + Sync,
) -> (Image, ImageStats) {
    let start = Instant::now();
    let (w, h) = (camera.width, camera.height);
    let tiles_x = w.div_ceil(TILE);
    let tiles_y = h.div_ceil(TILE);
    let counter = StageCounter::new(progress, stage, (tiles_x * tiles_y) as u64);
    let rays = AtomicU64::new(0);
    let invalid = AtomicU64::new(0);
    let non_finite = AtomicU64::new(0);
    let spp = spp.max(1);
    let aperture = camera.pixel_angle();
    let tiles: Vec<(u32, Vec<Vec3>)> = (0..tiles_x * tiles_y)
        .into_par_iter()
        .map(|tile| {
            let nf0 = non_finite_count();
            let (tx, ty) = (tile % tiles_x, tile / tiles_x);
            let mut out = Vec::with_capacity((TILE * TILE) as usize);
            let mut local_rays = 0u64;
            let mut local_invalid = 0u64;
            let mut st = state();
            for y in ty * TILE..((ty + 1) * TILE).min(h) {
                for x in tx * TILE..((tx + 1) * TILE).min(w) {
                    let pixel = (y as u64) * w as u64 + x as u64;
                    let mut rng = Pcg32::new(seed, pixel);
                    let pixel_seed = pixel_seed(seed, pixel);
                    let mut sum = Vec3::ZERO;
                    for s in 0..spp {
                        let film = Vec2::new(x as f32, y as f32) + jitter(s, spp, &mut rng);
                        let l = radiance(
                            Sample {
                                film,
                                camera,
                                aperture,
                                rng: &mut rng,
                                rays: &mut local_rays,
                                index: s,
                                pixel_seed,
                                pixel: glam::UVec2::new(x, y),
                            },
                            &mut st,
                        );
                        if l.is_finite() {
                            sum += l;
                        } else {
                            local_invalid += 1;
                        }
                    }
                    out.push(sum / spp as f32);
                }
            }
            rays.fetch_add(local_rays, Ordering::Relaxed);
            invalid.fetch_add(local_invalid, Ordering::Relaxed);
            non_finite.fetch_add(non_finite_count() - nf0, Ordering::Relaxed);
            counter.add(1);
            (tile, out)
        })
        .collect();
    let mut img = Image::new(w, h);
    for (tile, px) in tiles {
        let (tx, ty) = (tile % tiles_x, tile / tiles_x);
        let mut k = 0;
        for y in ty * TILE..((ty + 1) * TILE).min(h) {
            for x in tx * TILE..((tx + 1) * TILE).min(w) {
                img.pixels[(y * w + x) as usize] = px[k];
                k += 1;
            }
        }
    }
    let stats = ImageStats {
        seconds: start.elapsed().as_secs_f64(),
        samples: w as u64 * h as u64 * spp as u64,
        rays: rays.into_inner(),
        invalid_samples: invalid.into_inner(),
        non_finite: non_finite.into_inner(),
    };
    (img, stats)
}
