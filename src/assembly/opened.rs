//! What a host opens by path: one aggregate (`.agg`) or an assembly manifest (`.json`), behind
//! one interface, so that the C ABI, the Python module and the Mitsuba host render either
//! with the same calls (issue 19: `agg_open` takes "an .agg file or assembly manifest").

use std::path::Path;

use glam::{Vec2, Vec3};

use super::{is_manifest, Assembly, AssemblyError};
use crate::bsdf::Bsdf;
use crate::lights::Lights;
use crate::runtime::{
    Cone, LayerHit, LodScene, PixelSamples, RuntimeError, TraceSettings, VoxelHandle,
};

/// Why a path could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The aggregate could not be opened.
    #[error(transparent)]
    Aggregate(#[from] RuntimeError),
    /// The manifest or one of its aggregates could not be opened.
    #[error(transparent)]
    Assembly(#[from] AssemblyError),
}

/// What a host needs to shade a picked voxel with one light sample and one ABSDF sample
/// (multiple importance sampling): [`Opened::shade_voxel`]. Directions in the opened frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct VoxelShade {
    /// f̂(ω_light, ω_o) (0 without a light sample).
    pub light_value: Vec3,
    /// The pdf of the ABSDF sampling ω_light.
    pub light_pdf: f32,
    /// min(1, V̂(ω_light)/η) ([`VoxelHandle::incident_visibility`]).
    pub light_visibility: f32,
    /// The ABSDF sample's direction (0 where none was drawn).
    pub wi: Vec3,
    /// f̂(ω_i, ω_o), not divided by the pdf.
    pub value: Vec3,
    /// Its solid-angle pdf, 0 where no direction was drawn.
    pub pdf: f32,
    /// min(1, V̂(ω_i)/η).
    pub visibility: f32,
}

/// One cone's pick from its layer: [`Opened::pick`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LayerPick {
    /// The sum of the layer's weights (0 when nothing was picked).
    pub weight: f32,
    /// What the layer lets through to what lies behind.
    pub transmittance: f32,
    /// The cone's ray parameter at its first hit (infinite for none).
    pub entry: f32,
    /// The picked primitive; `None` where no hit weighs anything.
    pub hit: Option<LayerHit>,
}

/// An opened aggregate or assembly.
pub enum Opened {
    /// One `.agg` file.
    Aggregate(LodScene),
    /// An assembly manifest with its aggregates, each mapped once.
    Assembly(Assembly),
}

impl Opened {
    /// Opens `path`: a manifest when it ends in `.json` ([`is_manifest`]), else an aggregate.
    pub fn open(path: &Path) -> Result<Opened, OpenError> {
        Ok(if is_manifest(path) {
            Opened::Assembly(Assembly::open(path)?)
        } else {
            Opened::Aggregate(LodScene::open(path)?)
        })
    }

    /// The single aggregate, for the calls that take one (the traversal layer).
    pub fn aggregate(&self) -> Option<&LodScene> {
        match self {
            Opened::Aggregate(s) => Some(s),
            Opened::Assembly(_) => None,
        }
    }

    /// World bounds: the baked asset's (as the file records them; `None` for an empty one),
    /// or the union of the instances'.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        match self {
            Opened::Aggregate(s) => (s.level_count() > 0).then(|| s.aggregate().bounds()),
            Opened::Assembly(a) => a.bounds(),
        }
    }

    /// The box outside which cones of full aperture `aperture` meet nothing before ray
    /// parameter `t_max` ([`LodScene::walk_bounds`]; for an assembly, its instances' cubes, as
    /// its instance BVH bounds them): a host may skip the cones whose rays miss it. `None`
    /// when nothing can be met.
    pub fn walk_bounds(
        &self,
        aperture: f32,
        t_max: f32,
        settings: &TraceSettings,
    ) -> Option<(Vec3, Vec3)> {
        match self {
            Opened::Aggregate(s) => s.walk_bounds(aperture, t_max, settings),
            Opened::Assembly(a) => a.bounds(),
        }
    }

    /// The levels' resolutions, finest first: the aggregate's, or for an assembly the
    /// distinct resolutions of its aggregates' levels, finest first.
    pub fn level_resolutions(&self) -> Vec<u32> {
        let of =
            |s: &LodScene| -> Vec<u32> { (0..s.level_count()).map(|l| s.grid(l).res).collect() };
        match self {
            Opened::Aggregate(s) => of(s),
            Opened::Assembly(a) => a.level_resolutions(),
        }
    }

    /// Traces `cones` in parallel into `rgba` (4 floats a cone: radiance, background
    /// transmittance), cone i drawing stream i of `seed`: [`LodScene::trace_batch`], or
    /// [`Assembly::trace`] per cone with the same streams.
    pub fn trace_batch(
        &self,
        cones: &[Cone],
        lights: &Lights,
        settings: &TraceSettings,
        seed: u64,
        rgba: &mut [f32],
    ) {
        match self {
            Opened::Aggregate(s) => s.trace_batch(cones, lights, settings, seed, rgba),
            Opened::Assembly(a) => crate::runtime::trace_batch_with(cones, seed, rgba, |c, rng| {
                a.trace(c, lights, settings, rng)
            }),
        }
    }

    /// [`Opened::trace_batch`] with the cones' samples stratified over their pixels
    /// ([`LodScene::trace_batch_stratified`]), for an aggregate or an assembly alike.
    pub fn trace_batch_stratified(
        &self,
        cones: &[Cone],
        at: PixelSamples<'_>,
        lights: &Lights,
        settings: &TraceSettings,
        seed: u64,
        rgba: &mut [f32],
    ) {
        match self {
            Opened::Aggregate(s) => {
                s.trace_batch_stratified(cones, at, lights, settings, seed, rgba)
            }
            Opened::Assembly(a) => {
                crate::runtime::trace_batch_stratified_with(cones, at, seed, rgba, |c, sampler| {
                    a.trace(c, lights, settings, sampler)
                })
            }
        }
    }

    /// [`LodScene::magnification`] of an aggregate: by how many levels its finest voxels are
    /// wider than `cone`, `None` where the cone misses it. An assembly's instances each choose
    /// their own levels: 0 where the cone meets the assembly's bounds.
    pub fn magnification(&self, cone: &Cone, settings: &TraceSettings) -> Option<u32> {
        match self {
            Opened::Aggregate(s) => s.magnification(cone, settings),
            Opened::Assembly(_) => {
                let (lo, hi) = self.bounds()?;
                let (t0, t1) = crate::spatial::box_interval(lo, hi, cone.origin, cone.dir.recip());
                (t0.max(cone.tmin) <= t1.min(cone.tmax)).then_some(0)
            }
        }
    }

    /// What the aggregate, or every instance of the assembly, lets through along `cone`.
    pub fn transmittance(&self, cone: &Cone, settings: &TraceSettings) -> f32 {
        self.transmittance_skipping(cone, settings, None)
    }

    /// [`Opened::transmittance`] leaving instance `skip` of an assembly out (a host's shadow
    /// cone from a hit on that instance, whose own occlusion its interior visibility already
    /// counts); ignored for an aggregate.
    pub fn transmittance_skipping(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        skip: Option<usize>,
    ) -> f32 {
        match self {
            Opened::Aggregate(s) => s.transmittance(cone, settings),
            Opened::Assembly(a) => a.transmittance(cone, settings, skip),
        }
    }

    /// The primitives `cone` meets, as one layer that a host shades and composites over what
    /// lies behind: [`LodScene::layer_into`] (instance 0) or [`Assembly::layer_into`].
    /// Returns the transmittance.
    pub fn layer_into(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        out: &mut Vec<LayerHit>,
    ) -> f32 {
        match self {
            Opened::Aggregate(s) => s.layer_into(cone, settings, 0, out),
            Opened::Assembly(a) => a.layer_into(cone, settings, out),
        }
    }

    /// One primitive of `cone`'s layer ([`Opened::layer_into`]) picked in proportion to its
    /// weight by the uniform number `u` (the first whose running sum passes u·Σw), with the
    /// layer's weight sum, transmittance and first hit: what a host that shades one hit a cone
    /// needs (the picked hit's radiance times `weight` is an unbiased estimate of Eq. 30's
    /// sum). `scratch` holds the layer (reused between calls).
    pub fn pick(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        u: f32,
        scratch: &mut Vec<LayerHit>,
    ) -> LayerPick {
        let mut out = [LayerPick::default()];
        self.picks(cone, settings, &[u], scratch, &mut out);
        out[0]
    }

    /// [`Opened::pick`] with one walk of `cone` serving several picks, one a number of `us`
    /// into `out` (as long): a host's samples of a pixel sharing the pixel's walk, as the
    /// runtime's own image loop shares them ([`TraceSettings::samples_per_walk`]).
    pub fn picks(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        us: &[f32],
        scratch: &mut Vec<LayerHit>,
        out: &mut [LayerPick],
    ) {
        scratch.clear();
        let transmittance = self.layer_into(cone, settings, scratch);
        let weight: f32 = scratch.iter().map(|h| h.weight).sum();
        let entry = scratch.first().map_or(f32::INFINITY, |h| h.t);
        for (o, &u) in out.iter_mut().zip(us) {
            let mut hit = None;
            if weight > 0.0 {
                let target = if u.is_finite() {
                    u.clamp(0.0, 1.0)
                } else {
                    0.0
                } * weight;
                let mut run = 0.0f32;
                // The last hit with a weight where rounding leaves the target past the end.
                for h in scratch.iter().filter(|h| h.weight > 0.0) {
                    run += h.weight;
                    hit = Some(*h);
                    if run > target {
                        break;
                    }
                }
            }
            *o = LayerPick {
                weight: if hit.is_some() { weight } else { 0.0 },
                transmittance,
                entry,
                hit,
            };
        }
    }

    /// [`Opened::picks`] for a batch of cones in parallel: `u` holds k numbers a cone (k ≥ 1,
    /// `u.len()` a multiple of `cones.len()`), and picks `i·k .. i·k + k` of the result come
    /// from cone i's walk. What the Python module's `Scene.pick` and the C ABI's
    /// `agg_pick_cones` call.
    pub fn pick_batch(
        &self,
        cones: &[Cone],
        u: &[f32],
        settings: &TraceSettings,
    ) -> Vec<LayerPick> {
        use rayon::prelude::*;
        if cones.is_empty() {
            return Vec::new();
        }
        let k = u.len() / cones.len();
        assert!(
            k >= 1 && k * cones.len() == u.len(),
            "k uniform numbers a cone"
        );
        let mut out = vec![LayerPick::default(); u.len()];
        out.par_chunks_mut(k)
            .zip(cones.par_iter().zip(u.par_chunks(k)))
            .for_each_init(Vec::new, |scratch, (o, (c, us))| {
                self.picks(c, settings, us, scratch, o)
            });
        out
    }

    /// Instances: the assembly's, 1 for an aggregate.
    pub fn instance_count(&self) -> usize {
        match self {
            Opened::Aggregate(_) => 1,
            Opened::Assembly(a) => a.manifest().instance_count(),
        }
    }

    /// The aggregate that `instance` draws (0 for an aggregate), `None` out of range.
    pub fn instance_scene(&self, instance: usize) -> Option<&LodScene> {
        match self {
            Opened::Aggregate(s) => (instance == 0).then_some(s),
            Opened::Assembly(a) => {
                (instance < a.manifest().instance_count()).then(|| a.instance_scene(instance))
            }
        }
    }

    /// A direction of the opened frame in `instance`'s own (the same for an aggregate), unit.
    /// `instance` must be in range.
    pub fn direction_to_local(&self, instance: usize, w: Vec3) -> Vec3 {
        match self {
            Opened::Aggregate(_) => crate::math::unit_or_zero(w),
            Opened::Assembly(a) => a.direction_to_local(instance, w),
        }
    }

    /// The shading inputs of voxel `v` of `instance` (as [`Opened::instance_scene`]'s
    /// `voxel` gives it) for outgoing `wo`, the light sample `wi_light` (if any) and the
    /// uniform numbers `u` (clamped into [0, 1)) of one ABSDF sample: the voxel's ABSDF and
    /// interior visibility towards both, the voxel looked up once by the caller. What the
    /// Python module's `voxel_shade` and the C ABI's `agg_instance_voxel_shade` compute.
    pub fn shade_voxel(
        &self,
        instance: usize,
        v: &VoxelHandle<'_>,
        wo: Vec3,
        wi_light: Option<Vec3>,
        u: Vec3,
    ) -> VoxelShade {
        let wo = self.direction_to_local(instance, wo);
        let mut r = VoxelShade::default();
        if let Some(wl) = wi_light {
            let wl = self.direction_to_local(instance, wl);
            (r.light_value, r.light_pdf) = v.eval_pdf(wl, wo);
            r.light_visibility = v.incident_visibility(wl);
        }
        let u = u.clamp(Vec3::ZERO, Vec3::splat(1.0 - f32::EPSILON));
        if let Some(smp) = v.sample(wo, u.x, Vec2::new(u.y, u.z)) {
            if smp.pdf > 0.0 && smp.pdf.is_finite() {
                r.wi = self.direction_to_world(instance, smp.wi);
                r.value = smp.value;
                r.pdf = smp.pdf;
                r.visibility = v.incident_visibility(smp.wi);
            }
        }
        r
    }

    /// `instance`'s direction `v` in the opened frame, unit. `instance` must be in range.
    pub fn direction_to_world(&self, instance: usize, v: Vec3) -> Vec3 {
        match self {
            Opened::Aggregate(_) => crate::math::unit_or_zero(v),
            Opened::Assembly(a) => a.direction_to_world(instance, v),
        }
    }

    /// The first error met while reading blocks lazily (a damaged block is refused when a
    /// cone first needs it), of the aggregate or of any of the assembly's aggregates.
    pub fn first_error(&self) -> Option<RuntimeError> {
        match self {
            Opened::Aggregate(s) => s.first_error(),
            Opened::Assembly(a) => {
                (0..a.manifest().assets.len()).find_map(|i| a.scene(i).first_error())
            }
        }
    }
}
