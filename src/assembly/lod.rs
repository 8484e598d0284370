//! An assembly rendered with the LoD runtime (paper §8): each unique aggregate opened once
//! (lazily: levels are paged in when cones need them), a BVH over the instances' world
//! bounds, and instances combined as uncorrelated.
//!
//! - **Camera cones.** The instances whose bounds the centre ray crosses are visited in order
//!   of entry distance; each is traced in its own space ([`LodScene::trace_placed`]) with the
//!   cone carried there (`local_cone`), so that it picks its level by its own footprint.
//!   The instances met are then composed in order of their **first primitive** along the ray
//!   (not of their bounds, which overlap: a ground's bounds hold the whole forest standing on
//!   it): the radiance of each is added through the transmittance of those before it, and its
//!   background transmittance (the ABV where the cone entered it) passes the rest on. An
//!   instance is composed as soon as no unvisited instance can come before it (its first hit
//!   is nearer than the next entry), and the walk stops once the transmittance is spent.
//! - **Light.** Light reaching a voxel of one instance is attenuated, besides the voxel's own
//!   AIV (which holds only its own asset's occlusion, each asset being baked alone), by every
//!   other instance its direction crosses: the shadow cone meets them through
//!   [`LodScene::transmittance`], their ABV. The shadow cone has the camera cone's aperture and
//!   the camera cone's width where it leaves the voxel (its apex set back by the camera
//!   distance), so that a distant instance is also shadowed at a coarse level.
//! - **Transforms.** Rotations and uniform scales are exact. A uniform scale s divides
//!   distances and cone widths alike, so the aperture is unchanged. A non-uniform scale is
//!   approximated: directions are mapped by the linear part and renormalised, and the cone's
//!   width by the cube root of the determinant (the mean scale).

use std::path::Path;
use std::time::Duration;

use glam::{Affine3A, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray as BvhRay, RayHit};
use obvhs::BvhBuildParams;

use super::manifest::Manifest;
use crate::film::{Camera, Image, ImageStats};
use crate::lights::Lights;
use crate::runtime::{Cone, ConeResult, LodScene, Placement, RuntimeError, Sampler, TraceSettings};
use crate::spatial::box_interval;

/// Why an assembly could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum AssemblyError {
    /// The manifest is unusable (or an aggregate file is missing).
    #[error(transparent)]
    Manifest(#[from] super::ManifestError),
    /// An asset's aggregate could not be opened.
    #[error("asset '{asset}': cannot open {path}: {source}")]
    Open {
        /// The asset id.
        asset: String,
        /// The aggregate.
        path: std::path::PathBuf,
        /// Why.
        #[source]
        source: RuntimeError,
    },
}

/// Transmittance below which a camera cone stops visiting instances: what lies behind can add
/// at most this fraction of its radiance.
const MIN_TRANSMITTANCE: f32 = 1e-4;

/// Transmittance below which a camera cone's walk through further instances is continued by
/// Russian roulette.
const ROULETTE_BELOW: f32 = 0.05;

/// An assembly ready for cone tracing.
pub struct Assembly {
    manifest: Manifest,
    /// One scene per asset (index as [`Manifest::assets`]).
    scenes: Vec<LodScene>,
    /// Per instance: world to object.
    world_to_local: Vec<[f32; 12]>,
    /// Per instance: world bounds (empty for an asset without levels).
    bounds: Vec<Aabb>,
    /// BVH over the bounds of the instances that have any; `None` without them.
    bvh: Option<CwBvh>,
    /// The BVH's primitives: instance indices.
    bvh_instances: Vec<u32>,
}

/// An instance's transform, inverse, and the factor its cone widths are scaled by.
#[derive(Clone, Copy)]
struct Xf {
    to_world: Affine3A,
    to_local: Affine3A,
    /// Local width of a unit world width: cbrt |det to_local| (1/s for a uniform scale s).
    lateral: f32,
}

impl Assembly {
    /// Opens every asset's aggregate once (lazily: milliseconds each) and builds the BVH over
    /// the instances' bounds.
    pub fn open(manifest_path: &Path) -> Result<Assembly, AssemblyError> {
        Self::new(Manifest::load(manifest_path)?)
    }

    /// [`Assembly::open`] on a parsed manifest.
    pub fn new(manifest: Manifest) -> Result<Assembly, AssemblyError> {
        use rayon::prelude::*;
        manifest.require_aggregates()?;
        let scenes = manifest
            .assets
            .iter()
            .map(|a| {
                LodScene::open(&a.aggregate).map_err(|source| AssemblyError::Open {
                    asset: a.id.clone(),
                    path: a.aggregate.clone(),
                    source,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let local_bounds: Vec<Option<(Vec3, Vec3)>> = scenes.iter().map(|s| s.bounds()).collect();
        let n = manifest.instance_count();
        let (world_to_local, bounds): (Vec<[f32; 12]>, Vec<Aabb>) = (0..n)
            .into_par_iter()
            .map(|i| {
                let m = manifest.transform(i);
                let mut world = Aabb::empty();
                if let Some((lo, hi)) = local_bounds[manifest.asset_of(i)] {
                    for k in 0..8 {
                        let c = Vec3A::new(
                            if k & 1 == 0 { lo.x } else { hi.x },
                            if k & 2 == 0 { lo.y } else { hi.y },
                            if k & 4 == 0 { lo.z } else { hi.z },
                        );
                        world.extend(m.transform_point3a(c));
                    }
                }
                (m.inverse().to_cols_array(), world)
            })
            .unzip();
        // Instances of an asset without levels have empty bounds and stay out of the BVH.
        let bvh_instances: Vec<u32> = (0..n as u32)
            .filter(|&i| bounds[i as usize].valid())
            .collect();
        let boxes: Vec<Aabb> = bvh_instances.iter().map(|&i| bounds[i as usize]).collect();
        let bvh = (!boxes.is_empty()).then(|| {
            build_cwbvh(
                &boxes,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            )
        });
        Ok(Assembly {
            manifest,
            scenes,
            world_to_local,
            bounds,
            bvh,
            bvh_instances,
        })
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The scene of asset `a` (index as [`Manifest::assets`]): which levels it prepared, its
    /// first error.
    pub fn scene(&self, a: usize) -> &LodScene {
        &self.scenes[a]
    }

    /// World bounds of every instance together, for framing views; `None` when empty.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut b = Aabb::empty();
        for x in &self.bounds {
            if x.valid() {
                b = b.union(x);
            }
        }
        (b.min.x <= b.max.x).then(|| (b.min.into(), b.max.into()))
    }

    #[inline]
    fn xf(&self, i: usize) -> Xf {
        let to_local = Affine3A::from_cols_array(&self.world_to_local[i]);
        Xf {
            to_world: self.manifest.transform(i),
            to_local,
            lateral: to_local.matrix3.determinant().abs().cbrt(),
        }
    }

    /// The instances whose bounds the centre ray of `cone` crosses within [tmin, tmax], as
    /// (entry distance, instance), sorted by entry when `sort`; `skip` is left out.
    fn along(&self, cone: &Cone, skip: Option<usize>, sort: bool, out: &mut Vec<(f32, u32)>) {
        out.clear();
        let Some(bvh) = &self.bvh else { return };
        if !(cone.dir.is_finite() && cone.origin.is_finite()) {
            return;
        }
        let inv = cone.dir.recip();
        let ray = BvhRay::new(cone.origin.into(), cone.dir.into(), cone.tmin, cone.tmax);
        let mut hit = RayHit::none();
        bvh.ray_traverse(ray, &mut hit, |_, id| {
            let i = self.bvh_instances[bvh.primitive_indices[id] as usize] as usize;
            if Some(i) != skip {
                let b = &self.bounds[i];
                let (t0, t1) = box_interval(b.min.into(), b.max.into(), cone.origin, inv);
                let (t0, t1) = (t0.max(cone.tmin), t1.min(cone.tmax));
                if t0 <= t1 {
                    out.push((t0, i as u32));
                }
            }
            f32::INFINITY
        });
        if sort {
            out.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        }
    }

    /// Traces one camera cone through the assembly with the runtime's lights and shading.
    pub fn trace<S: Sampler + ?Sized>(
        &self,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
    ) -> ConeResult {
        let background = lights.environment.eval(cone.dir);
        let mut list = Vec::new();
        self.along(cone, None, true, &mut list);
        let mut acc = Composite {
            radiance: Vec3::ZERO,
            transmittance: 1.0,
            primitives: 0,
            coverage: 0.0,
        };
        // Instances traced but not composed yet: (first hit, result), kept sorted by first
        // hit, nearest last.
        let mut pending: Vec<(f32, ConeResult)> = Vec::new();
        for &(entry, i) in &list {
            acc.flush(&mut pending, entry);
            if acc.transmittance <= MIN_TRANSMITTANCE {
                break;
            }
            // Russian roulette on what is left to see: below ROULETTE_BELOW the walk goes on
            // with probability T / ROULETTE_BELOW, its transmittance raised to ROULETTE_BELOW
            // (unbiased; instances traced but not yet composed share the fate of the rest).
            if acc.transmittance < ROULETTE_BELOW {
                if sampler.next_1d() * ROULETTE_BELOW >= acc.transmittance {
                    acc.transmittance = 0.0;
                    break;
                }
                acc.transmittance = ROULETTE_BELOW;
            }
            let i = i as usize;
            let xf = self.xf(i);
            let (local, k) = local_cone(&xf, cone);
            let place = InstancePlace {
                asm: self,
                instance: i,
                xf,
                camera: cone.origin,
                aperture: cone.aperture,
                settings,
            };
            let (r, first) = self.scenes[self.manifest.asset_of(i)]
                .trace_placed(&local, lights, settings, sampler, &place);
            if r.primitives == 0 && r.transmittance >= 1.0 {
                continue;
            }
            let t = first / k;
            let at = pending.partition_point(|p| p.0 > t);
            pending.insert(at, (t, r));
        }
        acc.flush(&mut pending, f32::INFINITY);
        let transmittance = if acc.transmittance <= MIN_TRANSMITTANCE {
            0.0
        } else {
            acc.transmittance
        };
        ConeResult {
            radiance: crate::math::finite_vec_or_zero(acc.radiance + background * transmittance),
            transmittance: crate::math::finite_or_zero(transmittance),
            primitives: acc.primitives,
            coverage: crate::math::finite_or_zero(acc.coverage),
        }
    }

    /// What every instance but `skip` lets through along `cone` (world space): the product of
    /// their ABV transmittances.
    pub fn transmittance(&self, cone: &Cone, settings: &TraceSettings, skip: Option<usize>) -> f32 {
        let mut list = Vec::new();
        self.along(cone, skip, false, &mut list);
        let mut t = 1.0f32;
        for &(_, i) in &list {
            let i = i as usize;
            let (local, _) = local_cone(&self.xf(i), cone);
            t *= self.scenes[self.manifest.asset_of(i)].transmittance(&local, settings);
            if t <= MIN_TRANSMITTANCE {
                return 0.0;
            }
        }
        t
    }
}

/// What a camera cone has gathered so far.
struct Composite {
    radiance: Vec3,
    transmittance: f32,
    primitives: u32,
    coverage: f32,
}

impl Composite {
    /// Composes, nearest first, the pending results whose first hit is before `t`.
    fn flush(&mut self, pending: &mut Vec<(f32, ConeResult)>, t: f32) {
        while let Some(&(first, r)) = pending.last() {
            if first > t {
                break;
            }
            pending.pop();
            self.radiance += self.transmittance * r.radiance;
            self.coverage += self.transmittance * r.coverage;
            self.primitives += r.primitives;
            self.transmittance *= r.transmittance;
        }
    }
}

/// A world cone in an instance's own space: the origin and the direction mapped, the ray
/// parameter scaled by k = |M⁻¹d| (so the same points are covered), the aperture's tangent by
/// lateral / k (unchanged for a uniform scale). Returns the cone and k.
#[inline]
fn local_cone(xf: &Xf, cone: &Cone) -> (Cone, f32) {
    let v = xf.to_local.transform_vector3(cone.dir);
    let k = v.length();
    let tan_half = (0.5 * cone.aperture).tan() * xf.lateral / k;
    (
        Cone {
            origin: xf.to_local.transform_point3(cone.origin),
            dir: v / k,
            aperture: 2.0 * tan_half.atan(),
            tmin: cone.tmin * k,
            tmax: cone.tmax * k,
        },
        k,
    )
}

/// An instance as the runtime's shading sees it.
struct InstancePlace<'a> {
    asm: &'a Assembly,
    instance: usize,
    xf: Xf,
    /// The camera cone's apex (world).
    camera: Vec3,
    aperture: f32,
    settings: &'a TraceSettings,
}

impl Placement for InstancePlace<'_> {
    #[inline]
    fn to_world(&self, local: Vec3) -> Vec3 {
        self.xf
            .to_world
            .transform_vector3(local)
            .normalize_or_zero()
    }
    #[inline]
    fn to_local(&self, world: Vec3) -> Vec3 {
        self.xf
            .to_local
            .transform_vector3(world)
            .normalize_or_zero()
    }
    fn occlusion(&self, p: Vec3, wi: Vec3) -> f32 {
        // The shadow cone: the camera cone's aperture, its apex set back along -wi by the
        // camera's distance so that its width at p is the camera cone's there.
        let pw = self.xf.to_world.transform_point3(p);
        let t0 = (pw - self.camera).length().max(1e-6);
        let cone = Cone {
            origin: pw - wi * t0,
            dir: wi,
            aperture: self.aperture,
            tmin: t0,
            tmax: f32::INFINITY,
        };
        self.asm
            .transmittance(&cone, self.settings, Some(self.instance))
    }
}

/// Renders an image of the assembly through the shared image loop
/// ([`crate::film::render_image`]): the same pixel sampling and seeds as a single aggregate's
/// render and as the reference.
pub fn render(
    asm: &Assembly,
    camera: &Camera,
    lights: &Lights,
    spp: u32,
    seed: u64,
    settings: &TraceSettings,
    progress: crate::util::Progress,
) -> (Image, ImageStats) {
    crate::film::render_image(camera, spp, seed, "LoD", progress, |s| {
        *s.rays += 1;
        let cone = Cone {
            origin: s.origin,
            dir: s.dir,
            aperture: s.aperture,
            tmin: 0.0,
            tmax: f32::INFINITY,
        };
        asm.trace(&cone, lights, settings, s.rng).radiance
    })
}

/// The assembly is shared by the image loop's threads.
const _: () = {
    const fn is_sync<T: Sync + Send>() {}
    is_sync::<Assembly>()
};
