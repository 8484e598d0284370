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
//! - **Hybrid representation** ([`Representation`], off unless asked for: `aggtool render`
//!   asks). An instance whose footprint where the cone meets it (its bounds, then its mesh
//!   hit) is finer than its aggregate's finest voxel is drawn from its mesh, loaded the first
//!   time it is needed ([`super::hybrid`]): an opaque hit, shaded by the reference renderer's
//!   code with real shadow rays through its own triangles and [`Assembly::transmittance`]
//!   through the others, which in turn stops at the triangles of instances drawn as meshes.
//! - **Transforms.** Rotations and uniform scales are exact. A uniform scale s divides
//!   distances and cone widths alike, so the aperture is unchanged. A non-uniform scale is
//!   approximated: directions are mapped by the linear part and renormalised, and the cone's
//!   width by the cube root of the determinant (the mean scale).

use std::cell::RefCell;
use std::path::Path;
use std::thread::LocalKey;
use std::time::Duration;

use glam::{Affine3A, Mat3, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray as BvhRay, RayHit};
use obvhs::BvhBuildParams;

use super::hybrid::{LazyMesh, MeshAsset, Representation};
use super::manifest::Manifest;
use crate::film::{Camera, Image, ImageStats};
use crate::lights::Lights;
use crate::math::sampling::Sampler;
use crate::runtime::{
    Cone, ConeResult, LayerHit, LodScene, Placement, RuntimeError, TraceSettings,
};
use crate::spatial::box_interval;
use crate::trace::{offset_origin, Hit as MeshHit, Ray, SurfacePoint};

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
    /// Per instance: |det M⁻¹|^(1/3), the local width of a unit world width ([`Xf`]'s
    /// `lateral`), computed once (its cube root was 1.6% of a city's render, per instance a
    /// cone met).
    lateral: Vec<f32>,
    /// Per instance: world bounds (empty for an asset without levels).
    bounds: Vec<Aabb>,
    /// BVH over the bounds of the instances that have any; `None` without them.
    bvh: Option<CwBvh>,
    /// The BVH's primitives: instance indices.
    bvh_instances: Vec<u32>,
    /// Per asset: the finest level's voxel size (the footprint below which the hybrid render
    /// draws the mesh), infinite for an asset without levels.
    finest: Vec<f32>,
    /// Per asset: how its instances are drawn.
    representation: Vec<Representation>,
    /// Per asset: its mesh, loaded when an instance first goes to mesh.
    meshes: Vec<LazyMesh>,
}

/// What a camera or shadow cone meets of an instance.
enum Pick<'a> {
    /// The aggregate.
    Aggregate,
    /// The mesh, hit at `hit` by `ray` (the world ray in the instance's space: t is the
    /// world's ray parameter).
    Mesh {
        mesh: &'a MeshAsset,
        ray: Ray,
        hit: MeshHit,
    },
    /// The mesh, not hit: the cone passes.
    Miss,
}

/// What an instance on a camera cone's list gives one sample ([`Assembly::compose`]).
enum Met {
    /// Nothing: the cone passes.
    Miss,
    /// A mesh hit at this world ray parameter, with its radiance: it ends the cone.
    Opaque(Vec3, f32),
    /// The aggregate's result (surfaces without background) and its first hit's world ray
    /// parameter.
    Aggregate(ConeResult, f32),
}

/// What an instance was drawn with where a cone first met it (the level picture).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Drawn {
    /// Its mesh.
    Mesh,
    /// Its aggregate, this level (0 = finest) at the first primitive met.
    Level(usize),
}

/// The first instance a cone meets: which, and how it was drawn there.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FirstHit {
    /// The instance (index in the manifest).
    pub instance: usize,
    /// Mesh or level.
    pub drawn: Drawn,
}

/// Per-thread scratch of [`Assembly::trace`]: the instances along the cone and those traced
/// but not composed yet. Kept between cones so that the hot path allocates nothing once the
/// vectors have grown to the deepest cone's needs.
#[derive(Default)]
struct TraceScratch {
    list: Vec<(f32, u32)>,
    pending: Vec<(f32, ConeResult)>,
}

/// Per-thread scratch of [`Assembly::layer_into`]: the instances along the cone, the layers
/// traced but not composed yet (first hit, range in `raw`, transmittance), and their hits.
#[derive(Default)]
struct LayerScratch {
    list: Vec<(f32, u32)>,
    pending: Vec<(f32, usize, usize, f32)>,
    raw: Vec<LayerHit>,
}

thread_local! {
    static TRACE_SCRATCH: RefCell<TraceScratch> = RefCell::default();
    static LAYER_SCRATCH: RefCell<LayerScratch> = RefCell::default();
    /// [`Assembly::transmittance`]'s list (called from inside a trace, so its own).
    static SHADOW_SCRATCH: RefCell<Vec<(f32, u32)>> = RefCell::default();
}

/// Runs `f` on this thread's scratch `key`, or on a fresh one if it is in use (a re-entrant
/// call, which the renderer does not make; then it allocates, but stays correct).
#[inline]
fn with_scratch<T: Default + 'static, R>(
    key: &'static LocalKey<RefCell<T>>,
    f: impl FnOnce(&mut T) -> R,
) -> R {
    let mut f = Some(f);
    let r = key.with(|c| match c.try_borrow_mut() {
        Ok(mut s) => Some((f.take().unwrap())(&mut s)),
        Err(_) => None,
    });
    match r {
        Some(r) => r,
        None => (f.take().unwrap())(&mut T::default()),
    }
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
        let lateral = world_to_local
            .iter()
            .map(|m| {
                Affine3A::from_cols_array(m)
                    .matrix3
                    .determinant()
                    .abs()
                    .cbrt()
            })
            .collect();
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
        let finest = scenes
            .iter()
            .map(|s| {
                if s.level_count() > 0 {
                    s.grid(0).voxel_size()
                } else {
                    f32::INFINITY
                }
            })
            .collect();
        let assets = manifest.assets.len();
        Ok(Assembly {
            manifest,
            scenes,
            world_to_local,
            lateral,
            bounds,
            bvh,
            bvh_instances,
            finest,
            representation: vec![Representation::Aggregate; assets],
            meshes: (0..assets).map(|_| LazyMesh::default()).collect(),
        })
    }

    /// Draws every asset's instances this way (the default is [`Representation::Aggregate`]).
    pub fn set_representation(&mut self, r: Representation) {
        self.representation.fill(r);
    }

    /// Draws asset `a`'s instances this way (index as [`Manifest::assets`]).
    pub fn set_asset_representation(&mut self, a: usize, r: Representation) {
        self.representation[a] = r;
    }

    /// Draws every asset of at most `at_most` triangles (counted from its source without
    /// importing it, [`crate::import::triangle_count`]) from its mesh at every distance,
    /// instead of as [`Representation::Hybrid`] does; other assets, and sources that cannot
    /// be counted, are left as they are. Returns the assets switched.
    ///
    /// An aggregate pays where it replaces many triangles with few voxels. For an asset of a
    /// few thousand triangles the mesh is cheaper to trace at any distance (a few BVH nodes
    /// where a cone walks voxels and weighs every primitive it meets), smaller in memory, and
    /// exact. The 1,000-instance city of `aggtool gen city` (30 assets of 20 to 11,799
    /// triangles) at 512×256, 16 spp: hybrid 2.7–3.0× the reference's time, every asset from
    /// its mesh 1.09–1.15× with less peak memory than the reference (the book's page of
    /// 2026-12-07, "Small meshes drawn as meshes").
    pub fn draw_small_meshes(&mut self, at_most: u64) -> usize {
        let mut switched = 0;
        for a in 0..self.representation.len() {
            if self.representation[a] != Representation::Hybrid {
                continue;
            }
            let source = &self.manifest.assets[a].source;
            if crate::import::triangle_count(source, at_most).is_ok_and(|n| n <= at_most) {
                self.representation[a] = Representation::Mesh;
                switched += 1;
            }
        }
        switched
    }

    /// How asset `a`'s instances are drawn.
    pub fn representation(&self, a: usize) -> Representation {
        self.representation[a]
    }

    /// Whether asset `a`'s mesh has been loaded (it is, the first time one of its instances
    /// goes to mesh).
    pub fn mesh_loaded(&self, a: usize) -> bool {
        self.meshes[a].loaded()
    }

    /// Triangles of asset `a`'s mesh, when it is loaded.
    pub fn mesh_triangles(&self, a: usize) -> Option<usize> {
        self.meshes[a]
            .peek()
            .map(|m| m.scene().unique_triangle_count())
    }

    /// The first mesh that failed to load (asset index and why): its instances were drawn from
    /// their aggregate instead.
    pub fn mesh_error(&self) -> Option<(usize, String)> {
        self.meshes
            .iter()
            .enumerate()
            .find_map(|(a, m)| m.error().map(|e| (a, e.to_string())))
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

    /// The distinct resolutions of its aggregates' levels, finest first.
    pub fn level_resolutions(&self) -> Vec<u32> {
        let mut r: Vec<u32> = (0..self.manifest().assets.len())
            .flat_map(|i| {
                let s = self.scene(i);
                (0..s.level_count()).map(move |l| s.grid(l).res)
            })
            .collect();
        r.sort_unstable_by(|x, y| y.cmp(x));
        r.dedup();
        r
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
            lateral: self.lateral[i],
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

    /// How instance `i` meets the world `cone`, which enters its bounds at `entry`: by its
    /// aggregate, unless its asset is drawn as a mesh, or hybrid and the cone's footprint there
    /// (its radius at the entry, and at the mesh hit, in the instance's space) is finer than
    /// the aggregate's finest voxel. A forced level (`settings.level`) means aggregates.
    #[inline]
    fn pick(
        &self,
        i: usize,
        xf: &Xf,
        cone: &Cone,
        entry: f32,
        settings: &TraceSettings,
    ) -> Pick<'_> {
        let a = self.manifest.asset_of(i);
        let hybrid = match self.representation[a] {
            Representation::Aggregate => return Pick::Aggregate,
            Representation::Hybrid => true,
            Representation::Mesh => false,
        };
        // The footprint's radius in the instance's space at world distance t:
        // tan(θ/2) · t · lateral (the local width of a unit world width).
        let radius = (0.5 * cone.aperture).tan() * xf.lateral;
        let finest = self.finest[a];
        if hybrid && (settings.level.is_some() || !finer(radius * entry, finest)) {
            return Pick::Aggregate;
        }
        let Some(mesh) = self.meshes[a].get(&self.manifest.assets[a].source) else {
            return Pick::Aggregate;
        };
        let ray = local_ray(xf, cone);
        match mesh.intersect(&ray) {
            None => Pick::Miss,
            Some(hit) if hybrid && !finer(radius * hit.t, finest) => Pick::Aggregate,
            Some(hit) => Pick::Mesh { mesh, ray, hit },
        }
    }

    /// Direct light at a mesh hit of instance `i`, shaded as the reference renderer shades
    /// (its material BSDF, sun and environment by MIS): shadow rays through the instance's own
    /// triangles, and through every other instance as [`Assembly::transmittance`] sees it (an
    /// aggregate's ABV, a mesh's triangles).
    #[allow(clippy::too_many_arguments)]
    fn shade_mesh<S: Sampler + ?Sized>(
        &self,
        i: usize,
        xf: &Xf,
        mesh: &MeshAsset,
        ray: &Ray,
        hit: &MeshHit,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
    ) -> Vec3 {
        let local = mesh.accel().surface(ray, hit);
        let normals = Mat3::from(xf.to_local.matrix3).transpose();
        let ng = (normals * local.ng).normalize_or(Vec3::Y);
        let sp = SurfacePoint {
            p: xf.to_world.transform_point3(local.p),
            ng,
            ns: (normals * local.ns).try_normalize().unwrap_or(ng),
            uv: local.uv,
            material: local.material,
        };
        // The shadow cone towards other instances: as for a voxel (InstancePlace::occlusion).
        let t0 = (sp.p - cone.origin).length().max(1e-6);
        crate::render::reference::shade(mesh.scene(), &sp, -cone.dir, lights, sampler, |wi| {
            let o = offset_origin(sp.p, sp.ng, wi);
            if mesh.occluded(
                xf.to_local.transform_point3(o),
                xf.to_local.transform_vector3(wi),
            ) {
                return 0.0;
            }
            let shadow = Cone {
                origin: o - wi * t0,
                dir: wi,
                aperture: cone.aperture,
                tmin: t0,
                tmax: f32::INFINITY,
            };
            self.transmittance(&shadow, settings, Some(i))
        })
    }

    /// Traces one camera cone through the assembly with the runtime's lights and shading.
    pub fn trace<S: Sampler + ?Sized>(
        &self,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
    ) -> ConeResult {
        with_scratch(&TRACE_SCRATCH, |scratch| {
            self.trace_with(cone, lights, settings, sampler, scratch)
        })
    }

    fn trace_with<S: Sampler + ?Sized>(
        &self,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
        scratch: &mut TraceScratch,
    ) -> ConeResult {
        let background = lights.environment.eval(cone.dir);
        let TraceScratch { list, pending } = scratch;
        self.along(cone, None, true, list);
        self.compose(list, pending, background, sampler, |j, opaque, sampler| {
            let (entry, i) = list[j];
            let i = i as usize;
            let xf = self.xf(i);
            match self.pick(i, &xf, cone, entry, settings) {
                Pick::Miss => Met::Miss,
                Pick::Mesh { mesh, ray, hit } => Met::Opaque(
                    self.shade_mesh(i, &xf, mesh, &ray, &hit, cone, lights, settings, sampler),
                    hit.t,
                ),
                Pick::Aggregate => {
                    let (local, k) = self.clipped_local_cone(&xf, cone, opaque);
                    let place = self.place(i, xf, cone, settings);
                    let (r, first) = self.scenes[self.manifest.asset_of(i)]
                        .trace_placed(&local, lights, settings, sampler, &place);
                    Met::Aggregate(r, first / k)
                }
            }
        })
    }

    /// Composes what the instances on a cone's list (`list`, ordered by entry) give, nearest
    /// first: `meet(j, opaque, sampler)` is what instance `list[j]` gives the cone, with the
    /// nearest opaque (mesh) hit before it at `opaque`. Instances are asked in the list's
    /// order until what is left to see falls below [`MIN_TRANSMITTANCE`] (Russian roulette
    /// below [`ROULETTE_BELOW`]); `pending` is scratch.
    fn compose<S: Sampler + ?Sized>(
        &self,
        list: &[(f32, u32)],
        pending: &mut Vec<(f32, ConeResult)>,
        background: Vec3,
        sampler: &mut S,
        mut meet: impl FnMut(usize, f32, &mut S) -> Met,
    ) -> ConeResult {
        pending.clear();
        // The nearest mesh hit so far: opaque, so aggregates traced after it stop there (what
        // lies behind it is hidden).
        let mut opaque = f32::INFINITY;
        let mut acc = Composite {
            radiance: Vec3::ZERO,
            transmittance: 1.0,
            primitives: 0,
            coverage: 0.0,
        };
        // Instances traced but not composed yet (`pending`): (first hit, result), kept sorted
        // by first hit, nearest last.
        for (j, &(entry, _)) in list.iter().enumerate() {
            acc.flush(pending, entry);
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
            let (r, t) = match meet(j, opaque, sampler) {
                Met::Miss => continue,
                // A mesh is opaque: it ends the cone where it is hit.
                Met::Opaque(radiance, t) => {
                    opaque = opaque.min(t);
                    (
                        ConeResult {
                            radiance,
                            transmittance: 0.0,
                            primitives: 1,
                            coverage: 1.0,
                        },
                        t,
                    )
                }
                Met::Aggregate(r, t) => {
                    if r.primitives == 0 && r.transmittance >= 1.0 {
                        continue;
                    }
                    (r, t)
                }
            };
            let at = pending.partition_point(|p| p.0 > t);
            pending.insert(at, (t, r));
        }
        acc.flush(pending, f32::INFINITY);
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

    /// World cone `cone` in instance space ([`local_cone`]), ended at the nearest opaque hit
    /// before it (world parameter `opaque`).
    #[inline]
    fn clipped_local_cone(&self, xf: &Xf, cone: &Cone, opaque: f32) -> (Cone, f32) {
        let (mut local, k) = local_cone(xf, cone);
        if opaque < f32::INFINITY {
            local.tmax = local.tmax.min(opaque * k);
        }
        (local, k)
    }

    /// Instance `i` as the runtime's shading sees it, for camera cone `cone`.
    #[inline]
    fn place<'a>(
        &'a self,
        i: usize,
        xf: Xf,
        cone: &Cone,
        settings: &'a TraceSettings,
    ) -> InstancePlace<'a> {
        InstancePlace {
            asm: self,
            instance: i,
            xf,
            camera: cone.origin,
            aperture: cone.aperture,
            settings,
        }
    }

    /// What every instance but `skip` lets through along `cone` (world space): the product of
    /// their ABV transmittances, and 0 where an instance drawn as a mesh blocks the centre ray
    /// (see [`Representation`]).
    pub fn transmittance(&self, cone: &Cone, settings: &TraceSettings, skip: Option<usize>) -> f32 {
        with_scratch(&SHADOW_SCRATCH, |list| {
            self.along(cone, skip, false, list);
            let mut t = 1.0f32;
            for &(entry, i) in list.iter() {
                let i = i as usize;
                let xf = self.xf(i);
                let a = self.manifest.asset_of(i);
                if self.representation[a] == Representation::Mesh {
                    // Drawn as a mesh at every distance: whether it blocks the centre ray is
                    // all a shadow cone asks, which any hit answers (what `pick`'s closest
                    // hit would say, sooner).
                    if let Some(mesh) = self.meshes[a].get(&self.manifest.assets[a].source) {
                        if mesh.blocks(&local_ray(&xf, cone)) {
                            return 0.0;
                        }
                        continue;
                    }
                }
                match self.pick(i, &xf, cone, entry, settings) {
                    Pick::Miss => continue,
                    Pick::Mesh { .. } => return 0.0,
                    Pick::Aggregate => {
                        let (local, _) = local_cone(&xf, cone);
                        t *= self.scenes[self.manifest.asset_of(i)].transmittance(&local, settings);
                    }
                }
                if t <= MIN_TRANSMITTANCE {
                    return 0.0;
                }
            }
            t
        })
    }

    /// The primitives the world `cone` meets in every instance's aggregate, appended to `out`
    /// as one layer for a host that shades them itself and composites the assembly over what
    /// lies behind it (the Mitsuba host): each instance's layer ([`LodScene::layer_into`],
    /// meshes not drawn), its weights times the transmittance of the instances composed in
    /// front of it, in the order [`Assembly::trace`] composes them (by first hit), until what
    /// is left to see falls below [`MIN_TRANSMITTANCE`]. Hits carry their instance, and their
    /// `t` is the world cone's. Returns the transmittance behind the assembly.
    pub fn layer_into(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        out: &mut Vec<LayerHit>,
    ) -> f32 {
        with_scratch(&LAYER_SCRATCH, |scratch| {
            let LayerScratch { list, pending, raw } = scratch;
            raw.clear();
            pending.clear();
            self.along(cone, None, true, list);
            let mut acc = 1.0f32;
            for &(entry, i) in list.iter() {
                flush_layers(pending, raw, out, &mut acc, entry);
                if acc <= MIN_TRANSMITTANCE {
                    break;
                }
                let xf = self.xf(i as usize);
                let (local, k) = local_cone(&xf, cone);
                let a = raw.len();
                let tr = self.scenes[self.manifest.asset_of(i as usize)]
                    .layer_into(&local, settings, i, raw);
                if raw.len() == a && tr >= 1.0 {
                    continue;
                }
                for h in &mut raw[a..] {
                    h.t /= k;
                }
                let first = raw.get(a).map_or(entry, |h| h.t);
                let at = pending.partition_point(|p| p.0 > first);
                pending.insert(at, (first, a, raw.len(), tr));
            }
            flush_layers(pending, raw, out, &mut acc, f32::INFINITY);
            if acc <= MIN_TRANSMITTANCE {
                0.0
            } else {
                acc
            }
        })
    }

    /// The aggregate instance `i` draws.
    pub fn instance_scene(&self, i: usize) -> &LodScene {
        &self.scenes[self.manifest.asset_of(i)]
    }

    /// World direction `w` in instance `i`'s space, unit length (zero for a zero vector).
    pub fn direction_to_local(&self, i: usize, w: Vec3) -> Vec3 {
        let m = Affine3A::from_cols_array(&self.world_to_local[i]);
        m.transform_vector3(w).normalize_or_zero()
    }

    /// Instance `i`'s direction `v` in world space, unit length (zero for a zero vector).
    pub fn direction_to_world(&self, i: usize, v: Vec3) -> Vec3 {
        self.manifest
            .transform(i)
            .transform_vector3(v)
            .normalize_or_zero()
    }

    /// The first instance `cone` meets and how it is drawn there (mesh, or the level of its
    /// aggregate's first primitive), as [`Assembly::trace`] would draw it; `None` when the cone
    /// meets nothing. Shades nothing: what the level picture (`render --level-map`) shows.
    pub fn first_hit(&self, cone: &Cone, settings: &TraceSettings) -> Option<FirstHit> {
        with_scratch(&TRACE_SCRATCH, |scratch| {
            let list = &mut scratch.list;
            self.along(cone, None, true, list);
            let mut best: Option<(f32, FirstHit)> = None;
            for &(entry, i) in list.iter() {
                if best.is_some_and(|b| b.0 < entry) {
                    break;
                }
                let i = i as usize;
                let xf = self.xf(i);
                let (t, drawn) = match self.pick(i, &xf, cone, entry, settings) {
                    Pick::Miss => continue,
                    Pick::Mesh { hit, .. } => (hit.t, Drawn::Mesh),
                    Pick::Aggregate => {
                        let (local, k) = local_cone(&xf, cone);
                        let mut hits =
                            self.scenes[self.manifest.asset_of(i)].hits(&local, settings);
                        match hits.next() {
                            Some(h) => (h.t / k, Drawn::Level(h.voxel.level())),
                            None => continue,
                        }
                    }
                };
                if best.is_none_or(|b| t < b.0) {
                    best = Some((t, FirstHit { instance: i, drawn }));
                }
            }
            best.map(|b| b.1)
        })
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

/// Appends, nearest first, the pending layers (first hit, range of `raw`, transmittance;
/// nearest last) whose first hit is before `t` to `out`, their weights times what is left to
/// see (`acc`), which each attenuates in turn ([`Assembly::layer_into`]).
fn flush_layers(
    pending: &mut Vec<(f32, usize, usize, f32)>,
    raw: &[LayerHit],
    out: &mut Vec<LayerHit>,
    acc: &mut f32,
    t: f32,
) {
    while let Some(&(first, a, b, tr)) = pending.last() {
        if first > t {
            break;
        }
        pending.pop();
        out.extend(raw[a..b].iter().map(|h| LayerHit {
            weight: h.weight * *acc,
            ..*h
        }));
        *acc *= tr;
    }
}

/// Whether a footprint of radius `r` is finer than a finest voxel of size `finest` (false
/// for NaN: the aggregate then).
#[inline]
fn finer(r: f32, finest: f32) -> bool {
    r < finest
}

/// The centre ray of a world cone in an instance's space, its direction mapped unnormalised so
/// that its parameter is the world's.
#[inline]
fn local_ray(xf: &Xf, cone: &Cone) -> Ray {
    Ray {
        origin: xf.to_local.transform_point3(cone.origin),
        dir: xf.to_local.transform_vector3(cone.dir),
        tmin: cone.tmin,
        tmax: cone.tmax,
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
    crate::runtime::render_sharing_walks(
        camera,
        spp,
        seed,
        settings,
        progress,
        |cone, sampler| asm.trace(cone, lights, settings, sampler),
        |_| 0,
        |walk: &mut AssemblyWalk, cone, dither, pixel_dir| {
            walk.start(asm, *cone, dither, pixel_dir)
        },
        |walk, sampler| walk.estimate(asm, lights, settings, sampler),
    )
}

/// A camera cone's way through the assembly kept for the samples of a pixel that share it
/// ([`TraceSettings::samples_per_walk`]): the instances on the cone, and for each the first
/// sample to reach it keeps what it is there (missed, its mesh's hit, or its aggregate's
/// walk); every sample shades and composes anew. Its buffers are kept between pixels.
#[derive(Default)]
struct AssemblyWalk<'a> {
    cone: Option<Cone>,
    dither: f32,
    /// The pixel's centre ray (world): the aggregates' walks take |B|_ω along it.
    pixel_dir: Vec3,
    list: Vec<(f32, u32)>,
    pending: Vec<(f32, ConeResult)>,
    kept: Vec<Kept<'a>>,
    /// The aggregates' walks ([`Kept::Aggregate`] indexes them); the first `used` are this
    /// cone's.
    walks: Vec<crate::runtime::Walk<'a>>,
    used: usize,
}

/// What an instance on an [`AssemblyWalk`]'s cone is there.
enum Kept<'a> {
    /// Not reached by a sample yet.
    Unknown,
    /// Missed.
    Miss,
    /// Its mesh, hit.
    Mesh {
        mesh: &'a MeshAsset,
        ray: Ray,
        hit: MeshHit,
    },
    /// Its aggregate: the walk's index and the local cone's scale k.
    Aggregate { walk: usize, k: f32 },
}

impl<'a> AssemblyWalk<'a> {
    /// Starts a new cone (the instances on it, nothing kept yet).
    fn start(&mut self, asm: &'a Assembly, cone: Cone, dither: f32, pixel_dir: Vec3) {
        asm.along(&cone, None, true, &mut self.list);
        self.kept.clear();
        self.kept.resize_with(self.list.len(), || Kept::Unknown);
        self.used = 0;
        self.cone = Some(cone);
        self.dither = dither;
        self.pixel_dir = pixel_dir;
    }

    /// One sample's estimate: [`Assembly::trace`] of the kept cone with what is kept.
    fn estimate<S: Sampler + ?Sized>(
        &mut self,
        asm: &'a Assembly,
        lights: &Lights,
        settings: &'a TraceSettings,
        sampler: &mut S,
    ) -> ConeResult {
        let Some(cone) = self.cone else {
            return ConeResult::compose(Vec3::ZERO, Vec3::ZERO, 1.0, 0, 0.0);
        };
        let background = lights.environment.eval(cone.dir);
        let AssemblyWalk {
            dither,
            pixel_dir,
            list,
            pending,
            kept,
            walks,
            used,
            ..
        } = self;
        asm.compose(list, pending, background, sampler, |j, opaque, sampler| {
            let (entry, i) = list[j];
            let i = i as usize;
            let xf = asm.xf(i);
            if matches!(kept[j], Kept::Unknown) {
                kept[j] = match asm.pick(i, &xf, &cone, entry, settings) {
                    Pick::Miss => Kept::Miss,
                    Pick::Mesh { mesh, ray, hit } => Kept::Mesh { mesh, ray, hit },
                    Pick::Aggregate => {
                        let (local, k) = asm.clipped_local_cone(&xf, &cone, opaque);
                        if *used == walks.len() {
                            walks.push(crate::runtime::Walk::default());
                        }
                        let scene = &asm.scenes[asm.manifest.asset_of(i)];
                        let dir = xf
                            .to_local
                            .transform_vector3(*pixel_dir)
                            .normalize_or_zero();
                        walks[*used].fill(scene, &local, lights, settings, *dither, dir);
                        *used += 1;
                        Kept::Aggregate { walk: *used - 1, k }
                    }
                };
            }
            match &kept[j] {
                Kept::Unknown | Kept::Miss => Met::Miss,
                Kept::Mesh { mesh, ray, hit } => Met::Opaque(
                    asm.shade_mesh(i, &xf, mesh, ray, hit, &cone, lights, settings, sampler),
                    hit.t,
                ),
                Kept::Aggregate { walk, k } => {
                    let place = asm.place(i, xf, &cone, settings);
                    let (surfaces, transmittance, primitives, coverage, first) =
                        walks[*walk].estimate_placed(lights, settings, sampler, &place);
                    let r = ConeResult::compose(
                        surfaces,
                        Vec3::ZERO,
                        transmittance,
                        primitives,
                        coverage,
                    );
                    Met::Aggregate(r, first / k)
                }
            }
        })
    }
}

/// The assembly is shared by the image loop's threads.
const _: () = {
    const fn is_sync<T: Sync + Send>() {}
    is_sync::<Assembly>()
};

/// The level picture: per pixel (row-major), what the cone through the pixel's centre meets
/// first ([`Assembly::first_hit`]), `None` for the sky.
pub fn level_map(
    asm: &Assembly,
    camera: &Camera,
    settings: &TraceSettings,
) -> Vec<Option<FirstHit>> {
    use rayon::prelude::*;
    let (w, h) = (camera.width, camera.height);
    let aperture = camera.pixel_angle();
    (0..w * h)
        .into_par_iter()
        .map(|k| {
            let p = glam::Vec2::new((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
            let (origin, dir) = camera.ray(p);
            asm.first_hit(&Cone::new(origin, dir, aperture), settings)
        })
        .collect()
}

/// Colour of the sky in the level picture.
pub const SKY_COLOUR: [u8; 3] = [24, 24, 24];
/// Colour of mesh hits in the level picture.
pub const MESH_COLOUR: [u8; 3] = [235, 60, 200];

/// Colour of level `l` (0 = finest) of `levels` in the level picture: a ramp from blue
/// (finest) through green and yellow to red (coarsest).
pub fn level_colour(l: usize, levels: usize) -> [u8; 3] {
    const RAMP: [[f32; 3]; 5] = [
        [40.0, 90.0, 240.0],
        [30.0, 200.0, 220.0],
        [60.0, 200.0, 60.0],
        [240.0, 220.0, 40.0],
        [230.0, 50.0, 30.0],
    ];
    let x = if levels > 1 {
        (l.min(levels - 1) as f32 / (levels - 1) as f32) * (RAMP.len() - 1) as f32
    } else {
        0.0
    };
    let i = (x.floor() as usize).min(RAMP.len() - 2);
    let f = x - i as f32;
    std::array::from_fn(|c| (RAMP[i][c] * (1.0 - f) + RAMP[i + 1][c] * f).round() as u8)
}

/// The level picture as sRGB8 with a legend strip under it (each line in its colour, with the
/// share of pixels), and the legend as text lines: (rgb, height, legend). Levels are named by
/// their resolution ("64³"), as `inspect` names them: `resolutions` lists every resolution the
/// assembly's aggregates hold, finest first, and `res_of` gives the resolution of a hit drawn
/// from a level.
pub fn level_map_picture(
    map: &[Option<FirstHit>],
    width: u32,
    height: u32,
    resolutions: &[u32],
    res_of: &dyn Fn(&FirstHit) -> u32,
) -> (Vec<u8>, u32, Vec<String>) {
    let levels = resolutions.len().max(1);
    let rank = |r: u32| {
        resolutions
            .iter()
            .position(|&x| x == r)
            .unwrap_or(levels - 1)
    };
    let mut counts = vec![0usize; levels + 2]; // levels, mesh, sky
    let mut rgb = Vec::with_capacity(map.len() * 3);
    for m in map {
        let (c, k) = match m {
            None => (SKY_COLOUR, levels + 1),
            Some(FirstHit {
                drawn: Drawn::Mesh, ..
            }) => (MESH_COLOUR, levels),
            Some(f) => {
                let l = rank(res_of(f));
                (level_colour(l, levels), l)
            }
        };
        counts[k] += 1;
        rgb.extend_from_slice(&c);
    }
    let n = map.len().max(1) as f32;
    let pct = |k: usize| 100.0 * counts[k] as f32 / n;
    let mut entries: Vec<(String, [u8; 3])> =
        vec![(format!("MESH {:.1}%", pct(levels)), MESH_COLOUR)];
    for (l, r) in resolutions.iter().enumerate() {
        entries.push((format!("{r}³ {:.1}%", pct(l)), level_colour(l, levels)));
    }
    entries.push((format!("SKY {:.1}%", pct(levels + 1)), [150, 150, 150]));
    let scale = if width >= 256 { 2 } else { 1 };
    let lines: Vec<&str> = entries.iter().map(|e| e.0.as_str()).collect();
    // A caption strip of the right height, then each line redrawn in its colour.
    let blank: Vec<&str> = lines.iter().map(|_| "").collect();
    let (mut out, h) = crate::render::label::with_caption(&rgb, width, height, &blank, scale);
    let pad = 2 * scale;
    for (k, (text, colour)) in entries.iter().enumerate() {
        crate::render::label::draw_text(
            &mut out,
            width,
            h,
            pad,
            height + pad + k as u32 * crate::render::label::line_height(scale),
            text,
            scale,
            *colour,
        );
    }
    (out, h, entries.into_iter().map(|e| e.0).collect())
}
