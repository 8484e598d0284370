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
use crate::trace::{offset_origin, Accel, Ray};
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
            let f = bsdf.eval(wi_l, wo_l);
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
            let (f, pdf_b) = bsdf.eval_pdf(wi_l, wo_l);
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
            l += bs.value * le * (bs.wi.z * power_heuristic(bs.pdf, pdf_l) / bs.pdf);
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
        |s| radiance(accel, lights, &Ray::new(s.origin, s.dir), s.rng, s.rays),
    )
}
