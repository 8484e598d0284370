//! The one scene representation that every importer produces and every later stage (ray
//! tracing, reference rendering, baking) consumes.
//!
//! Geometry is stored once per [`Mesh`] and placed by [`Instance`]s, so that a mesh used by
//! several glTF nodes (or by `EXT_mesh_gpu_instancing`) is never copied.

pub mod export;
pub mod flatten;
mod material;
mod texture;

use std::path::PathBuf;

use glam::{Affine3A, Vec2, Vec3};

pub use material::{AlphaMode, Material, SurfaceParams, TextureRef, UvTransform};
pub use texture::{Texture, WrapMode};

/// Triangle geometry with one material. Normals and UVs are per vertex; either may be empty.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// Where it came from, for messages: `"mesh 'Leaves' primitive 0"`.
    pub name: String,
    /// Object-space vertex positions.
    pub positions: Vec<Vec3>,
    /// Shading normals (unit length), or empty when the asset has none: geometric normals are
    /// used then.
    pub normals: Vec<Vec3>,
    /// First texture coordinate set, or empty.
    pub uvs: Vec<Vec2>,
    /// Triangles as three indices into `positions`.
    pub triangles: Vec<[u32; 3]>,
    /// Index into [`Scene::materials`].
    pub material: u32,
}

impl Mesh {
    /// Object-space bounds (min, max); (inf, -inf) when empty.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), &p| (lo.min(p), hi.max(p)),
        )
    }

    /// Vertices of triangle `t`.
    #[inline]
    pub fn triangle(&self, t: usize) -> [Vec3; 3] {
        let [a, b, c] = self.triangles[t];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// Total surface area in object space.
    pub fn area(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| {
                let [a, b, c] = self.triangle(t);
                0.5 * (b - a).cross(c - a).length() as f64
            })
            .sum()
    }
}

/// A placement of a mesh in the world.
#[derive(Clone, Copy, Debug)]
pub struct Instance {
    /// Index into [`Scene::meshes`].
    pub mesh: u32,
    /// Object to world.
    pub transform: Affine3A,
}

/// An imported scene.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    /// The meshes, each stored once.
    pub meshes: Vec<Mesh>,
    /// Their placements in the world.
    pub instances: Vec<Instance>,
    /// The materials meshes refer to.
    pub materials: Vec<Material>,
    /// The textures materials refer to.
    pub textures: Vec<Texture>,
    /// Non-fatal problems met while importing (skipped elements, ignored features).
    pub warnings: Vec<String>,
    /// The file the scene was read from, if any.
    pub source: Option<PathBuf>,
}

impl Scene {
    /// Triangles stored (each mesh counted once).
    pub fn unique_triangle_count(&self) -> usize {
        self.meshes.iter().map(|m| m.triangles.len()).sum()
    }

    /// Triangles placed in the world (each instance counted).
    pub fn instanced_triangle_count(&self) -> usize {
        self.instances
            .iter()
            .map(|i| self.meshes[i.mesh as usize].triangles.len())
            .sum()
    }

    /// World-space bounds of every instance (exact: every vertex is transformed).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for inst in &self.instances {
            for &p in &self.meshes[inst.mesh as usize].positions {
                let w = inst.transform.transform_point3(p);
                lo = lo.min(w);
                hi = hi.max(w);
            }
        }
        (lo, hi)
    }

    /// World-space bounding sphere (centre of the bounds, radius to the farthest corner).
    pub fn bounding_sphere(&self) -> (Vec3, f32) {
        let (lo, hi) = self.bounds();
        if !(lo.x <= hi.x) {
            return (Vec3::ZERO, 1.0);
        }
        let c = 0.5 * (lo + hi);
        (c, (0.5 * (hi - lo).length()).max(1e-6))
    }

    /// Total world-space surface area of all instances.
    pub fn world_area(&self) -> f64 {
        self.instances
            .iter()
            .map(|inst| {
                let m = &self.meshes[inst.mesh as usize];
                (0..m.triangles.len())
                    .map(|t| {
                        let [a, b, c] = m.triangle(t).map(|p| inst.transform.transform_point3(p));
                        0.5 * (b - a).cross(c - a).length() as f64
                    })
                    .sum::<f64>()
            })
            .sum()
    }

    /// Appends `other`'s content (materials, textures, meshes re-indexed) placed by `transform`.
    pub fn append(&mut self, other: &Scene, transform: Affine3A) {
        let tex0 = self.textures.len() as u32;
        let mat0 = self.materials.len() as u32;
        let mesh0 = self.meshes.len() as u32;
        self.textures.extend(other.textures.iter().cloned());
        for m in &other.materials {
            let mut m = m.clone();
            m.offset_textures(tex0);
            self.materials.push(m);
        }
        for m in &other.meshes {
            let mut m = m.clone();
            m.material += mat0;
            self.meshes.push(m);
        }
        for i in &other.instances {
            self.instances.push(Instance {
                mesh: i.mesh + mesh0,
                transform: transform * i.transform,
            });
        }
        self.warnings.extend(other.warnings.iter().cloned());
    }

    /// A one-line summary: `"3 meshes, 5 instances, 1200 triangles (2400 instanced), 2 materials"`.
    pub fn summary(&self) -> String {
        format!(
            "{} meshes, {} instances, {} triangles ({} instanced), {} materials, {} textures",
            self.meshes.len(),
            self.instances.len(),
            self.unique_triangle_count(),
            self.instanced_triangle_count(),
            self.materials.len(),
            self.textures.len()
        )
    }
}
