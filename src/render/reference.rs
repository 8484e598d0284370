//! The reference renderer: direct illumination on the original mesh, as the paper's
//! references. Pinhole camera, box pixel filter with jittered samples; at the first hit,
//! next-event estimation from the sun and from the importance-sampled environment, combined
//! with BSDF sampling by multiple importance sampling (power heuristic); shadow rays through
//! the BVH, honouring cut-outs. Parallel over 16×16 tiles with rayon; every pixel has its own
//! random stream derived from the seed, so the image is identical whatever the thread count.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use super::camera::Camera;
use super::image::Image;
use super::lights::Lights;
use crate::bsdf::BaseBsdf;
use crate::math::frame::Frame;
use crate::math::rng::Pcg32;
use crate::math::sampling::power_heuristic;
use crate::trace::{offset_origin, Accel, Ray};

/// Settings of a reference render.
#[derive(Clone, Copy, Debug)]
pub struct ReferenceSettings {
    pub spp: u32,
    pub seed: u64,
    /// Draw a progress bar on stderr (only when it is a terminal).
    pub progress: bool,
}

/// Figures of a finished render.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct RenderStats {
    pub seconds: f64,
    /// Camera, shadow and BSDF-sampled rays.
    pub rays: u64,
    pub rays_per_second: f64,
    /// Samples that produced NaN or infinity and were replaced by zero.
    pub invalid_samples: u64,
}

const TILE: u32 = 16;

/// Radiance along a camera ray: direct illumination at the first hit, or the environment.
pub fn radiance(
    accel: &Accel,
    lights: &Lights,
    ray: &Ray,
    rng: &mut Pcg32,
    rays: &mut u64,
) -> Vec3 {
    *rays += 1;
    let Some(hit) = accel.intersect(ray) else {
        return lights.environment.eval(ray.dir);
    };
    let scene = accel.scene();
    let sp = accel.surface(ray, &hit);
    let wo = -ray.dir;
    // Double-sided: face the shading normal towards the viewer (as Mitsuba's `twosided`).
    let ns = if sp.ns.dot(wo) < 0.0 { -sp.ns } else { sp.ns };
    let frame = Frame::from_z(ns);
    let wo_l = frame.to_local(wo);
    let Some(material) = scene.materials.get(sp.material as usize) else {
        return Vec3::ZERO;
    };
    let bsdf = BaseBsdf::new(material.eval(&scene.textures, sp.uv));
    let mut l = Vec3::ZERO;
    let shadow = |wi: Vec3, rays: &mut u64| {
        *rays += 1;
        let r = Ray::new(offset_origin(sp.p, sp.ng, wi), wi);
        accel.occluded(&r)
    };

    // Sun (a delta light: no MIS).
    if let Some(sun) = &lights.sun {
        let wi_l = frame.to_local(sun.direction);
        if wi_l.z > 0.0 {
            let f = bsdf.eval(wo_l, wi_l);
            if f.max_element() > 0.0 && !shadow(sun.direction, rays) {
                l += f * sun.irradiance * wi_l.z;
            }
        }
    }
    // Environment: light sampling.
    let u_light = rng.next_2d();
    if let Some(ls) = lights.environment.sample(u_light) {
        let wi_l = frame.to_local(ls.wi);
        if wi_l.z > 0.0 && ls.pdf > 0.0 && ls.radiance.max_element() > 0.0 {
            let (f, pdf_b) = bsdf.eval_pdf(wo_l, wi_l);
            if f.max_element() > 0.0 && !shadow(ls.wi, rays) {
                l += f * ls.radiance * (wi_l.z * power_heuristic(ls.pdf, pdf_b) / ls.pdf);
            }
        }
    }
    // Environment: BSDF sampling.
    let u_lobe = rng.next_f32();
    let u_bsdf = rng.next_2d();
    if let Some(bs) = bsdf.sample(wo_l, u_lobe, u_bsdf) {
        let wi = frame.to_world(bs.wi);
        let le = lights.environment.eval(wi);
        if le.max_element() > 0.0 && !shadow(wi, rays) {
            let pdf_l = lights.environment.pdf(wi);
            l += bs.f * le * (bs.wi.z * power_heuristic(bs.pdf, pdf_l) / bs.pdf);
        }
    }
    l
}

/// Jittered position of sample `s` of `spp` inside a pixel: stratified on a √spp grid when spp
/// is a perfect square, uniform otherwise.
#[inline]
fn jitter(s: u32, spp: u32, rng: &mut Pcg32) -> Vec2 {
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

/// Renders the image.
pub fn render(
    accel: &Accel,
    camera: &Camera,
    lights: &Lights,
    settings: ReferenceSettings,
) -> (Image, RenderStats) {
    let start = Instant::now();
    let (w, h) = (camera.width, camera.height);
    let tiles_x = w.div_ceil(TILE);
    let tiles_y = h.div_ceil(TILE);
    let ntiles = (tiles_x * tiles_y) as u64;
    let bar = progress_bar(settings.progress, ntiles, "reference");
    let rays = AtomicU64::new(0);
    let invalid = AtomicU64::new(0);
    let spp = settings.spp.max(1);
    let tiles: Vec<(u32, Vec<Vec3>)> = (0..tiles_x * tiles_y)
        .into_par_iter()
        .map(|tile| {
            let (tx, ty) = (tile % tiles_x, tile / tiles_x);
            let mut out = Vec::with_capacity((TILE * TILE) as usize);
            let mut local_rays = 0u64;
            let mut local_invalid = 0u64;
            for y in ty * TILE..((ty + 1) * TILE).min(h) {
                for x in tx * TILE..((tx + 1) * TILE).min(w) {
                    let mut rng = Pcg32::new(settings.seed, (y as u64) * w as u64 + x as u64);
                    let mut sum = Vec3::ZERO;
                    for s in 0..spp {
                        let p = Vec2::new(x as f32, y as f32) + jitter(s, spp, &mut rng);
                        let ray = camera.ray(p);
                        let l = radiance(accel, lights, &ray, &mut rng, &mut local_rays);
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
            bar.inc(1);
            (tile, out)
        })
        .collect();
    bar.finish_and_clear();
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
    let seconds = start.elapsed().as_secs_f64();
    let rays = rays.into_inner();
    (
        img,
        RenderStats {
            seconds,
            rays,
            rays_per_second: rays as f64 / seconds.max(1e-9),
            invalid_samples: invalid.into_inner(),
        },
    )
}

/// A progress bar on stderr, hidden when disabled or when stderr is not a terminal.
pub fn progress_bar(enabled: bool, len: u64, what: &str) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    if !enabled || !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix:>10} [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar.set_prefix(what.to_string());
    bar
}
