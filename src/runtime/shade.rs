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
    let wo = -cone.dir;
    let mut hits = scene.hits(cone, settings);
    let (surfaces, coverage) = match settings.shading {
        Shading::Every => {
            let (mut sum, mut cov) = (Vec3::ZERO, 0.0f32);
            for h in &mut hits {
                sum += shade(&h.voxel, wo, lights, settings.nee, sampler) * h.weight;
                cov += h.weight;
            }
            (sum, cov)
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
                (Vec3::ZERO, 0.0)
            } else {
                let (mut sum, mut cov) = (Vec3::ZERO, 0.0f32);
                for h in kept.iter().take(n).flatten() {
                    let k = hits.exact_factor(h);
                    if k > 0.0 {
                        sum += shade(&h.voxel, wo, lights, settings.nee, sampler) * k;
                        cov += k;
                    }
                }
                let scale = wsum / (n as f32 * p);
                (sum * scale, cov * scale)
            }
        }
    };
    ConeResult::compose(
        surfaces,
        background,
        hits.transmittance(),
        hits.primitives(),
        coverage,
    )
}
