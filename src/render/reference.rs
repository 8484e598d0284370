//! The reference renderer: direct illumination on the original mesh, as the paper's
//! references. Pinhole camera, box pixel filter with jittered samples; at the first hit,
//! next-event estimation from the sun and from the importance-sampled environment, combined
//! with BSDF sampling by multiple importance sampling (power heuristic); shadow rays through
//! the BVH, honouring cut-outs. The image loop is the one the LoD runtime uses
//! ([`crate::film::render_image`]): same pixel sampling, seeds and statistics.

use glam::Vec3;

use crate::bsdf::{BaseBsdf, Bsdf};
use crate::film::{Camera, Image, ImageStats};
use crate::lights::Lights;
use crate::math::frame::Frame;
use crate::math::rng::Pcg32;
use crate::math::sampling::power_heuristic;
use crate::math::sampling::Sampler;
use crate::scene::Scene;
use crate::trace::{offset_origin, Accel, Ray, SurfacePoint};
use crate::util::Progress;

/// Settings of a reference render.
#[derive(Clone, Copy, Debug)]
pub struct ReferenceSettings {
    /// Samples per pixel.
    pub spp: u32,
    /// Seed of the pixels' random streams.
    pub seed: u64,
}

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
    let sp = accel.surface(ray, &hit);
    shade(accel.scene(), &sp, -ray.dir, lights, rng, |wi| {
        *rays += 1;
        let r = Ray::new(offset_origin(sp.p, sp.ng, wi), wi);
        if accel.occluded(&r) {
            0.0
        } else {
            1.0
        }
    })
}

/// Direct illumination reflected towards `wo` at the surface point `sp` of `scene` (its
/// material and textures): the sun, then one environment sample by light sampling and one by
/// BSDF sampling, combined by MIS (power heuristic). `visibility(wi)` says what reaches `sp`
/// from unit direction `wi`, in [0, 1]: the reference's shadow ray (0 or 1), or, in an
/// assembly's hybrid render ([`crate::assembly`]), a shadow ray through the instance's own
/// triangles times what the other instances let through. All in one space (the world's).
pub fn shade<S: Sampler + ?Sized>(
    scene: &Scene,
    sp: &SurfacePoint,
    wo: Vec3,
    lights: &Lights,
    rng: &mut S,
    mut visibility: impl FnMut(Vec3) -> f32,
) -> Vec3 {
    // Double-sided: face the shading normal towards the viewer (as Mitsuba's `twosided`).
    let ns = if sp.ns.dot(wo) < 0.0 { -sp.ns } else { sp.ns };
    let frame = Frame::from_z(ns);
    let wo_l = frame.to_local(wo);
    let Some(material) = scene.materials.get(sp.material as usize) else {
        return Vec3::ZERO;
    };
    let bsdf = BaseBsdf::new(material.eval(&scene.textures, sp.uv));
    let mut l = Vec3::ZERO;

    // Sun (a delta light: no MIS).
    if let Some(sun) = &lights.sun {
        let wi_l = frame.to_local(sun.direction);
        if wi_l.z > 0.0 {
            let f = bsdf.eval(wi_l, wo_l);
            if f.max_element() > 0.0 {
                let v = visibility(sun.direction);
                if v > 0.0 {
                    l += f * sun.irradiance * (wi_l.z * v);
                }
            }
        }
    }
    // Environment: light sampling.
    let u_light = rng.next_2d();
    if let Some(ls) = lights.environment.sample(u_light) {
        let wi_l = frame.to_local(ls.wi);
        if wi_l.z > 0.0 && ls.pdf > 0.0 && ls.radiance.max_element() > 0.0 {
            let (f, pdf_b) = bsdf.eval_pdf(wi_l, wo_l);
            if f.max_element() > 0.0 {
                let v = visibility(ls.wi);
                if v > 0.0 {
                    l += f * ls.radiance * (wi_l.z * power_heuristic(ls.pdf, pdf_b) * v / ls.pdf);
                }
            }
        }
    }
    // Environment: BSDF sampling.
    let u_lobe = rng.next_1d();
    let u_bsdf = rng.next_2d();
    if let Some(bs) = bsdf.sample(wo_l, u_lobe, u_bsdf) {
        let wi = frame.to_world(bs.wi);
        let le = lights.environment.eval(wi);
        if le.max_element() > 0.0 {
            let v = visibility(wi);
            if v > 0.0 {
                let pdf_l = lights.environment.pdf(wi);
                l += bs.value * le * (bs.wi.z * power_heuristic(bs.pdf, pdf_l) * v / bs.pdf);
            }
        }
    }
    l
}

/// Renders the image through the shared image loop ([`crate::film::render_image`]).
pub fn render(
    accel: &Accel,
    camera: &Camera,
    lights: &Lights,
    settings: ReferenceSettings,
    progress: Progress,
) -> (Image, ImageStats) {
    crate::film::render_image(
        camera,
        settings.spp,
        settings.seed,
        "reference",
        progress,
        |s| {
            let (origin, dir) = s.ray();
            radiance(accel, lights, &Ray::new(origin, dir), s.rng, s.rays)
        },
    )
}

/// The fraction of each pixel the scene's surfaces cover, row by row: `n` × `n` stratified
/// primary rays a pixel, each hitting or not (the object mask of
/// [`crate::render::compare::compare_on_object`]).
pub fn coverage(accel: &Accel, camera: &Camera, n: u32) -> Vec<f32> {
    use rayon::prelude::*;
    let n = n.max(1);
    let (w, h) = (camera.width, camera.height);
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            let mut hits = 0u32;
            for j in 0..n * n {
                let u = ((j % n) as f32 + 0.5) / n as f32;
                let v = ((j / n) as f32 + 0.5) / n as f32;
                let (o, d) = camera.ray(glam::Vec2::new(x + u, y + v));
                hits += accel.intersect(&Ray::new(o, d)).is_some() as u32;
            }
            hits as f32 / (n * n) as f32
        })
        .collect()
}

/// What `aggtool reference` reports.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ReferenceReport {
    /// What was rendered and what it imported as.
    pub input: String,
    /// Import warnings.
    pub warnings: Vec<String>,
    /// Seconds to build the BVH.
    pub bvh_seconds: f64,
    /// Bottom-level BVHs (one per mesh).
    pub blas: usize,
    /// Top-level entries (instances).
    pub tlas_entries: usize,
    /// The render's figures.
    pub stats: ImageStats,
    /// Peak resident memory, as a line, where the platform tells it.
    pub peak_memory: Option<String>,
    /// The files written.
    pub output: crate::render::ImageFiles,
}

/// Renders `scene` as `view` says and writes `files` (the PNG at `exposure` stops); `input`
/// names what was rendered in the report.
pub fn render_to_files(
    scene: &Scene,
    input: String,
    view: &crate::render::View,
    files: &crate::render::ImageFiles,
    exposure: f32,
    progress: Progress,
) -> anyhow::Result<ReferenceReport> {
    let lights = view.lights()?;
    let t0 = std::time::Instant::now();
    let accel = Accel::build(scene);
    let bvh_seconds = t0.elapsed().as_secs_f64();
    let settings = ReferenceSettings {
        spp: view.spp,
        seed: view.seed,
    };
    let (img, stats) = render(&accel, &view.camera(), &lights, settings, progress);
    files.write(&img, exposure)?;
    Ok(ReferenceReport {
        input,
        warnings: scene.warnings.clone(),
        bvh_seconds,
        blas: accel.stats.blas_count,
        tlas_entries: accel.stats.tlas_entries,
        stats,
        peak_memory: crate::util::process::peak_rss_line(),
        output: files.clone(),
    })
}

impl std::fmt::Display for ReferenceReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for w in &self.warnings {
            writeln!(f, "warning: {w}")?;
        }
        writeln!(f, "input: {}", self.input)?;
        writeln!(
            f,
            "stats: bvh {:.2} s ({} BLAS, {} TLAS entries)",
            self.bvh_seconds, self.blas, self.tlas_entries
        )?;
        writeln!(f, "{}", self.stats.line("reference"))?;
        if let Some(l) = &self.peak_memory {
            writeln!(f, "{l}")?;
        }
        write!(f, "{}", self.output)
    }
}
