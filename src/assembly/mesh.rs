//! An assembly as meshes: what the reference renderer draws and what `inspect` counts.
//!
//! Each asset's source is imported once; [`scene`] appends its meshes, materials and textures
//! once to one [`Scene`] and places them by one [`crate::scene::Instance`] per (manifest
//! instance, asset placement). [`crate::trace::Accel`] then stores every mesh placed more than
//! once a single time in object space, under a top-level BVH over the placements' bounds: the
//! two-level BVH, with no triangle copied per instance.

use rayon::prelude::*;

use super::manifest::Manifest;
use crate::import::{self, ImportError, ImportOptions};
use crate::scene::{Instance, Scene};

/// Why an assembly's meshes could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// A source is missing.
    #[error(transparent)]
    Manifest(#[from] super::ManifestError),
    /// A source failed to import.
    #[error("asset '{asset}': {source}")]
    Import {
        /// The asset id.
        asset: String,
        /// Why.
        #[source]
        source: ImportError,
    },
}

/// Imports every asset's source once, in parallel (index as [`Manifest::assets`]).
pub fn load_sources(m: &Manifest, options: ImportOptions) -> Result<Vec<Scene>, MeshError> {
    m.require_sources()?;
    m.assets
        .par_iter()
        .map(|a| {
            import::load(&a.source, options).map_err(|source| MeshError::Import {
                asset: a.id.clone(),
                source,
            })
        })
        .collect()
}

/// The whole assembly as one scene: each asset's meshes stored once, placed by every instance.
pub fn scene(m: &Manifest, sources: &[Scene]) -> Scene {
    let mut out = Scene::default();
    // First mesh of each asset in `out`.
    let mut mesh0 = Vec::with_capacity(sources.len());
    for (a, src) in m.assets.iter().zip(sources) {
        let tex0 = out.textures.len() as u32;
        let mat0 = out.materials.len() as u32;
        mesh0.push(out.meshes.len() as u32);
        out.textures.extend(src.textures.iter().cloned());
        for mat in &src.materials {
            let mut mat = mat.clone();
            mat.offset_textures(tex0);
            out.materials.push(mat);
        }
        for mesh in &src.meshes {
            let mut mesh = mesh.clone();
            mesh.material += mat0;
            out.meshes.push(mesh);
        }
        out.warnings.extend(
            src.warnings
                .iter()
                .map(|w| format!("asset '{}': {w}", a.id)),
        );
    }
    let placements: usize = (0..m.instance_count())
        .map(|i| sources[m.asset_of(i)].instances.len())
        .sum();
    out.instances.reserve(placements);
    for i in 0..m.instance_count() {
        let a = m.asset_of(i);
        let xf = m.transform(i);
        for p in &sources[a].instances {
            out.instances.push(Instance {
                mesh: p.mesh + mesh0[a],
                transform: xf * p.transform,
            });
        }
    }
    out.source = Some(m.path.clone());
    out
}

/// What an assembly holds, for `aggtool inspect MANIFEST`.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Summary {
    /// Number of assets.
    pub assets: usize,
    /// Number of instances.
    pub instances: usize,
    /// Bytes the instances take in memory (a 3×4 transform and an index each).
    pub instance_bytes: usize,
    /// Per asset.
    pub per_asset: Vec<AssetSummary>,
    /// Bytes of the aggregates present, each counted once.
    pub aggregate_bytes: u64,
    /// Triangles stored: each asset's meshes once (`None` when a source is missing).
    pub unique_triangles: Option<u64>,
    /// Triangles placed in the world: each asset's placed triangles times its instances.
    pub instanced_triangles: Option<u64>,
}

/// One asset of a [`Summary`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct AssetSummary {
    /// Its id.
    pub id: String,
    /// The source (resolved).
    pub source: String,
    /// Whether the source exists.
    pub source_present: bool,
    /// The aggregate (resolved).
    pub aggregate: String,
    /// Its size, when present.
    pub aggregate_bytes: Option<u64>,
    /// Instances of it.
    pub instances: usize,
    /// Triangles of its meshes (each once), when its source imported.
    pub unique_triangles: Option<u64>,
    /// Triangles it places (its own instancing counted), when its source imported.
    pub placed_triangles: Option<u64>,
}

/// Summarises an assembly. With `import_sources`, every source present is imported to count
/// triangles (an import failure is an error naming the asset).
pub fn summary(m: &Manifest, import_sources: bool) -> Result<Summary, MeshError> {
    let counts = m.instances_per_asset();
    let per_asset: Vec<AssetSummary> = m
        .assets
        .par_iter()
        .zip(counts.par_iter())
        .map(|(a, &n)| {
            let source_present = a.source.is_file();
            let tris = if import_sources && source_present {
                let s = import::load(&a.source, ImportOptions::default()).map_err(|source| {
                    MeshError::Import {
                        asset: a.id.clone(),
                        source,
                    }
                })?;
                Some((
                    s.unique_triangle_count() as u64,
                    s.instanced_triangle_count() as u64,
                ))
            } else {
                None
            };
            Ok(AssetSummary {
                id: a.id.clone(),
                source: a.source.display().to_string(),
                source_present,
                aggregate: a.aggregate.display().to_string(),
                aggregate_bytes: std::fs::metadata(&a.aggregate)
                    .ok()
                    .filter(|md| md.is_file())
                    .map(|md| md.len()),
                instances: n,
                unique_triangles: tris.map(|t| t.0),
                placed_triangles: tris.map(|t| t.1),
            })
        })
        .collect::<Result<_, MeshError>>()?;
    let all =
        |f: &dyn Fn(&AssetSummary) -> Option<u64>| -> Option<u64> { per_asset.iter().map(f).sum() };
    Ok(Summary {
        assets: m.assets.len(),
        instances: m.instance_count(),
        instance_bytes: m.instance_bytes(),
        aggregate_bytes: per_asset.iter().filter_map(|a| a.aggregate_bytes).sum(),
        unique_triangles: all(&|a| a.unique_triangles),
        instanced_triangles: all(&|a| a.placed_triangles.map(|t| t * a.instances as u64)),
        per_asset,
    })
}

/// What a render command reads as meshes: an asset file, or an assembly manifest (each source
/// imported once, [`scene`]); with a line saying what it is ("PATH: 3 meshes, …").
pub fn load_any(path: &std::path::Path, options: ImportOptions) -> anyhow::Result<(Scene, String)> {
    let scene = if super::is_manifest(path) {
        let m = Manifest::load(path)?;
        let sources = load_sources(&m, options)?;
        scene(&m, &sources)
    } else {
        import::load(path, options)?
    };
    let line = format!("{}: {}", path.display(), scene.summary());
    Ok((scene, line))
}
