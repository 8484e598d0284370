//! The "traditional volumetric model" the paper argues against (§6.1, Fig. 7), as a baseline
//! for the quality study: the same voxels, read as a participating medium.
//!
//! Each voxel becomes a homogeneous medium of flat scatterers whose extinction is the voxel's
//! projected surface area per unit volume,
//!
//! ```text
//! σ_t(ω) = |A|·E|n·ω| / s³          (area · coverage, normals from the voxel's SGGX mixture)
//! ```
//!
//! transmittance is Beer–Lambert along the ray (exp(−∫σ_t)), light is scattered once by the
//! voxel's averaged BSDF (the same f̂ as the aggregate, so that only the visibility model
//! differs), and shadowing towards each light sample is again exponential transmittance, marched
//! through the same level. There is no AIV, ABV, primitive or |A|/|B| term: correlation between
//! voxels is what this model cannot express.

use glam::Vec3;

use super::{ConeResult, LodScene, Voxel};
use crate::bake::voxelize::morton3;
use crate::math::rng::Pcg32;
use crate::render::lights::Lights;
use crate::trace::Ray;

use super::primitive::box_interval;

impl<'a> LodScene<'a> {
    /// Walks the voxels of level `li` along `origin + t·dir` for t in [tmin, tmax], calling
    /// `f(voxel, t0, t1)` for each occupied one in order; `f` returns false to stop.
    fn march(
        &self,
        li: usize,
        origin: Vec3,
        dir: Vec3,
        tmin: f32,
        tmax: f32,
        mut f: impl FnMut(&Voxel, f32, f32) -> bool,
    ) {
        let level = &self.levels[li];
        let g = &level.grid;
        let inv = dir.recip();
        let (c0, c1) = box_interval(g.origin, g.origin + Vec3::splat(g.size), origin, inv);
        let (t0, t1) = (c0.max(tmin), c1.min(tmax));
        if !(t0 <= t1) {
            return;
        }
        let mut dda = super::Dda::new(g, origin, dir, inv, t0, None);
        let mut t = t0;
        for _ in 0..3 * g.res as usize + 8 {
            let t_exit = dda.t_exit().min(t1);
            if let Some(&idx) = level.by_key.get(&morton3(dda.v.as_uvec3())) {
                if t_exit > t && !f(&level.voxels[idx as usize], t, t_exit) {
                    return;
                }
            }
            if t_exit >= t1 {
                return;
            }
            match dda.advance() {
                Some((_, tc)) => t = tc,
                None => return,
            }
        }
    }

    /// Extinction coefficient of a voxel of level `li` towards `w`.
    #[inline]
    fn extinction(&self, li: usize, v: &Voxel, w: Vec3) -> f32 {
        let s = self.levels[li].grid.voxel_size();
        (v.area * Self::mean_cosine(v, w) / (s * s * s)).max(0.0)
    }

    /// Beer–Lambert transmittance from `p` along `w` to the end of level `li`'s grid.
    fn volume_transmittance(&self, li: usize, p: Vec3, w: Vec3) -> f32 {
        let mut tau = 0.0f32;
        self.march(li, p, w, 0.0, f32::INFINITY, |v, t0, t1| {
            tau += self.extinction(li, v, w) * (t1 - t0);
            tau < 20.0
        });
        (-tau).exp()
    }

    /// Traces a ray through level `li` read as an exponential-transmittance volume (the
    /// baseline above). `transmittance` is the background's Beer–Lambert weight.
    pub fn trace_volume(
        &self,
        ray: &Ray,
        li: usize,
        lights: &Lights,
        nee: u32,
        rng: &mut Pcg32,
    ) -> ConeResult {
        let background = lights.environment.eval(ray.dir);
        if self.levels.is_empty() {
            return ConeResult {
                radiance: background,
                transmittance: 1.0,
                primitives: 0,
                coverage: 0.0,
            };
        }
        let li = li.min(self.levels.len() - 1);
        let wo = -ray.dir;
        let mut tr = 1.0f32;
        let mut sum = Vec3::ZERO;
        let mut touched = 0u32;
        self.march(li, ray.origin, ray.dir, ray.tmin, ray.tmax, |v, t0, t1| {
            let sigma = self.extinction(li, v, ray.dir);
            let len = t1 - t0;
            let absorbed = 1.0 - (-sigma * len).exp();
            if absorbed > 1e-6 {
                touched += 1;
                // A point distributed like the segment's first scattering.
                let u = rng.next_f32();
                let dt = (-(1.0 - u * absorbed).ln() / sigma).clamp(0.0, len);
                let p = ray.at(t0 + dt);
                let ls = Self::shade_with(v, wo, lights, nee, rng, |w| {
                    self.volume_transmittance(li, p, w)
                });
                let add = ls * (tr * absorbed);
                if add.is_finite() {
                    sum += add;
                }
                tr *= 1.0 - absorbed;
            }
            tr > 1e-4
        });
        ConeResult::compose(sum, background, tr, touched, 1.0 - tr)
    }
}
