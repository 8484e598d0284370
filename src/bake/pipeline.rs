//! The streaming bake of a whole asset into an `.agg` file: level by level, finest first, and
//! within a level block by block (at most [`BLOCK_VOXELS`] voxels or [`BLOCK_FACES`] faces in
//! memory at once, baked in parallel with rayon). Per-voxel seeds come from Morton keys, so
//! the bytes do not depend on the thread count.

use std::path::Path;
use std::time::Instant;

use rayon::prelude::*;

use super::boundary_visibility::ABV_BANDWIDTHS;
use super::level::{
    bake_face, bake_voxel, primitive_level, sorted_boundary_faces, voxel_primitive, VoxelCost,
};
use super::rate::{self, PendingLevel, RateReport};
use super::sampling::pieces_by_voxel;
use super::visibility::AIV_BANDWIDTHS;
use super::BakeSettings;
use crate::format::effects::{effect_lines, EffectLine};
use crate::format::encode::{self, ComponentBytes, Counts, IndexEntry, LevelEntry};
use crate::format::part::{BlockKind, PartLevel, PartMeta, PartWriter, Shard};
use crate::format::{encode_voxel_keys, VoxelData, Writer};
use crate::scene::Scene;
use crate::spatial::{Ellipsoid, Grid};
use crate::trace::Accel;
use crate::util::{Progress, StageCounter};

/// Voxels per block: about 1 MiB of records, lobes, moments and trees inflated, the unit the
/// runtime's block cache prepares and evicts. 4096 made a block 4 MiB prepared, and a cache
/// of a few blocks per thread thrashed: the maple's 64³ aggregate at 256², 4 spp, under an 8 MiB
/// budget took 134.6 s with 4096 and 1.56 s with 1024 (the same pixels; default budget 0.17 /
/// 0.16 s), for a file 1.8% larger (Zstandard frames of a quarter of the size).
pub const BLOCK_VOXELS: usize = 1024;
/// Faces per block (about as many bytes as a voxel block).
pub const BLOCK_FACES: usize = 2048;

/// Wall-clock seconds per stage.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct StageSeconds {
    /// Voxelizing the scene (exact per-voxel areas).
    pub voxelize: f64,
    /// Sampling, statistics and visibility of the voxels.
    pub voxels: f64,
    /// Boundary visibility of the faces.
    pub faces: f64,
    /// Encoding, compressing and writing blocks.
    pub write: f64,
}

/// What one level cost and holds.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LevelReport {
    /// Resolution of the level (voxels a side).
    pub res: u32,
    /// Non-empty voxels.
    pub voxels: u64,
    /// Boundary faces (with an ABV map).
    pub faces: u64,
    /// Non-empty voxels over res³.
    pub occupancy: f64,
    /// Surface samples per voxel at this level.
    pub samples_per_voxel: u32,
    /// Boundary-visibility rays traced from each face (fewer above `abv_full_res`).
    pub abv_rays_per_face: u32,
    /// Wall-clock seconds per stage.
    pub seconds: StageSeconds,
    /// CPU seconds (summed over threads) of sampling and statistics.
    pub cpu_statistics: f64,
    /// CPU seconds of the AIV rays.
    pub cpu_aiv: f64,
    /// Interior-visibility rays traced.
    pub aiv_rays: u64,
    /// Voxels per AIV bandwidth: `aiv_bandwidth[i]` voxels gather each cell's rays as
    /// [`AIV_BANDWIDTHS`]`[i]` does (chosen by cross-validation, or the setting).
    pub aiv_bandwidth: [u64; AIV_BANDWIDTHS.len()],
    /// Boundary-visibility rays traced.
    pub abv_rays: u64,
    /// Faces per ABV bandwidth: `abv_bandwidth[i]` faces gather each cell's P⁺ rays as
    /// [`ABV_BANDWIDTHS`]`[i]` does (chosen by cross-validation).
    pub abv_bandwidth: [u64; ABV_BANDWIDTHS.len()],
    /// Bytes of the level's blocks in the file.
    pub bytes: u64,
    /// What the level stores (voxels, faces, effects), counted while encoding.
    pub counts: Counts,
}

impl LevelReport {
    /// "1 ray 23%, 2 rays 54%, …": the share of the level's voxels at each AIV bandwidth
    /// (those with none omitted).
    pub fn aiv_bandwidth_summary(&self) -> String {
        let names = AIV_BANDWIDTHS.map(|b| b.to_string());
        bandwidth_summary(&names, &self.aiv_bandwidth)
    }

    /// The same for the faces' ABV bandwidths.
    pub fn abv_bandwidth_summary(&self) -> String {
        let names = ABV_BANDWIDTHS.map(|b| b.to_string());
        bandwidth_summary(&names, &self.abv_bandwidth)
    }
}

/// "1 ray 23%, 2 rays 54%, …" of `counts[i]` items at bandwidth `candidates[i]`.
fn bandwidth_summary(names: &[String], counts: &[u64]) -> String {
    let total: u64 = counts.iter().sum();
    names
        .iter()
        .zip(counts)
        .filter(|(_, &n)| n > 0)
        .map(|(k, &n)| format!("{k} {:.0}%", 100.0 * n as f64 / total as f64))
        .collect::<Vec<_>>()
        .join(", ")
}

/// What a bake did, for the `stats:` lines and `--report`.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BakeReport {
    /// The file written.
    pub output: String,
    /// Its size in bytes.
    pub bytes: u64,
    /// The settings baked with (recorded in the file).
    pub settings: BakeSettings,
    /// One report per level, finest first.
    pub levels: Vec<LevelReport>,
    /// Wall-clock seconds per stage, over all levels.
    pub seconds: StageSeconds,
    /// Wall-clock seconds of the whole bake.
    pub total_seconds: f64,
    /// Visibility rays traced (AIV and ABV).
    pub rays: u64,
    /// Visibility rays per wall-clock second of the voxel and face stages.
    pub rays_per_second: f64,
    /// Bytes per component of the file (keys, records, lobes, moments, AIV and ABV trees).
    pub components: ComponentBytes,
    /// Peak resident memory of the process (Linux), bytes.
    pub peak_memory: Option<u64>,
    /// Per effect of the appearance model, whether the file holds it and why not.
    pub effects: Vec<EffectLine>,
    /// What the rate control chose and met, when the settings name a target.
    pub rate: Option<RateReport>,
}

/// Why a bake failed.
#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    /// The settings are inconsistent (the message says which).
    #[error("invalid settings: {0}")]
    Settings(String),
    /// Nothing to bake.
    #[error("the scene has no surface to bake (no triangles with area)")]
    Empty,
    /// The output could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The path that failed.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// Peak resident set size of this process (VmHWM), where the platform tells it.
pub fn peak_memory() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Where the blocks go: an `.agg` file, or a shard's part file.
enum Sink<'a> {
    Agg(&'a mut Writer),
    Part(&'a mut PartWriter),
}

impl Sink<'_> {
    /// Writes block `chunk` of level `level` (keys `first..=last`, `count` records): into the
    /// file, its reference added to `refs`, or into the part, which records where it goes.
    #[allow(clippy::too_many_arguments)]
    fn put(
        &mut self,
        level: usize,
        kind: BlockKind,
        chunk: usize,
        blob: &[u8],
        (first, last): (u64, u64),
        count: usize,
        refs: &mut Vec<crate::format::fb::BlobRef>,
    ) -> std::io::Result<()> {
        match self {
            Sink::Agg(w) => refs.push(w.write_block(blob, first, last, count as u32)?),
            Sink::Part(w) => w.write_block(
                level as u32,
                kind,
                chunk as u64,
                blob,
                first,
                last,
                count as u32,
            )?,
        }
        Ok(())
    }
}

/// The levels as baked: index entries, reports, and for a shard what its part records.
struct Baked {
    bounds: (glam::Vec3, glam::Vec3),
    entries: Vec<LevelEntry>,
    reports: Vec<LevelReport>,
    components: ComponentBytes,
    total: StageSeconds,
    rays: u64,
    part_levels: Vec<PartLevel>,
}

/// The bake's levels, block by block into `sink`. With a shard, only the chunks it owns are
/// baked to the end and written (see [`crate::format::part`]); the voxels of other chunks get
/// their primitive alone, which the boundary faces need.
/// With `defer`, the blocks are not encoded: each level's voxels and faces are held there for
/// the rate control ([`super::rate`]), and the entries' blocks and counts are left empty.
fn bake_levels(
    scene: &Scene,
    settings: &BakeSettings,
    shard: Option<Shard>,
    sink: &mut Sink,
    progress: Progress,
    mut defer: Option<&mut Vec<PendingLevel>>,
) -> std::io::Result<Baked> {
    let accel = Accel::build(scene);
    let (lo, hi) = scene.bounds();
    let mut entries = Vec::new();
    let mut reports = Vec::new();
    let mut components = ComponentBytes::default();
    let mut total = StageSeconds::default();
    let mut rays = 0u64;
    let mut part_levels = Vec::new();
    // Chunks counted across levels: shard I bakes chunk g where g mod N == I.
    let mut g = 0u64;
    let owns = |g: u64| shard.is_none_or(|s| s.owns(g));
    for (li, res) in settings.resolutions().into_iter().enumerate() {
        let grid = Grid::around(lo, hi, res);
        let ls = settings.level(res);
        let by_block = settings.allocates_per_block();
        if let Some(d) = defer.as_mut() {
            d.push(PendingLevel {
                voxel_size: grid.voxel_size(),
                ..Default::default()
            });
        }
        let mut sec = StageSeconds::default();
        let mut counts = Counts::default();
        let mut bytes = 0u64;
        let mut level_components = ComponentBytes::default();
        // Voxelize: exact pieces of surface per voxel, in Morton order.
        let t = Instant::now();
        let pieces: Vec<(u64, Vec<super::sampling::Piece>)> =
            pieces_by_voxel(scene, &grid).into_iter().collect();
        sec.voxelize = t.elapsed().as_secs_f64();
        // Voxels, block by block.
        let bar = StageCounter::new(progress, format!("{res}³ voxels"), pieces.len() as u64);
        let (mut cpu_stats, mut cpu_aiv) = (0f64, 0f64);
        let mut aiv_bandwidth = [0u64; AIV_BANDWIDTHS.len()];
        let mut aiv_rays = 0u64;
        let mut keys_prims: Vec<(u64, Ellipsoid)> = Vec::with_capacity(pieces.len());
        let mut voxel_blocks = Vec::new();
        let voxel_chunks = pieces.len().div_ceil(BLOCK_VOXELS) as u64;
        for (ci, chunk) in pieces.chunks(BLOCK_VOXELS).enumerate() {
            let t = Instant::now();
            if !owns(g + ci as u64) {
                // Another shard's chunk: the primitives alone, for the faces.
                let prims: Vec<Option<(u64, Ellipsoid)>> = chunk
                    .par_iter()
                    .map(|(key, p)| {
                        let e = voxel_primitive(scene, &grid, *key, p, &ls);
                        bar.add(1);
                        e.map(|e| (*key, e))
                    })
                    .collect();
                keys_prims.extend(prims.into_iter().flatten());
                sec.voxels += t.elapsed().as_secs_f64();
                continue;
            }
            let baked: Vec<(Option<VoxelData>, VoxelCost)> = chunk
                .par_iter()
                .map(|(key, p)| {
                    let (v, cost) = bake_voxel(scene, &accel, &grid, *key, p, &ls);
                    bar.add(1);
                    (v, cost)
                })
                .collect();
            let voxels: Vec<VoxelData> = baked
                .into_iter()
                .filter_map(|(v, cost)| {
                    aiv_rays += cost.rays;
                    cpu_stats += cost.cpu[0];
                    cpu_aiv += cost.cpu[1];
                    if let Some(i) = AIV_BANDWIDTHS
                        .iter()
                        .position(|&b| Some(b) == cost.aiv_bandwidth)
                    {
                        aiv_bandwidth[i] += 1;
                    }
                    v
                })
                .collect();
            sec.voxels += t.elapsed().as_secs_f64();
            if voxels.is_empty() {
                continue;
            }
            let t = Instant::now();
            keys_prims.extend(voxels.iter().map(|v| (v.key, v.ellipsoid)));
            if let Some(level) = defer.as_mut().and_then(|d| d.last_mut()) {
                level.voxels.push(voxels);
                sec.write += t.elapsed().as_secs_f64();
                continue;
            }
            let voxels = if by_block {
                let (s, size) = (settings, grid.voxel_size());
                rate::equal_error_block(voxels, Vec::new(), size, s.keep, s.energy).0
            } else {
                voxels
            };
            let blob = encode::voxel_block(
                li as u32,
                &voxels,
                settings.keep_all_effects,
                settings.lossless,
                &mut counts,
                &mut level_components,
            );
            bytes += blob.len() as u64;
            let (first, last) = (voxels[0].key, voxels[voxels.len() - 1].key);
            sink.put(
                li,
                BlockKind::Voxel,
                ci,
                &blob,
                (first, last),
                voxels.len(),
                &mut voxel_blocks,
            )?;
            sec.write += t.elapsed().as_secs_f64();
        }
        drop(pieces);
        // Boundary faces, block by block.
        let t = Instant::now();
        // Every shard has every key: a CRC-32 of them lets the merge check the shards agree.
        let keys_crc32 = shard.map_or(0, |_| {
            let mut h = crc32fast::Hasher::new();
            for (k, _) in &keys_prims {
                h.update(&k.to_le_bytes());
            }
            h.finalize()
        });
        let kept_voxels = keys_prims.len() as u64;
        // The level's keys for the index, so that a reader learns its occupancy without
        // inflating every block (a shard's merge rebuilds them from the blocks).
        let voxel_keys = shard
            .is_none()
            .then(|| {
                crate::format::encode_voxel_keys(
                    keys_prims.iter().map(|k| k.0),
                    settings.compression,
                )
            })
            .flatten();
        let faces = sorted_boundary_faces(keys_prims.iter().map(|k| k.0), res);
        let prims = primitive_level(grid, keys_prims.into_iter());
        let bar = StageCounter::new(progress, format!("{res}³ faces"), faces.len() as u64);
        let mut abv_rays = 0u64;
        let mut abv_bandwidth = [0u64; ABV_BANDWIDTHS.len()];
        let mut face_blocks = Vec::new();
        g += voxel_chunks;
        let face_chunks = faces.len().div_ceil(BLOCK_FACES) as u64;
        for (ci, chunk) in faces.chunks(BLOCK_FACES).enumerate() {
            if !owns(g + ci as u64) {
                bar.add(chunk.len() as u64);
                continue;
            }
            let t = Instant::now();
            let baked: Vec<_> = chunk
                .par_iter()
                .map(|f| {
                    let r = bake_face(&prims, &accel, *f, &ls);
                    bar.add(1);
                    r
                })
                .collect();
            for b in &baked {
                abv_rays += b.1;
                if let Some(i) = ABV_BANDWIDTHS.iter().position(|&k| k == b.2) {
                    abv_bandwidth[i] += 1;
                }
            }
            let data: Vec<_> = baked.into_iter().map(|b| b.0).collect();
            sec.faces += t.elapsed().as_secs_f64();
            if let Some(level) = defer.as_mut().and_then(|d| d.last_mut()) {
                level.faces.push(data);
                continue;
            }
            let t = Instant::now();
            let data = if by_block {
                let (s, size) = (settings, grid.voxel_size());
                rate::equal_error_block(Vec::new(), data, size, s.keep, s.energy).1
            } else {
                data
            };
            let blob = encode::face_block(
                li as u32,
                &data,
                settings.lossless,
                &mut counts,
                &mut level_components,
            );
            bytes += blob.len() as u64;
            let (first, last) = (
                encode::face_key(&data[0]),
                encode::face_key(&data[data.len() - 1]),
            );
            sink.put(
                li,
                BlockKind::Face,
                ci,
                &blob,
                (first, last),
                data.len(),
                &mut face_blocks,
            )?;
            sec.write += t.elapsed().as_secs_f64();
        }
        let _ = t;
        g += face_chunks;
        components.add(&level_components);
        if shard.is_some() {
            part_levels.push(PartLevel {
                res,
                origin_bits: grid.origin.to_array().map(f32::to_bits),
                size_bits: grid.size.to_bits(),
                voxel_chunks,
                face_chunks,
                voxels: kept_voxels,
                keys_crc32,
                counts,
                components: level_components,
            });
        }
        rays += aiv_rays + abv_rays;
        total.voxelize += sec.voxelize;
        total.voxels += sec.voxels;
        total.faces += sec.faces;
        total.write += sec.write;
        entries.push(LevelEntry {
            res,
            origin: grid.origin,
            size: grid.size,
            voxel_blocks,
            face_blocks,
            counts,
            voxel_keys,
        });
        reports.push(LevelReport {
            res,
            voxels: counts.voxels,
            faces: counts.faces,
            occupancy: counts.voxels as f64 / (res as f64).powi(3),
            samples_per_voxel: ls.samples_per_voxel,
            abv_rays_per_face: ls.abv_rays * (ls.abv_res / ls.abv_stride).pow(2),
            seconds: sec,
            cpu_statistics: cpu_stats,
            cpu_aiv,
            aiv_rays,
            aiv_bandwidth,
            abv_rays,
            abv_bandwidth,
            bytes,
            counts,
        });
    }
    Ok(Baked {
        bounds: (lo, hi),
        entries,
        reports,
        components,
        total,
        rays,
        part_levels,
    })
}

/// Bakes `scene` into `out` (written atomically). `source` is the asset's file name, recorded
/// in the index; `progress` hears of every voxel and face done, stage by stage.
pub fn bake_to_file(
    scene: &Scene,
    source: &str,
    settings: &BakeSettings,
    out: &Path,
    progress: Progress,
) -> Result<BakeReport, BakeError> {
    settings.validate().map_err(BakeError::Settings)?;
    if !(scene.world_area() > 0.0) {
        return Err(BakeError::Empty);
    }
    let io = |e: std::io::Error| BakeError::Io {
        path: out.display().to_string(),
        source: e,
    };
    // Before the bake, not after it: a folder given as the output fails now.
    crate::util::check_destination(out).map_err(io)?;
    let t_start = Instant::now();
    let mut writer = Writer::create(out).map_err(io)?;
    writer.set_compression(settings.compression);
    let target = settings.rate_target();
    let mut pending = Vec::new();
    let mut b = bake_levels(
        scene,
        settings,
        None,
        &mut Sink::Agg(&mut writer),
        progress,
        target.is_some().then_some(&mut pending),
    )
    .map_err(io)?;
    let (lo, hi) = b.bounds;
    let recorded = settings.recorded();
    let index_of = |entries: &[LevelEntry]| {
        encode::index(&IndexEntry {
            generator: concat!("aggtool ", env!("CARGO_PKG_VERSION")),
            source,
            bounds: (lo, hi),
            settings: &recorded,
            tables_version: crate::tables::TABLES_VERSION,
            tables_crc32: crc32fast::hash(crate::tables::EMBEDDED),
            levels: entries,
        })
    };
    let mut rate_report = None;
    if let Some(target) = target {
        let t = Instant::now();
        let (placed, report) = place_levels(
            &mut writer,
            pending,
            &mut b.entries,
            settings,
            target,
            &index_of,
        )
        .map_err(io)?;
        b.components = ComponentBytes::default();
        for (r, p) in b.reports.iter_mut().zip(&placed) {
            r.counts = p.counts;
            r.voxels = p.counts.voxels;
            r.faces = p.counts.faces;
            r.occupancy = p.counts.voxels as f64 / (r.res as f64).powi(3);
            r.bytes = p.bytes;
            b.components.add(&p.components);
        }
        b.total.write += t.elapsed().as_secs_f64();
        rate_report = Some(report);
    }
    let entries = b.entries;
    let mut total = b.total;
    let index = index_of(&entries);
    let t = Instant::now();
    let size = writer.finish(&index).map_err(io)?;
    if let Some(r) = rate_report.as_mut() {
        r.settle(size);
    }
    let (reports, components, rays) = (b.reports, b.components, b.rays);
    total.write += t.elapsed().as_secs_f64();
    let total_seconds = t_start.elapsed().as_secs_f64();
    let per_level: Vec<(u32, Counts)> = entries.iter().map(|e| (e.res, e.counts)).collect();
    Ok(BakeReport {
        output: out.display().to_string(),
        bytes: size,
        settings: settings.clone(),
        levels: reports,
        seconds: total,
        total_seconds,
        rays,
        rays_per_second: rays as f64 / (total.voxels + total.faces).max(1e-9),
        components,
        peak_memory: peak_memory(),
        effects: effect_lines(&per_level, settings.keep_all_effects),
        rate: rate_report,
    })
}

/// What a level holds once the rate control has placed it in the file.
struct Placed {
    bytes: u64,
    counts: Counts,
    components: ComponentBytes,
}

/// Chooses the rate control's multiplier for `pending` ([`rate::allocate`]) and writes the
/// levels' blocks, in file order, filling `entries`' block references and counts.
/// `index_of` encodes the index of a set of entries (its size, with placeholder references,
/// is part of what a file budget counts).
fn place_levels(
    writer: &mut Writer,
    pending: Vec<PendingLevel>,
    entries: &mut [LevelEntry],
    settings: &BakeSettings,
    target: rate::RateTarget,
    index_of: &dyn Fn(&[LevelEntry]) -> Vec<u8>,
) -> std::io::Result<(Vec<Placed>, RateReport)> {
    // The index's bytes depend on λ only through the levels' counts (FlatBuffers leaves a
    // zero out): block references have a fixed size.
    let mut sized = entries.to_vec();
    for (e, p) in sized.iter_mut().zip(&pending) {
        e.voxel_blocks = vec![Default::default(); p.voxels.len()];
        e.face_blocks = vec![Default::default(); p.faces.len()];
    }
    let fixed = |counts: &[Counts]| {
        let mut s = sized.clone();
        for (e, c) in s.iter_mut().zip(counts) {
            e.counts = *c;
        }
        crate::format::HEADER_SIZE as u64 + index_of(&s).len() as u64
    };
    let (levels, report) = rate::allocate(&pending, settings, target, &fixed);
    drop(pending);
    let mut placed = Vec::with_capacity(levels.len());
    for (e, level) in entries.iter_mut().zip(levels) {
        let mut bytes = 0;
        e.voxel_blocks.clear();
        e.face_blocks.clear();
        for (blocks, refs) in [
            (level.voxel_blocks, &mut e.voxel_blocks),
            (level.face_blocks, &mut e.face_blocks),
        ] {
            for blk in blocks {
                bytes += blk.blob.len() as u64;
                refs.push(writer.write_blob(
                    &blk.blob,
                    blk.keys.0,
                    blk.keys.1,
                    blk.count as u32,
                )?);
            }
        }
        e.counts = level.counts;
        placed.push(Placed {
            bytes,
            counts: level.counts,
            components: level.components,
        });
    }
    Ok((placed, report))
}

/// Re-spends the visibility details of the baked file `input` on the rate target of
/// `settings` ([`BakeSettings::rate_target`]), without baking again, into `out` (written
/// atomically): `aggtool rate`. The candidates are the details the file holds, so a file
/// baked with a target (or `--keep 1 --energy 1`) can be re-rated to any smaller budget, and
/// a default file only to a smaller one. Everything else is copied as it is.
pub fn rate_file(
    input: &crate::format::Aggregate,
    target: rate::RateTarget,
    out: &Path,
) -> Result<(u64, RateReport), BakeError> {
    let io = |e: std::io::Error| BakeError::Io {
        path: out.display().to_string(),
        source: e,
    };
    crate::util::check_destination(out).map_err(io)?;
    let mut settings = BakeSettings::from_recorded(input.settings());
    (settings.size_mib, settings.level_mib, settings.error) = match target {
        rate::RateTarget::FileBytes(b) => (b as f64 / (1024.0 * 1024.0), 0.0, 0.0),
        rate::RateTarget::LevelBytes(b) => (0.0, b as f64 / (1024.0 * 1024.0), 0.0),
        rate::RateTarget::Error(e) => (0.0, 0.0, e),
    };
    let mut pending = Vec::with_capacity(input.level_count());
    let mut entries = Vec::with_capacity(input.level_count());
    for l in 0..input.level_count() {
        let level = input.read_level(l);
        let keys = encode_voxel_keys(level.voxels.iter().map(|v| v.key), settings.compression);
        entries.push(LevelEntry {
            res: level.grid.res,
            origin: level.grid.origin,
            size: level.grid.size,
            voxel_blocks: Vec::new(),
            face_blocks: Vec::new(),
            counts: Counts::default(),
            voxel_keys: keys,
        });
        pending.push(PendingLevel {
            voxel_size: level.grid.voxel_size(),
            voxels: level
                .voxels
                .chunks(BLOCK_VOXELS)
                .map(<[_]>::to_vec)
                .collect(),
            faces: level.faces.chunks(BLOCK_FACES).map(<[_]>::to_vec).collect(),
        });
    }
    let recorded = settings.recorded();
    let (tables_version, tables_crc32) = input.tables();
    let index_of = |entries: &[LevelEntry]| {
        encode::index(&IndexEntry {
            generator: concat!("aggtool ", env!("CARGO_PKG_VERSION")),
            source: input.source(),
            bounds: input.bounds(),
            settings: &recorded,
            tables_version,
            tables_crc32,
            levels: entries,
        })
    };
    let mut writer = Writer::create(out).map_err(io)?;
    writer.set_compression(settings.compression);
    let (_, mut report) = place_levels(
        &mut writer,
        pending,
        &mut entries,
        &settings,
        target,
        &index_of,
    )
    .map_err(io)?;
    let size = writer.finish(&index_of(&entries)).map_err(io)?;
    report.settle(size);
    Ok((size, report))
}

/// Bakes shard `shard` of `scene` into the part file `out` (written atomically; see
/// [`crate::format::part`]): the blocks of the chunks it owns, encoded and compressed as
/// [`bake_to_file`] writes them, and what `aggtool merge` needs. The report's counts and bytes
/// are this shard's.
pub fn bake_shard_to_file(
    scene: &Scene,
    source: &str,
    settings: &BakeSettings,
    shard: Shard,
    out: &Path,
    progress: Progress,
) -> Result<BakeReport, BakeError> {
    settings.validate().map_err(BakeError::Settings)?;
    if shard.count == 0 || shard.index >= shard.count {
        return Err(BakeError::Settings(format!(
            "shard {}/{}: need 0 <= I < N",
            shard.index, shard.count
        )));
    }
    if let Some(t) = settings.rate_target() {
        return Err(BakeError::Settings(format!(
            "a farm's shards cannot share a rate target ({}): the multiplier is chosen over the \
             whole file; bake it in one process, or without --size-mib, --level-mib and --error",
            t.describe()
        )));
    }
    if !(scene.world_area() > 0.0) {
        return Err(BakeError::Empty);
    }
    let io = |e: std::io::Error| BakeError::Io {
        path: out.display().to_string(),
        source: e,
    };
    crate::util::check_destination(out).map_err(io)?;
    let t_start = Instant::now();
    let mut writer = PartWriter::create(out, settings.compression).map_err(io)?;
    let b = bake_levels(
        scene,
        settings,
        Some(shard),
        &mut Sink::Part(&mut writer),
        progress,
        None,
    )
    .map_err(io)?;
    let (lo, hi) = b.bounds;
    let recorded = settings.recorded();
    let meta = PartMeta {
        shard: shard.index,
        shards: shard.count,
        generator: concat!("aggtool ", env!("CARGO_PKG_VERSION")).to_string(),
        source: source.to_string(),
        bounds_bits: [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z].map(f32::to_bits),
        settings_float_bits: [recorded.keep.to_bits(), recorded.energy.to_bits()],
        settings: recorded,
        tables_version: crate::tables::TABLES_VERSION,
        tables_crc32: crc32fast::hash(crate::tables::EMBEDDED),
        levels: b.part_levels,
        blocks: Vec::new(),
    };
    let mut total = b.total;
    let t = Instant::now();
    let size = writer.finish(meta).map_err(io)?;
    total.write += t.elapsed().as_secs_f64();
    let per_level: Vec<(u32, Counts)> = b.entries.iter().map(|e| (e.res, e.counts)).collect();
    Ok(BakeReport {
        output: out.display().to_string(),
        bytes: size,
        settings: settings.clone(),
        levels: b.reports,
        seconds: total,
        total_seconds: t_start.elapsed().as_secs_f64(),
        rays: b.rays,
        rays_per_second: b.rays as f64 / (total.voxels + total.faces).max(1e-9),
        components: b.components,
        peak_memory: peak_memory(),
        effects: effect_lines(&per_level, settings.keep_all_effects),
        rate: None,
    })
}
