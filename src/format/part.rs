//! Part files of a sharded bake (`aggtool convert ASSET --shard I/N -o PART`) and their merge
//! (`aggtool merge PART... -o OUT.agg`) into exactly the bytes a one-machine bake writes.
//!
//! A bake cuts every level into chunks: voxel chunks of `BLOCK_VOXELS` keys, then face chunks
//! of `BLOCK_FACES` boundary faces, numbered across levels (finest first) by one counter `g`.
//! Shard `I` of `N` encodes and compresses the blocks of the chunks with `g mod N == I`; every
//! shard voxelises every level and fits every voxel's primitive (the faces' visibility needs
//! all of them), so all shards agree on the chunks. A part file is:
//!
//! ```text
//! offset 0   magic "AGGPART\n"
//!        8   u32 version (1), u32 CRC-32 of the metadata
//!       16   u64 metadata offset, u64 metadata size
//!       32   the shard's blobs as `.agg` stores them (compressed where the bake compresses)
//!            then the metadata: JSON (PartMeta), floats stored as their bit patterns
//! ```
//!
//! The merge checks that the parts are shards 0..N-1 of one bake, each once (same generator,
//! source, bounds, settings, tables, levels, chunk counts and a CRC-32 of each level's voxel
//! keys), that each block belongs to its shard and that its bytes match their CRC-32; then it
//! writes the blocks in chunk order through [`super::Writer`] and the index from the summed
//! counts. Any failure leaves nothing written.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::encode::{self, ComponentBytes, Counts, IndexEntry, LevelEntry};
use super::settings::RecordedSettings;
use super::{compress_block, fb, Writer};

/// The first eight bytes of a part file.
pub const PART_MAGIC: [u8; 8] = *b"AGGPART\n";
/// The part-file version this build writes and reads.
pub const PART_VERSION: u32 = 1;
const PART_HEADER: u64 = 32;

/// Which share of the chunks a bake encodes: chunk `g` where `g mod count == index`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// I: this shard's number, 0 to N-1.
    pub index: u32,
    /// N: how many shards share the bake.
    pub count: u32,
}

impl Shard {
    /// Parses `I/N` (0 ≤ I < N).
    pub fn parse(s: &str) -> Result<Shard, String> {
        let (i, n) = s
            .split_once('/')
            .ok_or_else(|| format!("shard '{s}': expected I/N, e.g. 0/4"))?;
        let index: u32 = i
            .trim()
            .parse()
            .map_err(|_| format!("shard '{s}': I is not a number"))?;
        let count: u32 = n
            .trim()
            .parse()
            .map_err(|_| format!("shard '{s}': N is not a number"))?;
        if count == 0 || index >= count {
            return Err(format!("shard '{s}': need 0 <= I < N"));
        }
        Ok(Shard { index, count })
    }

    /// Whether chunk `g` (counted across levels) is this shard's.
    pub fn owns(&self, g: u64) -> bool {
        g % self.count as u64 == self.index as u64
    }
}

/// Voxel or face block.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BlockKind {
    /// A block of voxels.
    Voxel,
    /// A block of boundary faces.
    Face,
}

/// One block a part holds.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PartBlock {
    /// The level (0: finest).
    pub level: u32,
    /// Voxels or faces.
    pub kind: BlockKind,
    /// The chunk's number within its level and kind.
    pub chunk: u64,
    /// Where the stored bytes are in the part file.
    pub offset: u64,
    /// Stored bytes.
    pub size: u64,
    /// The first and last key of the block, as the index records them.
    pub first_key: u64,
    /// See `first_key`.
    pub last_key: u64,
    /// Voxels or faces in the block.
    pub count: u32,
    /// CRC-32 of the stored bytes.
    pub crc32: u32,
}

/// One level as every shard sees it, with what this shard's blocks hold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartLevel {
    /// Voxels per axis.
    pub res: u32,
    /// Bits of the level cube's origin and edge (f32).
    pub origin_bits: [u32; 3],
    /// See `origin_bits`.
    pub size_bits: u32,
    /// Voxel and face chunks of the level (all shards).
    pub voxel_chunks: u64,
    /// See `voxel_chunks`.
    pub face_chunks: u64,
    /// Voxels kept in the level and a CRC-32 of their keys (little-endian u64s).
    pub voxels: u64,
    /// See `voxels`.
    pub keys_crc32: u32,
    /// What this shard's blocks of the level hold.
    pub counts: Counts,
    /// Bytes per component of this shard's blocks of the level.
    pub components: ComponentBytes,
}

/// The metadata of a part file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartMeta {
    /// I of I/N.
    pub shard: u32,
    /// N of I/N.
    pub shards: u32,
    /// The generator the index records.
    pub generator: String,
    /// The source asset's file name.
    pub source: String,
    /// Bits of the bounds' min and max (f32).
    pub bounds_bits: [u32; 6],
    /// The bake settings the index records.
    pub settings: RecordedSettings,
    /// Bits of `settings.keep` and `settings.energy` (JSON need not round-trip an f32).
    pub settings_float_bits: [u32; 2],
    /// Version of the tables.
    pub tables_version: u32,
    /// CRC-32 of the tables.
    pub tables_crc32: u32,
    /// The levels, finest first.
    pub levels: Vec<PartLevel>,
    /// The blocks this part holds, in the order written.
    pub blocks: Vec<PartBlock>,
}

impl PartMeta {
    /// What every shard of one bake shares: everything but the shard number, its blocks and
    /// their counts.
    fn fingerprint(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).expect("serialisable");
        let o = v.as_object_mut().expect("object");
        o.remove("shard");
        o.remove("blocks");
        if let Some(levels) = o.get_mut("levels").and_then(|l| l.as_array_mut()) {
            for l in levels {
                if let Some(l) = l.as_object_mut() {
                    l.remove("counts");
                    l.remove("components");
                }
            }
        }
        v
    }
}

/// Streams a shard's blocks into a part file (through a temporary file, renamed into place by
/// [`PartWriter::finish`]; dropped unfinished, it leaves nothing).
pub struct PartWriter {
    file: Option<BufWriter<File>>,
    tmp: crate::util::LiveTemp,
    dest: PathBuf,
    pos: u64,
    compression: i32,
    blocks: Vec<PartBlock>,
}

impl PartWriter {
    /// Starts writing `dest`; blocks are compressed at this Zstandard level as
    /// [`Writer::write_block`] does.
    pub fn create(dest: &Path, compression: i32) -> std::io::Result<PartWriter> {
        let (tmp, mut file) = super::temp_beside(dest, "out.aggpart")?;
        file.write_all(&[0u8; PART_HEADER as usize])?;
        Ok(PartWriter {
            file: Some(file),
            tmp,
            dest: dest.to_path_buf(),
            pos: PART_HEADER,
            compression,
            blocks: Vec::new(),
        })
    }

    /// Appends a block's FlatBuffer, stored as `.agg` would store it.
    #[allow(clippy::too_many_arguments)]
    pub fn write_block(
        &mut self,
        level: u32,
        kind: BlockKind,
        chunk: u64,
        block: &[u8],
        first_key: u64,
        last_key: u64,
        count: u32,
    ) -> std::io::Result<()> {
        let z = if self.compression > 0 {
            compress_block(block, self.compression)
        } else {
            None
        };
        let bytes = z.as_deref().unwrap_or(block);
        let file = self.file.as_mut().expect("part writer already finished");
        file.write_all(bytes)?;
        self.blocks.push(PartBlock {
            level,
            kind,
            chunk,
            offset: self.pos,
            size: bytes.len() as u64,
            first_key,
            last_key,
            count,
            crc32: crc32fast::hash(bytes),
        });
        self.pos += bytes.len() as u64;
        Ok(())
    }

    /// Writes the metadata (its `blocks` are the ones written) and the header, syncs and
    /// renames into place. Returns the file size.
    pub fn finish(mut self, mut meta: PartMeta) -> std::io::Result<u64> {
        meta.blocks = std::mem::take(&mut self.blocks);
        let r = self.finish_inner(&meta);
        if r.is_err() {
            self.file = None;
            let _ = std::fs::remove_file(self.tmp.path());
        }
        r
    }

    fn finish_inner(&mut self, meta: &PartMeta) -> std::io::Result<u64> {
        let json = serde_json::to_vec(meta).map_err(std::io::Error::other)?;
        let mut file = self.file.take().expect("part writer already finished");
        file.write_all(&json)?;
        let mut h = [0u8; PART_HEADER as usize];
        h[0..8].copy_from_slice(&PART_MAGIC);
        h[8..12].copy_from_slice(&PART_VERSION.to_le_bytes());
        h[12..16].copy_from_slice(&crc32fast::hash(&json).to_le_bytes());
        h[16..24].copy_from_slice(&self.pos.to_le_bytes());
        h[24..32].copy_from_slice(&(json.len() as u64).to_le_bytes());
        file.seek(SeekFrom::Start(0))?;
        file.write_all(&h)?;
        let file = file.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(self.tmp.path(), &self.dest)?;
        Ok(self.pos + json.len() as u64)
    }
}

impl Drop for PartWriter {
    fn drop(&mut self) {
        if self.file.take().is_some() {
            let _ = std::fs::remove_file(self.tmp.path());
        }
    }
}

/// Why a merge failed (nothing was written).
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    /// One part file is unreadable, damaged or inconsistent.
    #[error("{path}: {message}")]
    Part {
        /// The part file.
        path: String,
        /// What is wrong with it.
        message: String,
    },
    /// The parts given are not one whole bake (missing, duplicate or mismatched shards).
    #[error("{0}")]
    Set(String),
    /// The output could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The output file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
}

/// Reads a part file's metadata, checking its header and that its blocks lie inside it.
pub fn read_part_meta(path: &Path) -> Result<PartMeta, MergeError> {
    let err = |message: String| MergeError::Part {
        path: path.display().to_string(),
        message,
    };
    let mut f = File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
    let len = f
        .metadata()
        .map_err(|e| err(format!("cannot stat: {e}")))?
        .len();
    let mut h = [0u8; PART_HEADER as usize];
    if len < PART_HEADER || f.read_exact(&mut h).is_err() {
        return Err(err(format!(
            "not a part file: {len} bytes, shorter than its header"
        )));
    }
    if h[0..8] != PART_MAGIC {
        return Err(err(
            "not a part file (written by `aggtool convert --shard I/N`)".into(),
        ));
    }
    let u32_at = |o: usize| u32::from_le_bytes(h[o..o + 4].try_into().unwrap());
    let u64_at = |o: usize| u64::from_le_bytes(h[o..o + 8].try_into().unwrap());
    if u32_at(8) != PART_VERSION {
        return Err(err(format!(
            "part version {} (this build reads {PART_VERSION})",
            u32_at(8)
        )));
    }
    let (off, size) = (u64_at(16), u64_at(24));
    if off < PART_HEADER || off.checked_add(size) != Some(len) {
        return Err(err(format!(
            "truncated or damaged: metadata at {off}+{size} in a file of {len} bytes"
        )));
    }
    let mut json = vec![0u8; size as usize];
    f.seek(SeekFrom::Start(off))
        .and_then(|_| f.read_exact(&mut json))
        .map_err(|e| err(format!("cannot read the metadata: {e}")))?;
    if crc32fast::hash(&json) != u32_at(12) {
        return Err(err("metadata checksum mismatch".into()));
    }
    let meta: PartMeta =
        serde_json::from_slice(&json).map_err(|e| err(format!("bad metadata: {e}")))?;
    if meta.shards == 0 || meta.shard >= meta.shards {
        return Err(err(format!("bad shard {}/{}", meta.shard, meta.shards)));
    }
    for b in &meta.blocks {
        let end = b.offset.checked_add(b.size);
        if b.offset < PART_HEADER || end.is_none_or(|e| e > off) {
            return Err(err(format!(
                "block at {}+{} lies outside the blob area",
                b.offset, b.size
            )));
        }
    }
    Ok(meta)
}

/// Joins the parts of a sharded bake into `out` (written atomically): the same bytes as the
/// one-machine bake. Returns the file size.
pub fn merge(parts: &[PathBuf], out: &Path) -> Result<u64, MergeError> {
    if parts.is_empty() {
        return Err(MergeError::Set("no part files given".into()));
    }
    let metas: Vec<PartMeta> = parts
        .iter()
        .map(|p| read_part_meta(p))
        .collect::<Result<_, _>>()?;
    let name = |i: usize| parts[i].display().to_string();
    // One bake, every shard once.
    let n = metas[0].shards;
    let print = metas[0].fingerprint();
    let mut by_shard: BTreeMap<u32, usize> = BTreeMap::new();
    for (i, m) in metas.iter().enumerate() {
        if m.shards != n {
            return Err(MergeError::Set(format!(
                "{} is shard {}/{} but {} is of {n} shards",
                name(i),
                m.shard,
                m.shards,
                name(0)
            )));
        }
        if m.fingerprint() != print {
            let a = print.as_object().unwrap();
            let b = m.fingerprint();
            let b = b.as_object().unwrap();
            let what: Vec<&str> = a
                .keys()
                .filter(|k| a.get(*k) != b.get(*k))
                .map(|k| k.as_str())
                .collect();
            return Err(MergeError::Set(format!(
                "{} and {} are not shards of the same bake ({} differ)",
                name(0),
                name(i),
                what.join(", ")
            )));
        }
        if let Some(&j) = by_shard.get(&m.shard) {
            return Err(MergeError::Set(format!(
                "duplicate shard {}/{n}: {} and {}",
                m.shard,
                name(j),
                name(i)
            )));
        }
        by_shard.insert(m.shard, i);
    }
    let missing: Vec<String> = (0..n)
        .filter(|s| !by_shard.contains_key(s))
        .map(|s| format!("{s}/{n}"))
        .collect();
    if !missing.is_empty() {
        return Err(MergeError::Set(format!(
            "missing shard(s) {} (given {} of {n})",
            missing.join(", "),
            metas.len()
        )));
    }
    // Every block where its shard should have it, each chunk once.
    let levels = &metas[0].levels;
    let mut base = Vec::with_capacity(levels.len());
    let mut g = 0u64;
    for l in levels {
        base.push(g);
        g += l.voxel_chunks + l.face_chunks;
    }
    let mut order: BTreeMap<(u32, u8, u64), (usize, &PartBlock)> = BTreeMap::new();
    for (i, m) in metas.iter().enumerate() {
        for b in &m.blocks {
            let bad = |why: &str| MergeError::Part {
                path: name(i),
                message: format!(
                    "level {} {:?} block of chunk {}: {why}",
                    b.level, b.kind, b.chunk
                ),
            };
            let Some(l) = levels.get(b.level as usize) else {
                return Err(bad("no such level"));
            };
            let (kind, gi) = match b.kind {
                BlockKind::Voxel if b.chunk < l.voxel_chunks => {
                    (0u8, base[b.level as usize] + b.chunk)
                }
                BlockKind::Face if b.chunk < l.face_chunks => {
                    (1u8, base[b.level as usize] + l.voxel_chunks + b.chunk)
                }
                _ => return Err(bad("no such chunk")),
            };
            if gi % n as u64 != m.shard as u64 {
                return Err(bad("not this shard's chunk"));
            }
            if order.insert((b.level, kind, b.chunk), (i, b)).is_some() {
                return Err(bad("stored twice"));
            }
        }
    }
    // Write: blocks in chunk order, then the index from the summed counts.
    let io = |e: std::io::Error| MergeError::Io {
        path: out.display().to_string(),
        source: e,
    };
    let mut files: Vec<File> = parts
        .iter()
        .enumerate()
        .map(|(i, p)| {
            File::open(p).map_err(|e| MergeError::Part {
                path: name(i),
                message: format!("cannot open: {e}"),
            })
        })
        .collect::<Result<_, _>>()?;
    let mut writer = Writer::create(out).map_err(io)?;
    let mut entries: Vec<LevelEntry> = levels
        .iter()
        .map(|l| LevelEntry {
            res: l.res,
            origin: Vec3::from_array(l.origin_bits.map(f32::from_bits)),
            size: f32::from_bits(l.size_bits),
            voxel_blocks: Vec::new(),
            face_blocks: Vec::new(),
            counts: Counts::default(),
            voxel_keys: None,
        })
        .collect();
    // Each level's voxel keys, rebuilt from its voxel blocks in chunk order.
    let mut level_keys: Vec<Vec<u64>> = vec![Vec::new(); levels.len()];
    for m in &metas {
        for (e, l) in entries.iter_mut().zip(&m.levels) {
            e.counts.add(&l.counts);
        }
    }
    let mut buf = Vec::new();
    for ((level, kind, _), (i, b)) in &order {
        buf.resize(b.size as usize, 0);
        files[*i]
            .seek(SeekFrom::Start(b.offset))
            .and_then(|_| files[*i].read_exact(&mut buf))
            .map_err(|e| MergeError::Part {
                path: name(*i),
                message: format!("cannot read a block: {e}"),
            })?;
        if crc32fast::hash(&buf) != b.crc32 {
            return Err(MergeError::Part {
                path: name(*i),
                message: format!(
                    "level {level} {:?} block of chunk {}: checksum mismatch (damaged part)",
                    b.kind, b.chunk
                ),
            });
        }
        let r: fb::BlobRef = writer
            .write_blob(&buf, b.first_key, b.last_key, b.count)
            .map_err(io)?;
        let e = &mut entries[*level as usize];
        if *kind == 0 {
            let keys = super::read::stored_block_keys(&buf).map_err(|why| MergeError::Part {
                path: name(*i),
                message: format!("level {level} voxel block of chunk {}: {why}", b.chunk),
            })?;
            level_keys[*level as usize].extend(keys);
            e.voxel_blocks.push(r);
        } else {
            e.face_blocks.push(r);
        }
    }
    for ((e, keys), l) in entries.iter_mut().zip(&level_keys).zip(levels.iter()) {
        let mut h = crc32fast::Hasher::new();
        for k in keys {
            h.update(&k.to_le_bytes());
        }
        if keys.len() as u64 != l.voxels || h.finalize() != l.keys_crc32 {
            return Err(MergeError::Part {
                path: name(0),
                message: format!(
                    "level {}³: the blocks' voxel keys disagree with the parts' metadata",
                    l.res
                ),
            });
        }
        e.voxel_keys =
            super::encode_voxel_keys(keys.iter().copied(), metas[0].settings.compression);
    }
    let m = &metas[0];
    let mut settings = m.settings.clone();
    settings.keep = f32::from_bits(m.settings_float_bits[0]);
    settings.energy = f32::from_bits(m.settings_float_bits[1]);
    let bb = m.bounds_bits.map(f32::from_bits);
    let index = encode::index(&IndexEntry {
        generator: &m.generator,
        source: &m.source,
        bounds: (
            Vec3::new(bb[0], bb[1], bb[2]),
            Vec3::new(bb[3], bb[4], bb[5]),
        ),
        settings: &settings,
        tables_version: m.tables_version,
        tables_crc32: m.tables_crc32,
        levels: &entries,
    });
    writer.finish(&index).map_err(io)
}

/// Which part files `aggtool merge` joins: listed, or named after a prefix as the farm
/// template names them.
#[derive(Clone, Debug)]
pub enum PartFiles {
    /// The part files, every shard once, in any order.
    Listed(Vec<PathBuf>),
    /// `PREFIX.I-of-N.aggpart` for I in 0..N.
    Prefix(PathBuf, u32),
}

impl PartFiles {
    /// The paths.
    pub fn paths(&self) -> Vec<PathBuf> {
        match self {
            PartFiles::Listed(p) => p.clone(),
            PartFiles::Prefix(prefix, n) => (0..*n)
                .map(|i| {
                    let mut p = prefix.clone().into_os_string();
                    p.push(format!(".{i}-of-{n}.aggpart"));
                    PathBuf::from(p)
                })
                .collect(),
        }
    }
}

/// What `aggtool merge` reports.
#[derive(Clone, Debug, serde::Serialize)]
pub struct MergeReport {
    /// The aggregate written.
    pub output: String,
    /// Its size.
    pub bytes: u64,
    /// The parts joined.
    pub parts: Vec<String>,
    /// Whether the part files were deleted.
    pub removed_parts: bool,
    /// Seconds.
    pub seconds: f64,
}

/// [`merge`]s `parts` into `out`, then deletes the parts if `remove_parts`.
pub fn merge_files(
    parts: &PartFiles,
    out: &Path,
    remove_parts: bool,
) -> anyhow::Result<MergeReport> {
    let t0 = std::time::Instant::now();
    let paths = parts.paths();
    let bytes = merge(&paths, out)?;
    if remove_parts {
        for p in &paths {
            std::fs::remove_file(p).map_err(|e| {
                crate::report::output(format!("cannot remove {}: {e}", p.display()))
            })?;
        }
    }
    Ok(MergeReport {
        output: out.display().to_string(),
        bytes,
        parts: paths.iter().map(|p| p.display().to_string()).collect(),
        removed_parts: remove_parts,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

impl std::fmt::Display for MergeReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "output: {} ({}) from {} parts in {:.2} s",
            self.output,
            crate::report::mib(self.bytes),
            self.parts.len(),
            self.seconds
        )
    }
}
