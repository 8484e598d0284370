//! The hybrid representation of an assembly: an instance seen finer than its aggregate's
//! finest level is drawn from its mesh (issue 18, item 3).
//!
//! Each asset's source is imported and its two-level BVH ([`Accel`]) built the first time a
//! cone needs it as a mesh ([`LazyMesh::get`]), once, whatever the number of threads asking:
//! assets that never go to mesh are never read.

use std::path::Path;
use std::sync::OnceLock;

use glam::Vec3;

use crate::import::{self, ImportOptions};
use crate::scene::Scene;
use crate::trace::{Accel, Hit, Ray};

/// How an asset's instances are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Representation {
    /// From the aggregate only (what `aggtool render MANIFEST --no-mesh` does, and what a
    /// host opening an assembly gets unless it asks otherwise).
    #[default]
    Aggregate,
    /// From the mesh where the cone's footprint on the instance is finer than the aggregate's
    /// finest voxel, from the aggregate elsewhere (`aggtool render MANIFEST`'s default).
    Hybrid,
    /// From the mesh always (for tests and comparisons).
    Mesh,
}

/// An asset's mesh ready for ray tracing, in the asset's own space.
pub struct MeshAsset {
    /// Borrows `scene`, which is boxed and never moved or dropped before it (field order).
    accel: Accel<'static>,
    scene: Box<Scene>,
}

impl MeshAsset {
    /// Imports `source` and builds its BVH.
    fn load(source: &Path) -> Result<MeshAsset, String> {
        let scene = Box::new(
            import::load(source, ImportOptions::default())
                .map_err(|e| format!("cannot import {}: {e}", source.display()))?,
        );
        let accel = Accel::build(&scene);
        // SAFETY: `accel` borrows the boxed scene, whose heap address is stable; the box is
        // owned by the same struct, never mutated, and dropped after `accel` (declaration
        // order). The lifetime is narrowed back to `&self` by the accessors.
        let accel = unsafe { std::mem::transmute::<Accel<'_>, Accel<'static>>(accel) };
        Ok(MeshAsset { accel, scene })
    }

    /// The imported scene (materials and textures for shading).
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The BVH.
    pub fn accel(&self) -> &Accel<'_> {
        &self.accel
    }

    /// Closest hit of a ray in the asset's space.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        self.accel.intersect(ray)
    }

    /// Whether anything blocks a ray in the asset's space.
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3) -> bool {
        self.blocks(&Ray::new(origin, dir))
    }

    /// Whether anything blocks `ray` within its interval (any hit: what
    /// [`MeshAsset::intersect`] finding one says, without looking for the closest).
    #[inline]
    pub fn blocks(&self, ray: &Ray) -> bool {
        self.accel.occluded(ray)
    }
}

/// An asset's mesh, loaded on first use.
#[derive(Default)]
pub struct LazyMesh {
    slot: OnceLock<Result<MeshAsset, String>>,
}

impl LazyMesh {
    /// The mesh, imported now if it was not; `None` when it failed (see [`Self::error`]).
    ///
    /// The import runs on a thread of its own with a pool of its own: the caller is usually a
    /// worker of the image loop's pool, and the import and BVH build use rayon; run on that
    /// pool, a worker waiting for them could pick up a pixel that asks for this same mesh and
    /// re-enter the initialisation. Other threads asking meanwhile wait for the one import.
    pub fn get(&self, source: &Path) -> Option<&MeshAsset> {
        self.slot
            .get_or_init(|| {
                std::thread::scope(|s| {
                    s.spawn(|| {
                        let pool = rayon::ThreadPoolBuilder::new()
                            .build()
                            .map_err(|e| format!("cannot start threads: {e}"))?;
                        pool.install(|| MeshAsset::load(source))
                    })
                    .join()
                    .unwrap_or_else(|_| Err(format!("importing {} panicked", source.display())))
                })
            })
            .as_ref()
            .ok()
    }

    /// Whether it was loaded (successfully).
    pub fn loaded(&self) -> bool {
        matches!(self.slot.get(), Some(Ok(_)))
    }

    /// The loaded mesh, without loading it.
    pub fn peek(&self) -> Option<&MeshAsset> {
        self.slot.get().and_then(|r| r.as_ref().ok())
    }

    /// Why loading failed, if it did.
    pub fn error(&self) -> Option<&str> {
        match self.slot.get() {
            Some(Err(e)) => Some(e),
            _ => None,
        }
    }
}
