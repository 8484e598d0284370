//! `aggtool inspect`: what an `.agg` file holds, as one [`Summary`] that `inspect --json`
//! serialises, `inspect` prints as text, and the Python module's `Scene.inspect()` returns.
//!
//! The settings are the bake's own [`BakeSettings`] (decoded from the file's record by
//! [`BakeSettings::from_recorded`]) with the one thing a reader needs and a bake does not
//! choose, the AIV weighting of the format version, so that `inspect --json` and
//! `convert --report` name every setting alike.

use std::path::Path;

use serde::Serialize;

use crate::bake::BakeSettings;
use crate::format::effects::{effect_lines, EffectLine};
use crate::format::encode::{ComponentBytes, Counts};
use crate::format::{Aggregate, AivWeighting};

/// The settings a file was baked with, as [`BakeSettings`] names them.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct InspectedSettings {
    /// The bake's settings.
    #[serde(flatten)]
    pub bake: BakeSettings,
    /// What the AIV averages over (area in format 1.0–1.1, projected area from 1.2 on).
    pub aiv_weighting: AivWeighting,
}

/// One level of a file.
#[derive(Clone, Debug, Serialize)]
pub struct LevelSummary {
    /// Resolution (voxels per axis).
    pub res: u32,
    /// Non-empty voxels stored.
    pub voxels: u64,
    /// Boundary faces stored (with an ABV map).
    pub faces: u64,
    /// Blocks of voxels.
    pub voxel_blocks: usize,
    /// Blocks of faces.
    pub face_blocks: usize,
    /// Bytes stored in the file (compressed blocks as stored).
    pub bytes: u64,
    /// Bytes of the blocks once inflated (format 1.5).
    pub inflated_bytes: u64,
    /// `inflated_bytes / bytes` (1 when nothing is compressed).
    pub compression_ratio: f64,
    /// Bytes per component (payloads, without FlatBuffers headers and padding).
    pub components: ComponentBytes,
    /// Whether the level uses format 1.4's quantized layout.
    pub quantized: bool,
    /// What the level stores, counted by the bake (effects per voxel and face).
    pub counts: Counts,
}

/// What a file holds: header, provenance, bounds, tables, settings, levels and effects.
#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    /// The path it was read from.
    pub file: String,
    /// Format version, "MAJOR.MINOR".
    pub format: String,
    /// File size in bytes.
    pub bytes: u64,
    /// The program that wrote it, e.g. "aggtool 0.1.0".
    pub generator: String,
    /// The source asset's file name.
    pub source: String,
    /// The source asset's bounds (min, max).
    pub bounds: [[f32; 3]; 2],
    /// Version of the ABSDF tables the file must be evaluated with.
    pub tables_version: u32,
    /// CRC-32 of the tables' bytes.
    pub tables_crc32: u32,
    /// The bake's settings.
    pub settings: InspectedSettings,
    /// Per level, finest first.
    pub levels: Vec<LevelSummary>,
    /// Every effect, kept or dropped, with its reason and per-level counts.
    pub effects: Vec<EffectLine>,
    /// The minor format version (the layout line of `inspect` applies from 1.4 on).
    #[serde(skip)]
    pub minor: u16,
}

impl Summary {
    /// Whether the file's tables are the ones this build embeds.
    pub fn same_tables(&self) -> bool {
        self.tables_crc32 == crc32fast::hash(crate::tables::EMBEDDED)
    }
}

/// The summary of an open file (`file`: the path to report).
pub fn summary(agg: &Aggregate, file: &Path) -> Summary {
    let h = agg.header();
    let s = agg.settings();
    let counts: Vec<(u32, Counts)> = (0..agg.level_count())
        .map(|l| (agg.grid(l).res, agg.counts(l)))
        .collect();
    let levels = (0..agg.level_count())
        .map(|l| {
            let (vb, fb) = agg.level_bytes(l);
            let (voxel_blocks, face_blocks) = agg.block_counts(l);
            let (components, quantized) = agg.component_bytes(l);
            let (stored, inflated) = agg.stored_and_inflated_bytes(l);
            LevelSummary {
                res: counts[l].0,
                voxels: counts[l].1.voxels,
                faces: counts[l].1.faces,
                voxel_blocks,
                face_blocks,
                bytes: vb + fb,
                inflated_bytes: inflated,
                compression_ratio: if stored > 0 {
                    inflated as f64 / stored as f64
                } else {
                    1.0
                },
                components,
                quantized,
                counts: counts[l].1,
            }
        })
        .collect();
    let (lo, hi) = agg.bounds();
    let (tables_version, tables_crc32) = agg.tables();
    Summary {
        file: file.display().to_string(),
        format: format!("{}.{}", h.major, h.minor),
        bytes: h.file_size,
        generator: agg.generator().to_string(),
        source: agg.source().to_string(),
        bounds: [lo.to_array(), hi.to_array()],
        tables_version,
        tables_crc32,
        settings: InspectedSettings {
            bake: BakeSettings::from_recorded(s),
            aiv_weighting: s.aiv_weighting,
        },
        levels,
        effects: effect_lines(&counts, s.keep_all_effects),
        minor: h.minor,
    }
}

/// Opens `file` (verifying every checksum and structure, as `Aggregate::open` does) and
/// summarises it.
pub fn inspect(file: &Path) -> anyhow::Result<Summary> {
    use anyhow::Context;
    let agg = Aggregate::open(file).with_context(|| format!("cannot read {}", file.display()))?;
    Ok(summary(&agg, file))
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let sm = self;
        let s = &sm.settings.bake;
        writeln!(
            f,
            "{}: aggtool format {}, {} bytes, written by {}",
            sm.file, sm.format, sm.bytes, sm.generator
        )?;
        writeln!(
            f,
            "source: {}; bounds {:?} to {:?}; tables v{} (crc32 {:08x}{})",
            sm.source,
            sm.bounds[0],
            sm.bounds[1],
            sm.tables_version,
            sm.tables_crc32,
            if sm.same_tables() {
                ", same as this build"
            } else {
                ", NOT the tables of this build"
            }
        )?;
        writeln!(
            f,
            "settings: max-res {} min-res {} samples {} (max {}) aiv {}² × {} rays/sample ({}-weighted{}), abv {}² × {} rays/cell{}, ndf-lobes {}, moment-res {}, keep {} energy {}{}{}",
            s.max_res, s.min_res, s.samples, s.max_samples, s.aiv_res, s.aiv_rays,
            if sm.settings.aiv_weighting == AivWeighting::ProjectedArea { "projected-area" } else { "area" },
            match s.aiv_min_rays {
                0 => ", cells pooled per voxel by cross-validation".to_string(),
                1 => String::new(),
                n => format!(", cells pooled to at least {n} rays"),
            },
            s.abv_res, s.abv_rays,
            match s.abv_full_res {
                0 => String::new(),
                n => format!(" up to {n}³ (per block of (res/{n})² cells above)"),
            } + if s.abv_windows { ", centred windows" } else { "" },
            s.ndf_lobes, s.moment_res, s.keep, s.energy,
            if s.allocates_per_block() { " (at that error, allocated per block)" } else { "" },
            if s.keep_all_effects { ", keep-all-effects" } else { "" }
        )?;
        if s.shading_res() != 0 {
            writeln!(
                f,
                "visibility levels (1.7): the levels finer than {0}³ keep no interior visibility \
                 of their own; their voxels read the AIV of the {0}³ voxels",
                s.shading_res()
            )?;
        }
        if sm.minor >= 4 {
            writeln!(
                f,
                "layout: {}{}",
                if s.lossless {
                    "lossless (the 1.0–1.3 floats)"
                } else {
                    "quantized (1.4)"
                },
                match s.compression {
                    0 => String::new(),
                    z => format!(", blocks compressed (zstd level {z}, 1.5)"),
                }
            )?;
        }
        writeln!(
            f,
            "{:>6} {:>10} {:>10} {:>7} {:>7} {:>12} {:>12} {:>6}",
            "level", "voxels", "faces", "vblocks", "fblocks", "bytes", "inflated", "ratio"
        )?;
        for l in &sm.levels {
            writeln!(
                f,
                "{:>5}³ {:>10} {:>10} {:>7} {:>7} {:>12} {:>12} {:>5.2}×",
                l.res,
                l.voxels,
                l.faces,
                l.voxel_blocks,
                l.face_blocks,
                l.bytes,
                l.inflated_bytes,
                l.compression_ratio
            )?;
        }
        writeln!(
            f,
            "bytes per component (payloads, without FlatBuffers headers and padding):"
        )?;
        writeln!(
            f,
            "{:>6} {:>10} {:>10} {:>10} {:>11} {:>10} {:>11} {:>9}  layout",
            "level", "records", "lobes", "moments", "AIV nodes", "faces", "ABV nodes", "other"
        )?;
        for l in &sm.levels {
            let c = &l.components;
            writeln!(
                f,
                "{:>5}³ {:>10} {:>10} {:>10} {:>11} {:>10} {:>11} {:>9}  {}",
                l.res,
                c.voxels,
                c.lobes,
                c.moments + c.dielectric_moments,
                c.aiv_nodes,
                c.faces,
                c.abv_nodes,
                c.keys + c.exposure,
                if l.quantized { "quantized" } else { "float" }
            )?;
        }
        writeln!(f, "effects:")?;
        write!(f, "{}", crate::format::effects::format_effects(&sm.effects))
    }
}

/// What `aggtool inspect` reports: an aggregate's [`Summary`], or an assembly's.
#[derive(Clone, Debug, Serialize)]
#[serde(untagged)]
pub enum Inspection {
    /// An `.agg` file.
    Aggregate(Summary),
    /// An assembly manifest (`.json`).
    Assembly(AssemblySummary),
}

/// An assembly manifest's summary with its path.
#[derive(Clone, Debug, Serialize)]
pub struct AssemblySummary {
    /// The manifest.
    #[serde(skip)]
    pub file: String,
    /// What it holds.
    #[serde(flatten)]
    pub summary: crate::assembly::mesh::Summary,
}

/// Inspects an `.agg` file or, for a `.json` path, an assembly manifest (its sources imported
/// to count triangles).
pub fn inspect_file(file: &Path) -> anyhow::Result<Inspection> {
    if crate::assembly::is_manifest(file) {
        let m = crate::assembly::Manifest::load(file)?;
        Ok(Inspection::Assembly(AssemblySummary {
            file: file.display().to_string(),
            summary: crate::assembly::mesh::summary(&m, true)?,
        }))
    } else {
        Ok(Inspection::Aggregate(inspect(file)?))
    }
}

impl std::fmt::Display for Inspection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Inspection::Aggregate(s) => s.fmt(f),
            Inspection::Assembly(a) => a.fmt(f),
        }
    }
}

impl std::fmt::Display for AssemblySummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use crate::report::mib;
        let s = &self.summary;
        let opt = |v: Option<u64>| v.map_or("?".to_string(), |v| v.to_string());
        writeln!(
            f,
            "{}: {} assets, {} instances ({} in memory)",
            self.file,
            s.assets,
            s.instances,
            mib(s.instance_bytes as u64)
        )?;
        for a in &s.per_asset {
            writeln!(
                f,
                "asset '{}': {} instances, source {}{}, aggregate {} ({}), {} triangles ({} placed)",
                a.id,
                a.instances,
                a.source,
                if a.source_present { "" } else { " (missing)" },
                a.aggregate,
                a.aggregate_bytes.map_or("missing".into(), mib),
                opt(a.unique_triangles),
                opt(a.placed_triangles),
            )?;
        }
        write!(
            f,
            "aggregates: {} present; triangles: {} unique, {} instanced",
            mib(s.aggregate_bytes),
            opt(s.unique_triangles),
            opt(s.instanced_triangles)
        )
    }
}

/// What `aggtool info` reports of an asset file: counts, bounds, materials, warnings.
#[derive(Clone, Debug, Serialize)]
pub struct AssetInfo {
    /// The asset.
    #[serde(skip)]
    pub file: String,
    /// Meshes (each stored once).
    pub meshes: usize,
    /// Instances of the meshes.
    pub instances: usize,
    /// Triangles, each mesh once.
    pub triangles: u64,
    /// Triangles placed, instancing counted.
    pub instanced_triangles: u64,
    /// Each mesh once, 32 B a vertex and 12 a triangle: what the quality and compression
    /// studies weigh an aggregate against.
    pub geometry_bytes: u64,
    /// World bounds (min, max).
    pub bounds: [[f32; 3]; 2],
    /// The materials.
    pub materials: Vec<MaterialInfo>,
    /// Number of textures.
    pub textures: usize,
    /// Import warnings.
    pub warnings: Vec<String>,
    /// One line: meshes, instances, triangles, materials, textures.
    #[serde(skip)]
    pub summary: String,
}

/// One material of an [`AssetInfo`].
#[derive(Clone, Debug, Serialize)]
pub struct MaterialInfo {
    /// Its name.
    pub name: String,
    /// Linear base colour and alpha.
    pub base_color: [f32; 4],
    /// Metallic factor.
    pub metallic: f32,
    /// Perceptual roughness.
    pub roughness: f32,
    /// KHR_materials_specular factor.
    pub specular_factor: f32,
    /// Whether a base-colour texture is bound.
    pub textured: bool,
    /// Whether it cuts out (alpha mask or blend).
    pub cutout: bool,
}

/// Imports `file` and reports what it holds.
pub fn asset_info(file: &Path) -> anyhow::Result<AssetInfo> {
    let scene = crate::import::load(file, crate::import::ImportOptions { strict: false })?;
    let (lo, hi) = scene.bounds();
    Ok(AssetInfo {
        file: file.display().to_string(),
        meshes: scene.meshes.len(),
        instances: scene.instances.len(),
        triangles: scene.unique_triangle_count() as u64,
        instanced_triangles: scene.instanced_triangle_count() as u64,
        geometry_bytes: crate::eval::simplify::scene_bytes(&scene) as u64,
        bounds: [lo.to_array(), hi.to_array()],
        materials: scene
            .materials
            .iter()
            .map(|m| MaterialInfo {
                name: m.name.clone(),
                base_color: m.base_color.to_array(),
                metallic: m.metallic,
                roughness: m.perceptual_roughness,
                specular_factor: m.specular_factor,
                textured: m.base_color_texture.is_some(),
                cutout: m.has_cutout(),
            })
            .collect(),
        textures: scene.textures.len(),
        warnings: scene.warnings.clone(),
        summary: scene.summary(),
    })
}

impl std::fmt::Display for AssetInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for w in &self.warnings {
            writeln!(f, "warning: {w}")?;
        }
        writeln!(f, "{}: {}", self.file, self.summary)?;
        let [lo, hi] = self.bounds;
        write!(
            f,
            "bounds: {} .. {}",
            glam::Vec3::from(lo),
            glam::Vec3::from(hi)
        )?;
        for m in &self.materials {
            write!(
                f,
                "\nmaterial '{}': base {:?} metallic {:.2} roughness {:.2} specular {:.2}{}{}",
                m.name,
                m.base_color,
                m.metallic,
                m.roughness,
                m.specular_factor,
                if m.textured { " textured" } else { "" },
                if m.cutout { " cut-out" } else { "" }
            )?;
        }
        Ok(())
    }
}
