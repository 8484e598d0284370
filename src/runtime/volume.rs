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
//! through the same level with the same DDA. There is no AIV, ABV, primitive or |A|/|B| term:
//! correlation between voxels is what this model cannot express.

use glam::Vec3;

use super::level::Level;
use super::shade::shade_with;
use super::{Cone, ConeResult, LodScene, Sampler, TraceSettings};
use crate::lights::Lights;
use crate::spatial::{box_interval, Dda};

/// Walks the voxels of `level` along `origin + t·dir` for t in [tmin, tmax], calling
/// `f(voxel, t0, t1)` for each occupied one in order; `f` returns false to stop.
fn march(
    level: &Level,
    origin: Vec3,
    dir: Vec3,
    tmin: f32,
    tmax: f32,
    mut f: impl FnMut(u32, f32, f32) -> bool,
) {
    let g = &level.grid;
    let inv = dir.recip();
    let (lo, hi) = g.bounds();
    let (c0, c1) = box_interval(lo, hi, origin, inv);
    let (t0, t1) = (c0.max(tmin), c1.min(tmax));
    if !(t0 <= t1) {
        return;
    }
    let mut dda = Dda::new(g, origin, dir, inv, t0, None);
    let mut t = t0;
    for _ in 0..3 * g.res as usize + 8 {
        let t_exit = dda.t_exit().min(t1);
        if let Some(idx) = level.find(dda.v) {
            if t_exit > t && !f(idx, t, t_exit) {
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

/// Extinction coefficient of voxel `idx` of `level` towards `w`.
#[inline]
fn extinction(level: &Level, idx: u32, w: Vec3) -> f32 {
    let s = level.voxel_size;
    let Some(b) = level.voxels(idx) else {
        return 0.0;
    };
    let i = (idx - b.first) as usize;
    (b.hit[i].area * b.weight[i].mean_cosine(w) / (s * s * s)).max(0.0)
}

/// Beer–Lambert transmittance from `p` along `w` to the end of the level's grid.
fn volume_transmittance(level: &Level, p: Vec3, w: Vec3) -> f32 {
    let mut tau = 0.0f32;
    march(level, p, w, 0.0, f32::INFINITY, |v, t0, t1| {
        tau += extinction(level, v, w) * (t1 - t0);
        tau < 20.0
    });
    (-tau).exp()
}

impl LodScene {
    /// Traces a cone through its level read as an exponential-transmittance volume (the
    /// baseline above). `transmittance` is the background's Beer–Lambert weight.
    pub(crate) fn trace_volume<S: Sampler + ?Sized>(
        &self,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
    ) -> ConeResult {
        let background = lights.environment.eval(cone.dir);
        let miss = ConeResult {
            radiance: background,
            transmittance: 1.0,
            primitives: 0,
            coverage: 0.0,
        };
        let Some(g0) = self.grids.first() else {
            return miss;
        };
        let (c0, _) = box_interval(g0.bounds().0, g0.bounds().1, cone.origin, cone.dir.recip());
        let li = settings
            .level
            .unwrap_or_else(|| self.level_for(cone.aperture, c0.max(cone.tmin)))
            .min(self.grids.len() - 1);
        let Some(level) = self.level(li) else {
            return miss;
        };
        let wo = -cone.dir;
        let mut tr = 1.0f32;
        let mut sum = Vec3::ZERO;
        let mut touched = 0u32;
        march(
            level,
            cone.origin,
            cone.dir,
            cone.tmin,
            cone.tmax,
            |v, t0, t1| {
                let sigma = extinction(level, v, cone.dir);
                let len = t1 - t0;
                let absorbed = 1.0 - (-sigma * len).exp();
                if absorbed > 1e-6 {
                    touched += 1;
                    // A point distributed like the segment's first scattering.
                    let u = sampler.next_1d();
                    let dt = (-(1.0 - u * absorbed).ln() / sigma).clamp(0.0, len);
                    let p = cone.origin + cone.dir * (t0 + dt);
                    let ls = match level.voxels(v) {
                        Some(b) => shade_with(
                            b.absdf(v - b.first),
                            wo,
                            lights,
                            settings.nee,
                            sampler,
                            |w| volume_transmittance(level, p, w),
                        ),
                        None => Vec3::ZERO,
                    };
                    sum += ls * (tr * absorbed);
                    tr *= 1.0 - absorbed;
                }
                tr > 1e-4
            },
        );
        ConeResult::compose(sum, background, tr, touched, 1.0 - tr)
    }
}
