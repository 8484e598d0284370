//! Ray tracing against a [`Scene`]: a two-level BVH built with obvhs' compressed-wide BVH.
//!
//! obvhs' own TLAS/BLAS traversal does not transform rays into instance space, so the instance
//! layer is ours: the top level holds one entry per instanced placement and one entry for all
//! meshes that are placed only once, which are merged into a single world-space BLAS (an OBJ
//! file's dozens of objects then cost one traversal, not dozens). Meshes placed several times
//! are stored once in object space and reached through their placements' inverse transforms.
//! Rays keep their parameterisation across the transform (directions are not renormalised),
//! so `t` is comparable between instances.
//!
//! Alpha cut-outs (glTF MASK) are honoured by both queries: a candidate hit whose material
//! alpha at the hit's texture coordinate is below the cutoff is ignored.

use std::time::Duration;

use glam::{Affine3A, Mat3, Vec2, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::{build_cwbvh, build_cwbvh_from_tris};
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray as BvhRay, RayHit};
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

use crate::scene::Scene;

/// A ray `origin + t · dir` for t in [tmin, tmax].
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Origin.
    pub origin: Vec3,
    /// Direction (not necessarily unit: `t` is in its units).
    pub dir: Vec3,
    /// Start of the interval searched.
    pub tmin: f32,
    /// End of the interval searched.
    pub tmax: f32,
}

impl Ray {
    /// A ray over t in [0, ∞).
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Ray {
            origin,
            dir,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }
    /// The point at parameter `t`.

    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + t * self.dir
    }

    #[inline]
    pub(crate) fn to_bvh(self) -> BvhRay {
        BvhRay::new(self.origin.into(), self.dir.into(), self.tmin, self.tmax)
    }
}

/// The closest hit of a ray.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    /// Ray parameter of the hit.
    pub t: f32,
    /// Index into [`Scene::instances`].
    pub instance: u32,
    /// Triangle index within the instance's mesh.
    pub triangle: u32,
    /// Barycentric weights of vertices 1 and 2.
    pub bary: Vec2,
}

/// Geometry at a hit point, in world space.
#[derive(Clone, Copy, Debug)]
pub struct SurfacePoint {
    /// World-space position.
    pub p: Vec3,
    /// Unit geometric normal (orientation of the triangle's winding).
    pub ng: Vec3,
    /// Unit shading normal: interpolated vertex normals, or `ng` when the mesh has none.
    pub ns: Vec3,
    /// First texture coordinates, interpolated (zero when the mesh has none).
    pub uv: Vec2,
    /// Index into [`Scene::materials`].
    pub material: u32,
}

#[derive(Clone, Copy, Debug)]
struct PrimRef {
    /// Scene instance, or `u32::MAX` for object-space BLASes (the TLAS entry knows it).
    instance: u32,
    triangle: u32,
}

struct Blas {
    bvh: CwBvh,
    /// Triangles in BVH order.
    tris: Vec<Triangle>,
    refs: Vec<PrimRef>,
    /// Whether any triangle's material can be cut out.
    cutout: bool,
}

#[derive(Clone, Copy)]
struct TlasEntry {
    blas: u32,
    instance: u32,
    world_to_object: Affine3A,
    identity: bool,
}

/// Per-instance data used when shading a hit.
#[derive(Clone, Copy)]
struct InstanceXf {
    object_to_world: Affine3A,
    normal_matrix: Mat3,
}

/// Build statistics.
#[derive(Clone, Copy, Debug, Default)]
pub struct AccelStats {
    /// Bottom-level BVHs built (one for the meshes placed once, one per instanced mesh).
    pub blas_count: usize,
    /// Entries of the top level (instanced placements and the merged world-space BLAS).
    pub tlas_entries: usize,
    /// Triangles stored over all BLASes.
    pub stored_triangles: usize,
    /// Wall seconds of the build.
    pub build_seconds: f64,
}

/// A two-level BVH over a scene.
pub struct Accel<'s> {
    scene: &'s Scene,
    blases: Vec<Blas>,
    tlas: Option<CwBvh>,
    entries: Vec<TlasEntry>,
    xf: Vec<InstanceXf>,
    /// Build statistics.
    pub stats: AccelStats,
}

fn to_tri(a: Vec3, b: Vec3, c: Vec3) -> Triangle {
    Triangle {
        v0: a.into(),
        v1: b.into(),
        v2: c.into(),
    }
}

fn build_blas(tris: Vec<Triangle>, refs: Vec<PrimRef>, cutout: bool) -> Blas {
    let bvh = build_cwbvh_from_tris(
        &tris,
        BvhBuildParams::medium_build(),
        &mut Duration::default(),
    );
    let ordered_tris = bvh
        .primitive_indices
        .iter()
        .map(|&i| tris[i as usize])
        .collect();
    let ordered_refs = bvh
        .primitive_indices
        .iter()
        .map(|&i| refs[i as usize])
        .collect();
    Blas {
        bvh,
        tris: ordered_tris,
        refs: ordered_refs,
        cutout,
    }
}

/// Möller–Trumbore barycentrics (weights of v1 and v2) of the point where `o + t d` meets the
/// triangle's plane.
#[inline]
fn barycentrics(tri: &Triangle, o: Vec3A, d: Vec3A) -> Vec2 {
    let e1 = tri.v1 - tri.v0;
    let e2 = tri.v2 - tri.v0;
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 {
        return Vec2::ZERO;
    }
    let inv = 1.0 / det;
    let tv = o - tri.v0;
    let q = tv.cross(e1);
    Vec2::new(tv.dot(p) * inv, d.dot(q) * inv)
}

impl<'s> Accel<'s> {
    /// Builds the structure (BLASes in parallel).
    pub fn build(scene: &'s Scene) -> Self {
        use rayon::prelude::*;
        let start = std::time::Instant::now();
        let mut uses = vec![0usize; scene.meshes.len()];
        for i in &scene.instances {
            uses[i.mesh as usize] += 1;
        }
        let cut = |mesh: usize| {
            scene
                .materials
                .get(scene.meshes[mesh].material as usize)
                .is_some_and(|m| m.has_cutout())
        };
        // Merged world-space BLAS of singly placed meshes.
        let mut merged_tris = Vec::new();
        let mut merged_refs = Vec::new();
        let mut merged_cut = false;
        for (ii, inst) in scene.instances.iter().enumerate() {
            let mi = inst.mesh as usize;
            if uses[mi] != 1 {
                continue;
            }
            let m = &scene.meshes[mi];
            merged_cut |= cut(mi);
            for t in 0..m.triangles.len() {
                let [a, b, c] = m.triangle(t).map(|p| inst.transform.transform_point3(p));
                merged_tris.push(to_tri(a, b, c));
                merged_refs.push(PrimRef {
                    instance: ii as u32,
                    triangle: t as u32,
                });
            }
        }
        // Object-space BLASes of meshes placed more than once.
        let shared: Vec<usize> = (0..scene.meshes.len()).filter(|&m| uses[m] > 1).collect();
        let mut blases: Vec<Blas> = shared
            .par_iter()
            .map(|&mi| {
                let m = &scene.meshes[mi];
                let tris = (0..m.triangles.len())
                    .map(|t| {
                        let [a, b, c] = m.triangle(t);
                        to_tri(a, b, c)
                    })
                    .collect();
                let refs = (0..m.triangles.len())
                    .map(|t| PrimRef {
                        instance: u32::MAX,
                        triangle: t as u32,
                    })
                    .collect();
                build_blas(tris, refs, cut(mi))
            })
            .collect();
        let mut blas_of_mesh = vec![u32::MAX; scene.meshes.len()];
        for (k, &mi) in shared.iter().enumerate() {
            blas_of_mesh[mi] = k as u32;
        }
        let mut entries = Vec::new();
        let mut aabbs = Vec::new();
        if !merged_tris.is_empty() {
            let b = build_blas(merged_tris, merged_refs, merged_cut);
            aabbs.push(b.bvh.total_aabb);
            entries.push(TlasEntry {
                blas: blases.len() as u32,
                instance: u32::MAX,
                world_to_object: Affine3A::IDENTITY,
                identity: true,
            });
            blases.push(b);
        }
        for (ii, inst) in scene.instances.iter().enumerate() {
            let b = blas_of_mesh[inst.mesh as usize];
            if b == u32::MAX {
                continue;
            }
            let local = blases[b as usize].bvh.total_aabb;
            let mut world = Aabb::empty();
            for k in 0..8 {
                let c = Vec3A::new(
                    if k & 1 == 0 { local.min.x } else { local.max.x },
                    if k & 2 == 0 { local.min.y } else { local.max.y },
                    if k & 4 == 0 { local.min.z } else { local.max.z },
                );
                world.extend(inst.transform.transform_point3a(c));
            }
            aabbs.push(world);
            entries.push(TlasEntry {
                blas: b,
                instance: ii as u32,
                world_to_object: inst.transform.inverse(),
                identity: false,
            });
        }
        let tlas = if aabbs.is_empty() {
            None
        } else {
            Some(build_cwbvh(
                &aabbs,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            ))
        };
        let xf = scene
            .instances
            .iter()
            .map(|i| InstanceXf {
                object_to_world: i.transform,
                normal_matrix: Mat3::from(i.transform.matrix3).inverse().transpose(),
            })
            .collect();
        let stats = AccelStats {
            blas_count: blases.len(),
            tlas_entries: entries.len(),
            stored_triangles: blases.iter().map(|b| b.tris.len()).sum(),
            build_seconds: start.elapsed().as_secs_f64(),
        };
        Accel {
            scene,
            blases,
            tlas,
            entries,
            xf,
            stats,
        }
    }

    /// The scene the BVH was built over.
    pub fn scene(&self) -> &'s Scene {
        self.scene
    }

    /// Whether a candidate hit on `r` (a BLAS primitive) is cut out by its material's alpha.
    #[inline]
    fn cut_out(&self, instance: u32, triangle: u32, tri: &Triangle, ray: &BvhRay) -> bool {
        let mesh = &self.scene.meshes[self.scene.instances[instance as usize].mesh as usize];
        let Some(mat) = self.scene.materials.get(mesh.material as usize) else {
            return false;
        };
        if !mat.has_cutout() {
            return false;
        }
        if mesh.uvs.is_empty() {
            return !mat.is_opaque_at(&self.scene.textures, Vec2::ZERO);
        }
        let b = barycentrics(tri, ray.origin, ray.direction);
        let [i0, i1, i2] = mesh.triangles[triangle as usize];
        let uv = mesh.uvs[i0 as usize] * (1.0 - b.x - b.y)
            + mesh.uvs[i1 as usize] * b.x
            + mesh.uvs[i2 as usize] * b.y;
        !mat.is_opaque_at(&self.scene.textures, uv)
    }

    #[inline]
    fn object_ray(&self, e: &TlasEntry, ray: &BvhRay) -> BvhRay {
        if e.identity {
            *ray
        } else {
            BvhRay::new(
                e.world_to_object.transform_point3a(ray.origin),
                e.world_to_object.transform_vector3a(ray.direction),
                ray.tmin,
                ray.tmax,
            )
        }
    }

    /// Whether candidate `pid` of entry `e`'s BLAS is cut out.
    #[inline]
    fn entry_cut(&self, e: &TlasEntry, blas: &Blas, pid: usize, r: &BvhRay) -> bool {
        let pr = blas.refs[pid];
        let inst = if pr.instance == u32::MAX {
            e.instance
        } else {
            pr.instance
        };
        self.cut_out(inst, pr.triangle, &blas.tris[pid], r)
    }

    /// Closest hit inside one TLAS entry: (t, BLAS primitive).
    #[inline]
    fn entry_closest(&self, e: &TlasEntry, r: &BvhRay) -> Option<(f32, u32)> {
        let blas = &self.blases[e.blas as usize];
        let or = self.object_ray(e, r);
        let mut h = RayHit::none();
        let hit = blas.bvh.ray_traverse(or, &mut h, |r2, pid| {
            let t = blas.tris[pid].intersect(r2);
            if t < r2.tmax && blas.cutout && self.entry_cut(e, blas, pid, r2) {
                return f32::INFINITY;
            }
            t
        });
        hit.then_some((h.t, h.primitive_id))
    }

    /// Whether anything inside one TLAS entry blocks the ray.
    #[inline]
    fn entry_occluded(&self, e: &TlasEntry, r: &BvhRay) -> bool {
        let blas = &self.blases[e.blas as usize];
        let or = self.object_ray(e, r);
        !blas.bvh.ray_traverse_miss(or, |r2, pid| {
            let t = blas.tris[pid].intersect(r2);
            if t < r2.tmax && blas.cutout && self.entry_cut(e, blas, pid, r2) {
                return f32::INFINITY;
            }
            t
        })
    }

    /// Closest hit along the ray, honouring cut-outs.
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let tlas = self.tlas.as_ref()?;
        let world = ray.to_bvh();
        // (entry, BLAS primitive, t)
        let (entry_id, pid, t) = if self.entries.len() == 1 {
            // One entry (every single-placement mesh merged): skip the top level.
            let (t, pid) = self.entry_closest(&self.entries[0], &world)?;
            (0, pid, t)
        } else {
            let mut best: Option<(u32, u32)> = None;
            let mut top_hit = RayHit::none();
            tlas.ray_traverse(world, &mut top_hit, |r, id| {
                let entry_id = tlas.primitive_indices[id];
                match self.entry_closest(&self.entries[entry_id as usize], r) {
                    Some((t, pid)) if t < r.tmax => {
                        best = Some((entry_id, pid));
                        t
                    }
                    _ => f32::INFINITY,
                }
            });
            let (e, p) = best?;
            (e, p, top_hit.t)
        };
        let e = &self.entries[entry_id as usize];
        let blas = &self.blases[e.blas as usize];
        let pr = blas.refs[pid as usize];
        let or = self.object_ray(e, &world);
        Some(Hit {
            t,
            instance: if pr.instance == u32::MAX {
                e.instance
            } else {
                pr.instance
            },
            triangle: pr.triangle,
            bary: barycentrics(&blas.tris[pid as usize], or.origin, or.direction),
        })
    }

    /// Whether anything blocks the ray in [tmin, tmax], honouring cut-outs.
    pub fn occluded(&self, ray: &Ray) -> bool {
        let Some(tlas) = self.tlas.as_ref() else {
            return false;
        };
        let world = ray.to_bvh();
        if self.entries.len() == 1 {
            return self.entry_occluded(&self.entries[0], &world);
        }
        !tlas.ray_traverse_miss(world, |r, id| {
            if self.entry_occluded(&self.entries[tlas.primitive_indices[id] as usize], r) {
                r.tmin
            } else {
                f32::INFINITY
            }
        })
    }

    /// World-space geometry at a hit.
    pub fn surface(&self, ray: &Ray, hit: &Hit) -> SurfacePoint {
        let inst = &self.scene.instances[hit.instance as usize];
        let mesh = &self.scene.meshes[inst.mesh as usize];
        let xf = &self.xf[hit.instance as usize];
        let [i0, i1, i2] = mesh.triangles[hit.triangle as usize];
        let (b1, b2) = (hit.bary.x, hit.bary.y);
        let b0 = 1.0 - b1 - b2;
        let [a, b, c] = mesh.triangle(hit.triangle as usize);
        let ng_obj = (b - a).cross(c - a);
        let ng = (xf.normal_matrix * ng_obj).normalize_or(Vec3::Z);
        let ns = if mesh.normals.is_empty() {
            ng
        } else {
            let n = mesh.normals[i0 as usize] * b0
                + mesh.normals[i1 as usize] * b1
                + mesh.normals[i2 as usize] * b2;
            (xf.normal_matrix * n).try_normalize().unwrap_or(ng)
        };
        let uv = if mesh.uvs.is_empty() {
            Vec2::ZERO
        } else {
            mesh.uvs[i0 as usize] * b0 + mesh.uvs[i1 as usize] * b1 + mesh.uvs[i2 as usize] * b2
        };
        // The hit point from the interpolated vertices is more accurate than o + t d far away.
        let p_obj = a * b0 + b * b1 + c * b2;
        let p = xf.object_to_world.transform_point3(p_obj);
        let p = if p.is_finite() { p } else { ray.at(hit.t) };
        SurfacePoint {
            p,
            ng,
            ns,
            uv,
            material: mesh.material,
        }
    }
}

/// Offset a ray origin off a surface along the geometric normal, on the side of `dir`, scaled to
/// the magnitude of the position (f32 rounding grows with it).
#[inline]
pub fn offset_origin(p: Vec3, ng: Vec3, dir: Vec3) -> Vec3 {
    let eps = 1e-5 * (1.0 + p.abs().max_element());
    let n = if ng.dot(dir) >= 0.0 { ng } else { -ng };
    p + n * eps
}
