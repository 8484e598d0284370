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
