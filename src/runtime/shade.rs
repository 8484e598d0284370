//! The shading layer: Algorithm 1 on top of the traversal (lines 13–19, 24–25).

use glam::Vec3;

use super::hits::{AreaCache, Hit, Hits, Weights};
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

/// Candidates of positive weight [`Picks`] holds to pick by cumulative weight; past them it
/// keeps by [`reservoir_step`].
const HELD_HITS: usize = 16;

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
    // The level's dither (continuous LoD), drawn first: a pixel's samples stratify it.
    // Not drawn where it would not be read (a forced level), which keeps those renders' bits.
    let dither = draws_dither(settings).then(|| sampler.next_1d());
    let mut hits = scene.hits_weighted(cone, settings, walk_weights(settings), dither);
    estimate(&mut hits, cone, lights, settings, sampler, place)
}

/// Whether a cone's walk reads a dither (continuous LoD and no forced level).
#[inline]
pub(crate) fn draws_dither(settings: &TraceSettings) -> bool {
    settings.continuous_lod && settings.level.is_none()
}

/// The weights the walk yields for `settings`' shading: reservoir shading weighs hits by a
/// bound of |B|_ω (see [`estimate`]).
#[inline]
fn walk_weights(settings: &TraceSettings) -> Weights {
    match settings.shading {
        Shading::Every => Weights::Exact,
        Shading::Reservoir { .. } => Weights::Bound,
    }
}

/// Where the hits of a cone's estimate come from: its own walk ([`Hits`]), or a walk a
/// pixel's samples share ([`Walk`]). The estimate holds its candidates as `Item`s: the hits
/// themselves, or (read again from a kept walk) their indices, which cost nothing to move.
pub(crate) trait HitSource<'s> {
    /// A candidate as the reservoir holds it.
    type Item: Clone;
    /// The next hit, in order: the candidate, its weight and its ray parameter.
    fn next_hit(&mut self) -> Option<(Self::Item, f32, f32)>;
    /// The hit a candidate stands for.
    fn get<'a>(&'a self, item: &'a Self::Item) -> &'a Hit<'s>;
    /// The walk the hits came from (its cone and settings; its transmittance once exhausted).
    fn walk(&self) -> &Hits<'s>;
    /// `n` picks among the rest of the hits, each hit k with probability w_k / Σw and an
    /// increasing function of `u` ([`Picks`]); with Σw and the ray parameter of the first hit
    /// (infinite when none).
    fn picks(&mut self, n: usize, u: f32) -> ([Option<Self::Item>; MAX_PICKS], f32, f32) {
        let mut reservoir = Picks::new(n, u);
        let mut first = f32::INFINITY;
        while let Some((item, w, t)) = self.next_hit() {
            first = first.min(t);
            reservoir.push(item, w);
        }
        let (kept, wsum) = reservoir.finish();
        (kept, wsum, first)
    }
}

impl<'s> HitSource<'s> for Hits<'s> {
    type Item = Hit<'s>;
    #[inline]
    fn next_hit(&mut self) -> Option<(Hit<'s>, f32, f32)> {
        let h = self.next()?;
        let (w, t) = (h.weight, h.t);
        Some((h, w, t))
    }
    #[inline]
    fn get<'a>(&'a self, item: &'a Hit<'s>) -> &'a Hit<'s> {
        item
    }
    #[inline]
    fn walk(&self) -> &Hits<'s> {
        self
    }
}

/// One cone's walk kept whole, for the samples of a pixel to shade from in turn (the image
/// loop's walk reuse, [`TraceSettings::walks_per_pixel`]). Its buffers are kept between
/// pixels: refilling allocates nothing once they have grown.
#[derive(Default)]
pub(crate) struct Walk<'s> {
    hits: Option<Hits<'s>>,
    list: Vec<Hit<'s>>,
    /// The hits' cumulative weights, for the picks to search.
    cumulative: Vec<f64>,
    /// Σw as [`Picks`] sums it.
    sum: f32,
    first: f32,
    background: Vec3,
}

impl<'s> Walk<'s> {
    /// Walks `cone` (with the level's dither `dither`), one of the shared walks of a pixel
    /// whose centre ray is `pixel_dir`, and keeps its hits. The walk takes the |B|_ω of the
    /// primitives that cross their voxels along `pixel_dir`, each computed once for all the
    /// pixel's walks ([`AreaCache`]).
    pub(crate) fn fill(
        &mut self,
        scene: &'s LodScene,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        dither: f32,
        pixel_dir: Vec3,
    ) {
        self.list.clear();
        let dither = draws_dither(settings).then_some(dither);
        // Restarted in place (moving a new walk's state, a few hundred bytes, into the slot
        // was 2% of a render in `memmove`).
        let hits = match &mut self.hits {
            Some(h) => {
                scene.restart_hits(h, cone, settings, walk_weights(settings), dither);
                h
            }
            None => self.hits.insert(scene.hits_weighted(
                cone,
                settings,
                walk_weights(settings),
                dither,
            )),
        };
        hits.areas
            .get_or_insert_with(|| std::cell::RefCell::new(AreaCache::new()))
            .borrow_mut()
            .aim(scene as *const LodScene as usize, pixel_dir);
        self.list.extend(&mut *hits);
        self.cumulative.clear();
        let (mut c, mut sum, mut first) = (0.0f64, 0.0f32, f32::INFINITY);
        for h in &self.list {
            // The walk yields only positive weights.
            c += h.weight as f64;
            sum += h.weight;
            first = first.min(h.t);
            self.cumulative.push(c);
        }
        (self.sum, self.first) = (sum, first);
        self.background = lights.environment.eval(cone.dir);
    }

    /// One sample's estimate from the kept hits ([`LodScene::trace`]'s result for the walk's
    /// cone, drawing the shading's numbers from `sampler`).
    pub(crate) fn estimate<S: Sampler + ?Sized>(
        &self,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
    ) -> ConeResult {
        let (surfaces, transmittance, primitives, coverage, _) =
            self.estimate_placed(lights, settings, sampler, &Alone);
        ConeResult::compose(
            surfaces,
            self.background,
            transmittance,
            primitives,
            coverage,
        )
    }

    /// [`Walk::estimate`] through a placement, as [`trace_surfaces`] gives it: the surfaces'
    /// radiance (no background), the background's weight, the primitives met, the coverage,
    /// and the ray parameter of the first primitive met (infinite when none).
    pub(crate) fn estimate_placed<S: Sampler + ?Sized, P: Placement + ?Sized>(
        &self,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
        place: &P,
    ) -> (Vec3, f32, u32, f32, f32) {
        let Some(hits) = &self.hits else {
            return (Vec3::ZERO, 1.0, 0, 0.0, f32::INFINITY);
        };
        let cone = hits.cone();
        let mut replay = Replay {
            walk: self,
            next: 0,
        };
        estimate(&mut replay, &cone, lights, settings, sampler, place)
    }
}

/// A [`Walk`]'s hits, read again.
struct Replay<'w, 's> {
    walk: &'w Walk<'s>,
    next: usize,
}

impl<'s> HitSource<'s> for Replay<'_, 's> {
    type Item = u32;
    #[inline]
    fn next_hit(&mut self) -> Option<(u32, f32, f32)> {
        let h = self.walk.list.get(self.next)?;
        self.next += 1;
        Some(((self.next - 1) as u32, h.weight, h.t))
    }
    #[inline]
    fn get<'a>(&'a self, item: &'a u32) -> &'a Hit<'s> {
        &self.walk.list[*item as usize]
    }
    #[inline]
    fn walk(&self) -> &Hits<'s> {
        self.walk.hits.as_ref().expect("a filled walk")
    }
    /// [`Picks`]' choice over the kept cumulative weights, by binary search: the same
    /// probabilities, and increasing in `u`, for a sample's cost independent of the hits.
    fn picks(&mut self, n: usize, u: f32) -> ([Option<u32>; MAX_PICKS], f32, f32) {
        let w = self.walk;
        self.next = w.list.len();
        (pick_cumulative(&w.cumulative, n, u), w.sum, w.first)
    }
}

/// `n` picks (1 to [`MAX_PICKS`]) among candidates of cumulative weights `cumulative`
/// (increasing, positive weights), driven by `u` as [`Picks`] is: pick j is the candidate
/// whose share of the total holds (u + j/n mod 1)·Σw. `None` where there is no candidate.
fn pick_cumulative(cumulative: &[f64], n: usize, u: f32) -> [Option<u32>; MAX_PICKS] {
    let mut kept = [None; MAX_PICKS];
    if let Some(&total) = cumulative.last() {
        let n = n.clamp(1, MAX_PICKS);
        let u0 = if (0.0..1.0).contains(&u) {
            u as f64
        } else {
            0.0
        };
        for (j, slot) in kept.iter_mut().enumerate().take(n) {
            let target = (u0 + j as f64 / n as f64).fract() * total;
            let i = cumulative.partition_point(|&c| c <= target);
            *slot = Some(i.min(cumulative.len() - 1) as u32);
        }
    }
    kept
}

/// Eq. 30's estimate over a cone's hits: every hit shaded, or the reservoir's picks; the
/// surfaces' radiance (no background), the background's weight, the primitives met, the
/// coverage, and the ray parameter of the first primitive met (infinite when none).
fn estimate<'s, H: HitSource<'s>, S: Sampler + ?Sized, P: Placement + ?Sized>(
    hits: &mut H,
    cone: &Cone,
    lights: &Lights,
    settings: &TraceSettings,
    sampler: &mut S,
    place: &P,
) -> (Vec3, f32, u32, f32, f32) {
    let wo = place.to_world(-cone.dir);
    let mut first = f32::INFINITY;
    // The sum of the hits' weights (for `settings.normalize`): exact when every hit is
    // shaded; under reservoir shading the deterministic sum of bound weights times the mean
    // exact/bound factor of the hits shaded, so that a cone whose shading roulette drew nothing
    // is still normalised by its weights, not by zero.
    let (surfaces, coverage, weight_sum) = match settings.shading {
        Shading::Every => {
            let (mut sum, mut cov) = (Vec3::ZERO, 0.0f32);
            while let Some((item, w, t)) = hits.next_hit() {
                first = first.min(t);
                let h = hits.get(&item);
                sum += shade_placed(h, cone, wo, lights, settings.nee, sampler, place) * w;
                cov += w;
            }
            (sum, cov, cov)
        }
        Shading::Reservoir { picks, roulette } => {
            // Weighted reservoir sampling over bound weights ŵ_k (|B|_ω replaced by a cheap
            // upper bound): each pick keeps hit k with probability ŵ_k / Σŵ ([`Picks`], one
            // number a cone); shading the kept one and scaling by Σŵ · w_k/ŵ_k is an unbiased
            // estimate of Σ w_k L_o^k, with the exact |B|_ω computed once per pick.
            let n = (picks.max(1) as usize).min(MAX_PICKS);
            let (kept, wsum, first_hit) = hits.picks(n, sampler.next_1d());
            first = first_hit;
            // Coverage roulette: shade with probability min(1, Σŵ).
            let p = if roulette { wsum.min(1.0) } else { 1.0 };
            if !(p > 0.0) || (p < 1.0 && sampler.next_1d() >= p) {
                (Vec3::ZERO, 0.0, wsum)
            } else {
                let (mut sum, mut cov, mut factors, mut picked) =
                    (Vec3::ZERO, 0.0f32, 0.0f32, 0u32);
                for item in kept.iter().take(n).flatten() {
                    let h = hits.get(item);
                    let k = hits.walk().exact_factor(h);
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
    let walk = hits.walk();
    let mut transmittance = walk.transmittance();
    let (mut surfaces, mut coverage) = (surfaces, coverage);
    if settings.normalize {
        let total = weight_sum + transmittance;
        if total > 0.0 && total.is_finite() {
            surfaces /= total;
            coverage /= total;
            transmittance /= total;
        }
    }
    (surfaces, transmittance, walk.primitives(), coverage, first)
}

/// Weighted reservoir sampling of `n` picks from a stream of weighted candidates, driven by one
/// uniform number for all of them: pick j takes u_j = u + j/n (mod 1), and keeps the
/// candidate whose share of the cumulative weight holds u_j·Σw. The first [`HELD_HITS`]
/// candidates of positive weight are held for that; one beyond them is kept by
/// [`reservoir_step`], which leaves u_j uniform, and increasing in u where it keeps none. So
/// each pick is candidate k with probability w_k / Σw, as with a fresh number per candidate,
/// and is an increasing function of u: numbers stratified over a pixel's samples
/// ([`super::Stratified`]) make stratified picks, and the n picks of one cone are spread over
/// the candidates instead of drawn independently. Nothing is allocated.
pub(crate) struct Picks<T: Clone> {
    n: usize,
    u: [f64; MAX_PICKS],
    held: [Option<T>; HELD_HITS],
    cumulative: [f64; HELD_HITS],
    nheld: usize,
    held_sum: f64,
    kept: [Option<T>; MAX_PICKS],
    sum: f32,
}

impl<T: Clone> Picks<T> {
    /// `n` picks (1 to [`MAX_PICKS`]) driven by `u` in [0, 1) (anything else counts as 0).
    #[inline]
    pub(crate) fn new(n: usize, u: f32) -> Self {
        let n = n.clamp(1, MAX_PICKS);
        let u0 = if (0.0..1.0).contains(&u) {
            u as f64
        } else {
            0.0
        };
        let mut us = [0f64; MAX_PICKS];
        for (j, uj) in us.iter_mut().enumerate().take(n) {
            *uj = (u0 + j as f64 / n as f64).fract();
        }
        Picks {
            n,
            u: us,
            held: std::array::from_fn(|_| None),
            cumulative: [0.0; HELD_HITS],
            nheld: 0,
            held_sum: 0.0,
            kept: std::array::from_fn(|_| None),
            sum: 0.0,
        }
    }

    /// The next candidate; one of weight zero, negative or NaN is never kept.
    #[inline]
    pub(crate) fn push(&mut self, item: T, weight: f32) {
        if !(weight > 0.0) {
            return;
        }
        self.sum += weight;
        if self.nheld < HELD_HITS {
            self.held_sum += weight as f64;
            self.held[self.nheld] = Some(item);
            self.cumulative[self.nheld] = self.held_sum;
            self.nheld += 1;
        } else {
            let p = (weight / self.sum) as f64;
            for (slot, uj) in self.kept.iter_mut().zip(self.u.iter_mut()).take(self.n) {
                if reservoir_step(uj, p) {
                    *slot = Some(item.clone());
                }
            }
        }
    }

    /// The picks (the first `n` entries; `None` only when no candidate had a positive
    /// weight) and the sum of the candidates' weights.
    #[inline]
    pub(crate) fn finish(mut self) -> ([Option<T>; MAX_PICKS], f32) {
        if self.nheld > 0 {
            for (slot, uj) in self.kept.iter_mut().zip(self.u.iter()).take(self.n) {
                if slot.is_none() {
                    let target = *uj * self.held_sum;
                    let i = self.cumulative[..self.nheld].partition_point(|&c| c <= target);
                    *slot = self.held[i.min(self.nheld - 1)].clone();
                }
            }
        }
        (self.kept, self.sum)
    }
}

/// One step of a weighted reservoir driven by one uniform number `u` for the whole stream
/// instead of one per candidate: keep the candidate when u < p (its probability ŵ_k / Σŵ so
/// far), and rescale u to what is left of its interval, u/p or (u − p)/(1 − p), which is again
/// uniform given the outcome, so that the candidate kept is distributed exactly as with a
/// fresh number per step. Where no step keeps, the final u is an increasing function of the
/// first. A p that is not in (0, 1] keeps nothing and leaves u as it is; p ≥ 1 keeps.
#[inline]
pub(crate) fn reservoir_step(u: &mut f64, p: f64) -> bool {
    /// The largest f64 below one: u stays in [0, 1) whatever the rounding.
    const BELOW_ONE: f64 = 1.0 - f64::EPSILON / 2.0;
    if !(p > 0.0) {
        return false;
    }
    if p >= 1.0 {
        return true;
    }
    if *u < p {
        *u = (*u / p).min(BELOW_ONE);
        true
    } else {
        *u = ((*u - p) / (1.0 - p)).clamp(0.0, BELOW_ONE);
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;
    use crate::math::special::gamma_q;

    /// A pixel's shared walks take the exact |B|_ω of the primitives that cross their voxels
    /// along the pixel's centre ray (`Walk::fill`'s `pixel_dir`), and a walk whose cache was
    /// filled by other pixels' walks gives what a fresh walk gives.
    #[test]
    fn shared_walks_take_the_pixels_areas() {
        use crate::gen::{generate, GenSettings};
        let scene = generate(
            "foliage",
            &GenSettings {
                triangles: 3000,
                ..Default::default()
            },
        )
        .unwrap()
        .to_scene();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.agg");
        let bake = crate::bake::BakeSettings {
            max_res: 16,
            min_res: 2,
            samples: 8,
            aiv_res: 8,
            aiv_rays: 8,
            abv_res: 8,
            abv_rays: 1,
            ..Default::default()
        };
        crate::bake::bake_to_file(&scene, "t", &bake, &path, &crate::util::no_progress).unwrap();
        let lod = LodScene::open(&path).unwrap();
        let (lo, hi) = lod.bounds().unwrap();
        let centre = 0.5 * (lo + hi);
        let eye = centre + Vec3::new(0.3, 0.4, 2.5) * (hi - lo).max_element();
        let settings = TraceSettings::default();
        let lights = Lights::constant(Vec3::ONE);
        let mut rng = Pcg32::new(3, 1);
        let mut cones = Vec::new();
        for _ in 0..200 {
            let target = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            cones.push(Cone::new(eye, target - eye, 0.004));
        }
        let pixel = |c: &Cone| (c.dir + Vec3::new(0.003, -0.002, 0.001)).normalize();
        // Each cone on a fresh walk, then all on one walk, twice over (the second pass finds
        // every area kept from the walks of the pixels before).
        fn areas<'s>(w: &mut Walk<'s>, lod: &'s LodScene, c: &Cone, pixel: Vec3) -> Vec<f32> {
            let settings = TraceSettings::default();
            w.fill(lod, c, &Lights::constant(Vec3::ONE), &settings, 0.5, pixel);
            w.list.iter().map(|h| h.exact_area).collect()
        }
        let fresh: Vec<Vec<f32>> = cones
            .iter()
            .map(|c| areas(&mut Walk::default(), &lod, c, pixel(c)))
            .collect();
        let mut crossing = 0;
        for (c, a) in cones.iter().zip(&fresh) {
            let w = &mut Walk::default();
            w.fill(&lod, c, &lights, &settings, 0.5, pixel(c));
            for (h, &got) in w.list.iter().zip(a) {
                let (level, block, i) = (h.voxel.data, &h.voxel.block, h.voxel.i);
                if block.hit[i as usize].area_case == Some(crate::spatial::AreaCase::Crossing) {
                    let want = block.primitive(level, i).unwrap().projected_area(pixel(c));
                    assert_eq!(got, want, "|B| along the pixel's centre ray");
                    crossing += 1;
                }
            }
        }
        assert!(crossing > 100, "{crossing} crossing primitives met");
        let mut shared = Walk::default();
        for _pass in 0..2 {
            for (c, a) in cones.iter().zip(&fresh) {
                assert_eq!(&areas(&mut shared, &lod, c, pixel(c)), a);
            }
        }
    }

    /// Candidate k's weight: zero, NaN and a range of positive weights.
    fn weight(k: usize) -> f32 {
        match k % 7 {
            0 => 0.0,
            3 => f32::NAN,
            _ => 0.2 + (k % 5) as f32,
        }
    }

    /// The picks of one stream of `len` candidates.
    fn picks(len: usize, n: usize, u: f32) -> ([Option<usize>; MAX_PICKS], f32) {
        let mut p = Picks::new(n, u);
        for k in 0..len {
            p.push(k, weight(k));
        }
        p.finish()
    }

    /// Pearson's test of the picks' frequencies against w_k / Σw, with one pick and three,
    /// among the held candidates and past them; candidates of weight zero or NaN never picked.
    #[test]
    fn picks_follow_the_weights() {
        for len in [6usize, HELD_HITS + 40] {
            let total: f64 = (0..len)
                .map(weight)
                .filter(|w| *w > 0.0)
                .map(|w| w as f64)
                .sum();
            for n in [1usize, 3] {
                let mut rng = Pcg32::new(7, (len * 8 + n) as u64);
                let mut observed = vec![0f64; len];
                let draws = 20_000;
                for _ in 0..draws {
                    let (kept, sum) = picks(len, n, rng.next_f32());
                    assert!(
                        (sum as f64 - total).abs() < 1e-4 * total,
                        "{sum} vs {total}"
                    );
                    for k in kept.iter().take(n) {
                        observed[k.expect("every pick is made")] += 1.0;
                    }
                }
                let m = (draws * n) as f64;
                let (mut stat, mut cells) = (0.0, 0usize);
                for (k, o) in observed.iter().enumerate() {
                    let w = weight(k);
                    if !(w > 0.0) {
                        assert_eq!(*o, 0.0, "candidate {k} of weight {w} picked");
                        continue;
                    }
                    let e = m * w as f64 / total;
                    stat += (o - e).powi(2) / e;
                    cells += 1;
                }
                let dof = (cells - 1) as f64;
                let p = gamma_q(dof / 2.0, stat / 2.0);
                assert!(
                    p > 1e-4,
                    "{len} candidates, {n} picks: χ² {stat} on {dof}, p {p}"
                );
            }
        }
    }

    /// Stratified numbers make stratified picks: 64 numbers one to each 1/64 pick each held
    /// candidate within one of 64·w/Σw times, and a cone's two picks are never the same
    /// candidate when none holds half the weight.
    #[test]
    fn stratified_numbers_make_stratified_picks() {
        let len = 12;
        let total: f64 = (0..len)
            .map(weight)
            .filter(|w| *w > 0.0)
            .map(|w| w as f64)
            .sum();
        let mut count = vec![0f64; len];
        for i in 0..64 {
            let (kept, _) = picks(len, 2, (i as f32 + 0.5) / 64.0);
            let (a, b) = (kept[0].unwrap(), kept[1].unwrap());
            assert_ne!(a, b, "number {i}");
            count[a] += 1.0;
        }
        for (k, c) in count.iter().enumerate() {
            let want = 64.0 * (weight(k).max(0.0) as f64) / total;
            let want = if want.is_nan() { 0.0 } else { want };
            assert!(
                (c - want).abs() < 1.0,
                "candidate {k}: {c} picks, {want} expected"
            );
        }
        // No candidate of positive weight: no pick.
        let mut p = Picks::<u8>::new(1, 0.5);
        p.push(1, 0.0);
        p.push(2, f32::NAN);
        assert_eq!(p.finish().0[0], None);
    }

    /// The shared walk's picks by binary search ([`pick_cumulative`]) are the reservoir's.
    #[test]
    fn shared_walk_picks_are_the_reservoirs() {
        // Up to the held candidates the two are the same function of u; beyond them each
        // candidate is picked with the same probability w_k / Σw (both over a grid of u, the
        // frequencies exact to the grid's 1/20000 per boundary crossed).
        for len in [1usize, 5, 16, 40] {
            let w: Vec<f32> = (0..len).map(|k| 0.2 + (k % 5) as f32).collect();
            let cumulative: Vec<f64> = w
                .iter()
                .scan(0.0f64, |c, &x| {
                    *c += x as f64;
                    Some(*c)
                })
                .collect();
            let total = *cumulative.last().unwrap();
            for n in [1usize, 3] {
                let grid = 20_000;
                let mut by_search = vec![0u32; len];
                let mut by_reservoir = vec![0u32; len];
                for g in 0..grid {
                    let u = (g as f32 + 0.5) / grid as f32;
                    let a = pick_cumulative(&cumulative, n, u);
                    let mut reservoir = Picks::new(n, u);
                    for (k, &x) in w.iter().enumerate() {
                        reservoir.push(k, x);
                    }
                    let (b, _) = reservoir.finish();
                    for j in 0..n {
                        let (a, b) = (a[j].unwrap() as usize, b[j].unwrap());
                        if len <= HELD_HITS {
                            assert_eq!(a, b, "len {len} n {n} u {u}");
                        }
                        by_search[a] += 1;
                        by_reservoir[b] += 1;
                    }
                }
                for k in 0..len {
                    let p = w[k] as f64 / total;
                    let fs = by_search[k] as f64 / (grid * n) as f64;
                    let fr = by_reservoir[k] as f64 / (grid * n) as f64;
                    assert!(
                        (fs - p).abs() < 2e-4,
                        "search: len {len} k {k}: {fs} vs {p}"
                    );
                    assert!(
                        (fr - p).abs() < 0.01,
                        "reservoir: len {len} k {k}: {fr} vs {p}"
                    );
                }
            }
        }
        assert_eq!(pick_cumulative(&[], 2, 0.5), [None; MAX_PICKS]);
    }

    /// A reservoir step leaves its number in [0, 1) whatever the probability, and one that is
    /// not a probability neither keeps nor moves it.
    #[test]
    fn reservoir_steps_stay_in_range() {
        let mut rng = Pcg32::new(3, 3);
        let ps = [1e-300, 1e-9, 0.5, 1.0 - 1e-16, 1.0, 2.0];
        for _ in 0..10_000 {
            for &p in &ps {
                let mut u = [rng.next_f32() as f64, 1.0 - f64::EPSILON / 2.0, 0.0]
                    [rng.next_u32() as usize % 3];
                reservoir_step(&mut u, p);
                assert!((0.0..1.0).contains(&u), "u {u} after p {p}");
            }
        }
        for p in [f64::NAN, 0.0, -1.0] {
            let mut u = 0.25;
            assert!(!reservoir_step(&mut u, p));
            assert_eq!(u, 0.25);
        }
    }
}
