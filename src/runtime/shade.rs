//! The shading layer: Algorithm 1 on top of the traversal (lines 13–19, 24–25).

use glam::Vec3;

use super::hits::{Hit, Weights};
use super::{
    Cone, ConeResult, LodScene, PrimitiveKind, Sampler, Shading, TraceSettings, VoxelHandle,
};
use crate::bsdf::Bsdf;
use crate::lights::Lights;
use crate::math::sampling::power_heuristic;

/// Reflected radiance of a voxel towards `wo` (Algorithm 1, lines 13–17): the sun, then `nee`
/// environment samples and `nee` ABSDF samples combined by MIS (power heuristic), the voxel's
/// incident AIV standing in for shadow rays.
pub fn shade<S: Sampler + ?Sized>(
    voxel: &VoxelHandle,
    wo: Vec3,
    lights: &Lights,
    nee: u32,
    sampler: &mut S,
) -> Vec3 {
    shade_with(voxel, wo, lights, nee, sampler, |w| {
        voxel.incident_visibility(w)
    })
}

/// [`shade`] with `visibility(ω_i)` for the light (the volume baseline passes its own).
pub(crate) fn shade_with<S: Sampler + ?Sized>(
    bsdf: &impl Bsdf,
    wo: Vec3,
    lights: &Lights,
    nee: u32,
    sampler: &mut S,
    mut visibility: impl FnMut(Vec3) -> f32,
) -> Vec3 {
    let mut l = Vec3::ZERO;
    if let Some(sun) = &lights.sun {
        let f = bsdf.eval(sun.direction, wo);
        if f.max_element() > 0.0 {
            l += f * sun.irradiance * visibility(sun.direction);
        }
    }
    let env = &lights.environment;
    let m = nee.max(1);
    let mut acc = Vec3::ZERO;
    for _ in 0..m {
        if let Some(ls) = env.sample(sampler.next_2d()) {
            if ls.pdf > 0.0 && ls.radiance.max_element() > 0.0 {
                let (f, pdf_b) = bsdf.eval_pdf(ls.wi, wo);
                if f.max_element() > 0.0 {
                    acc += f
                        * ls.radiance
                        * (visibility(ls.wi) * power_heuristic(ls.pdf, pdf_b) / ls.pdf);
                }
            }
        }
        let u_lobe = sampler.next_1d();
        if let Some(bs) = bsdf.sample(wo, u_lobe, sampler.next_2d()) {
            let le = env.eval(bs.wi);
            if le.max_element() > 0.0 {
                let pdf_l = env.pdf(bs.wi);
                acc +=
                    bs.value * le * (visibility(bs.wi) * power_heuristic(bs.pdf, pdf_l) / bs.pdf);
            }
        }
    }
    l + acc / m as f32
}

/// Most reservoirs one cone keeps (picks beyond are folded into this many).
const MAX_PICKS: usize = 8;

/// Where a cone is traced from when the scene sits inside a larger one (an instance of an
/// assembly, [`crate::assembly`]): the hook of [`LodScene::trace_placed`]. The cone and the
/// hits are in the scene's own space; the lights, and the directions the ABSDF is evaluated
/// and sampled in, are the world's; and light reaching a voxel is attenuated by whatever the
/// rest of the world puts in its way ([`Placement::occlusion`]), on top of the voxel's own
/// interior visibility (the AIV holds only the scene's own occlusion).
pub trait Placement {
    /// The world direction of a unit direction of the scene's own space (unit).
    fn to_world(&self, local: Vec3) -> Vec3;
    /// The scene's own direction of a unit world direction (unit).
    fn to_local(&self, world: Vec3) -> Vec3;
    /// What the rest of the world lets through, in [0, 1], of light arriving from world
    /// direction `wi` at the point `p` of the scene's own space.
    fn occlusion(&self, p: Vec3, wi: Vec3) -> f32;
}

/// The scene on its own: the world is its space and nothing else is in it ([`LodScene::trace`];
/// everything it does compiles away).
pub(crate) struct Alone;

impl Placement for Alone {
    #[inline(always)]
    fn to_world(&self, local: Vec3) -> Vec3 {
        local
    }
    #[inline(always)]
    fn to_local(&self, world: Vec3) -> Vec3 {
        world
    }
    #[inline(always)]
    fn occlusion(&self, _p: Vec3, _wi: Vec3) -> f32 {
        1.0
    }
}

/// A voxel's ABSDF seen through a placement: world directions in and out.
struct Placed<'a, 'v, P: Placement + ?Sized> {
    voxel: &'a VoxelHandle<'v>,
    place: &'a P,
}

impl<P: Placement + ?Sized> Bsdf for Placed<'_, '_, P> {
    #[inline]
    fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        self.voxel
            .eval(self.place.to_local(wi), self.place.to_local(wo))
    }
    #[inline]
    fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        self.voxel
            .pdf(self.place.to_local(wi), self.place.to_local(wo))
    }
    #[inline]
    fn eval_pdf(&self, wi: Vec3, wo: Vec3) -> (Vec3, f32) {
        self.voxel
            .eval_pdf(self.place.to_local(wi), self.place.to_local(wo))
    }
    #[inline]
    fn sample(&self, wo: Vec3, u_lobe: f32, u: glam::Vec2) -> Option<crate::bsdf::BsdfSample> {
        let mut s = self.voxel.sample(self.place.to_local(wo), u_lobe, u)?;
        s.wi = self.place.to_world(s.wi);
        Some(s)
    }
}

/// [`shade`] of hit `h` of `cone` through a placement: `wo` is the world direction.
#[inline]
fn shade_placed<S: Sampler + ?Sized, P: Placement + ?Sized>(
    h: &Hit,
    cone: &Cone,
    wo: Vec3,
    lights: &Lights,
    nee: u32,
    sampler: &mut S,
    place: &P,
) -> Vec3 {
    let voxel = &h.voxel;
    let p = cone.origin + cone.dir * h.t;
    shade_with(&Placed { voxel, place }, wo, lights, nee, sampler, |w| {
        voxel.incident_visibility(place.to_local(w)) * place.occlusion(p, w)
    })
}

/// [`LodScene::trace`].
pub(crate) fn trace<S: Sampler + ?Sized>(
    scene: &LodScene,
    cone: &Cone,
    lights: &Lights,
    settings: &TraceSettings,
    sampler: &mut S,
) -> ConeResult {
    let background = lights.environment.eval(cone.dir);
    if settings.primitive == PrimitiveKind::Volume {
        return scene.trace_volume(cone, lights, settings, sampler);
    }
    let (surfaces, transmittance, primitives, coverage, _) =
        trace_surfaces(scene, cone, lights, settings, sampler, &Alone);
    ConeResult::compose(surfaces, background, transmittance, primitives, coverage)
}

/// [`LodScene::trace_placed`]: the surfaces' radiance (no background), the background's
/// weight, the primitives met, the coverage, and the ray parameter of the first primitive met
/// (infinite when none).
pub(crate) fn trace_surfaces<S: Sampler + ?Sized, P: Placement + ?Sized>(
    scene: &LodScene,
    cone: &Cone,
    lights: &Lights,
    settings: &TraceSettings,
    sampler: &mut S,
    place: &P,
) -> (Vec3, f32, u32, f32, f32) {
    let wo = place.to_world(-cone.dir);
    let mut hits = scene.hits(cone, settings);
    let mut first = f32::INFINITY;
    // The sum of the hits' weights (for `settings.normalize`): exact when every hit is
    // shaded; under reservoir shading the deterministic sum of bound weights times the mean
    // exact/bound factor of the hits shaded, so that a cone whose shading roulette drew nothing
    // is still normalised by its weights, not by zero.
    let (surfaces, coverage, weight_sum) = match settings.shading {
        Shading::Every => {
            let (mut sum, mut cov) = (Vec3::ZERO, 0.0f32);
            for h in &mut hits {
                first = first.min(h.t);
                sum += shade_placed(&h, cone, wo, lights, settings.nee, sampler, place) * h.weight;
                cov += h.weight;
            }
            (sum, cov, cov)
        }
        Shading::Reservoir { picks, roulette } => {
            // Weighted reservoir sampling (one reservoir per pick) over bound weights ŵ_k
            // (|B|_ω replaced by a cheap upper bound): each reservoir keeps hit k with
            // probability ŵ_k / Σŵ; shading the kept one and scaling by Σŵ · w_k/ŵ_k is an
            // unbiased estimate of Σ w_k L_o^k, with the exact |B|_ω computed once per pick.
            hits = hits.with_weights(Weights::Bound);
            let n = (picks.max(1) as usize).min(MAX_PICKS);
            let mut kept: [Option<Hit>; MAX_PICKS] = [None; MAX_PICKS];
            let mut wsum = 0.0f32;
            for h in &mut hits {
                first = first.min(h.t);
                wsum += h.weight;
                let p = h.weight / wsum;
                for slot in kept.iter_mut().take(n) {
                    if sampler.next_1d() < p {
                        *slot = Some(h);
                    }
                }
            }
            // Coverage roulette: shade with probability min(1, Σŵ).
            let p = if roulette { wsum.min(1.0) } else { 1.0 };
            if !(p > 0.0) || (p < 1.0 && sampler.next_1d() >= p) {
                (Vec3::ZERO, 0.0, wsum)
            } else {
                let (mut sum, mut cov, mut factors, mut picked) =
                    (Vec3::ZERO, 0.0f32, 0.0f32, 0u32);
                for h in kept.iter().take(n).flatten() {
                    let k = hits.exact_factor(h);
                    factors += k;
                    picked += 1;
                    if k > 0.0 {
                        sum += shade_placed(h, cone, wo, lights, settings.nee, sampler, place) * k;
                        cov += k;
                    }
                }
                let scale = wsum / (n as f32 * p);
                let mean_factor = if picked > 0 {
                    factors / picked as f32
                } else {
                    1.0
                };
                (sum * scale, cov * scale, wsum * mean_factor)
            }
        }
    };
    let mut transmittance = hits.transmittance();
    let (mut surfaces, mut coverage) = (surfaces, coverage);
    if settings.normalize {
        let total = weight_sum + transmittance;
        if total > 0.0 && total.is_finite() {
            surfaces /= total;
            coverage /= total;
            transmittance /= total;
        }
    }
    (surfaces, transmittance, hits.primitives(), coverage, first)
}
