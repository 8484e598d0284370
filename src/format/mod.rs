//! The `.agg` file: a fixed header, 64-byte-aligned FlatBuffer blobs, and an index blob
//! (schema in `schema/aggregate.fbs`, history in `schema/CHANGES.md`).
//!
//! ```text
//! offset 0   magic  89 41 47 47 0D 0A 1A 0A   ("\x89AGG\r\n\x1a\n": binary, catches text-mode
//!                                              and 7-bit mangling, like PNG's)
//!        8   u16 major, u16 minor              (fixed positions in every version)
//!       12   u32 header size (64)
//!       16   u64 index offset, u64 index size
//!       32   u64 file size
//!       40   u32 CRC-32 of the index, u32 flags (0)
//!       48   12 reserved bytes (0)
//!       60   u32 CRC-32 of bytes 0..60
//!       64   blobs: voxel and face blocks ("AGGB"), level by level, then the index ("AGGI")
//! ```
//!
//! Blocks hold a bounded number of voxels or faces (a few MiB), so every FlatBuffer stays far
//! below the format's 2 GiB limit while a file grows to any size, and the writer streams them:
//! a bake holds one block at a time. [`Writer`] writes through a temporary file and renames
//! it into place; [`Aggregate`] maps a file (memmap2), verifies it, and reads it zero-copy.

// flatc's output: its doc comments are the schema's, written for readers of the schema (E[c]
// is an expectation, not a link).
#[allow(clippy::all, unused_imports, dead_code, non_snake_case, mismatched_lifetime_syntaxes, missing_docs)]
#[allow(rustdoc::broken_intra_doc_links)]
#[rustfmt::skip]
mod aggregate_generated;
pub mod effects;
pub mod encode;
mod level;
pub mod part;
pub mod planar;
pub mod quantize;
mod read;
pub(crate) mod settings;

pub use aggregate_generated::aggtool::format as fb;
pub use level::{FaceData, LevelData, VoxelData};
pub use read::*;
pub use settings::{AivWeighting, RecordedSettings};

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::util::LiveTemp;

/// The file's first eight bytes.
pub const MAGIC: [u8; 8] = [0x89, b'A', b'G', b'G', b'\r', b'\n', 0x1a, b'\n'];
/// The format version this build writes. Readers accept any minor of their major.
pub const MAJOR: u16 = 1;
/// The minor version this build writes.
pub const MINOR: u16 = 8;
/// Bytes of the fixed header.
pub const HEADER_SIZE: usize = 64;
/// Alignment of every blob.
pub const ALIGN: u64 = 64;
/// FlatBuffer identifiers of the index and of blocks.
pub const INDEX_ID: &str = "AGGI";
/// See [`INDEX_ID`].
pub const BLOCK_ID: &str = "AGGB";
/// The first four bytes of a Zstandard frame (RFC 8878): from format 1.5 a block blob may be
/// one frame whose content is the block's FlatBuffer. A FlatBuffer never starts with them (its
/// first four bytes are a small root offset), so the two are told apart by these bytes alone.
pub const ZSTD_MAGIC: [u8; 4] = [0x28, 0xb5, 0x2f, 0xfd];
/// The largest block a compressed blob may inflate to (its frame must state its size).
pub const MAX_BLOCK_BYTES: u64 = 1 << 30;
/// The Zstandard level blocks are written with by default (`--compression-level`): measured
/// on the maple at 64³ (whole file), level 9 gives 2.10× in 0.3 s, 15 gives 2.15× in 2.9 s,
/// 19 gives 2.23× in 8.7 s, 22 no more than 19.
pub const DEFAULT_COMPRESSION: i32 = 19;

/// A block's FlatBuffer compressed as one Zstandard frame (with its content size, which
/// readers require), or `None` when compression would not make it smaller.
///
/// From format 1.6 the frame holds the block in byte planes ([`planar`]); from 1.8 with the
/// fields a reader recomputes left out ([`planar::derived`]), after
/// [`planar::DERIVED_MAGIC`] and the flags byte. The blob is checked to inflate to `block`
/// before it is returned; were it not (a block the bake did not build), the 1.6 planes are
/// written instead.
pub fn compress_block(block: &[u8], level: i32) -> Option<Vec<u8>> {
    let mut c = zstd::bulk::Compressor::new(level).ok()?;
    c.include_contentsize(true).ok()?;
    c.include_checksum(false).ok()?;
    let (flags, planes) = planar::to_derived_planes(block);
    let mut back = planes.clone();
    let out = if planar::from_derived_planes(&mut back, flags, &read::verifier_options()).is_ok()
        && back == block
    {
        let mut out = planar::DERIVED_MAGIC.to_vec();
        out.push(flags);
        out.extend(c.compress(&planes).ok()?);
        out
    } else {
        let mut out = planar::PLANAR_MAGIC.to_vec();
        out.extend(c.compress(&planar::to_planes(block)).ok()?);
        out
    };
    (out.len() < block.len()).then_some(out)
}

/// Whether a stored blob is coded (a Zstandard frame, a planar or a derived planar one)
/// rather than the block's FlatBuffer itself.
pub fn is_coded(stored: &[u8]) -> bool {
    stored.starts_with(&ZSTD_MAGIC)
        || stored.starts_with(&planar::PLANAR_MAGIC)
        || stored.starts_with(&planar::DERIVED_MAGIC)
}

/// A level's voxel keys as the index stores them (`Level.voxel_keys`): the LEB128 varints of
/// the differences of the ascending keys (the first from 0), in one Zstandard frame at
/// `level` that states its content size; `None` if Zstandard fails (the file then has no keys,
/// and readers take them from the blocks).
pub fn encode_voxel_keys(keys: impl IntoIterator<Item = u64>, level: i32) -> Option<Vec<u8>> {
    let mut raw = Vec::new();
    let mut prev = 0u64;
    for k in keys {
        let mut d = k.wrapping_sub(prev);
        prev = k;
        loop {
            let byte = (d & 0x7f) as u8;
            d >>= 7;
            if d == 0 {
                raw.push(byte);
                break;
            }
            raw.push(byte | 0x80);
        }
    }
    let mut c = zstd::bulk::Compressor::new(level.max(1)).ok()?;
    c.include_contentsize(true).ok()?;
    c.include_checksum(false).ok()?;
    c.compress(&raw).ok()
}

/// The keys [`encode_voxel_keys`] stored, given how many there must be: strictly ascending,
/// each below `limit` (the level's voxel count), or an error saying what is wrong.
pub fn decode_voxel_keys(bytes: &[u8], count: u64, limit: u64) -> Result<Vec<u64>, String> {
    // At most 10 varint bytes per key.
    let most = count.saturating_mul(10).min(MAX_BLOCK_BYTES);
    let size = match zstd::zstd_safe::get_frame_content_size(bytes) {
        Ok(Some(n)) if n <= most => n as usize,
        Ok(Some(n)) => return Err(format!("voxel keys inflate to {n} bytes for {count} keys")),
        _ => return Err("voxel keys without a readable content size".into()),
    };
    let raw = zstd::bulk::decompress(bytes, size).map_err(|e| format!("voxel keys: {e}"))?;
    if raw.len() != size {
        return Err("voxel keys inflate to fewer bytes than their frame says".into());
    }
    let mut keys = Vec::with_capacity(count as usize);
    let (mut prev, mut d, mut shift) = (0u64, 0u64, 0u32);
    for &b in &raw {
        if shift > 63 || (shift == 63 && b & 0x7e != 0) {
            return Err("voxel keys: a varint overflows".into());
        }
        d |= ((b & 0x7f) as u64) << shift;
        if b & 0x80 != 0 {
            shift += 7;
            continue;
        }
        let k = prev.checked_add(d).ok_or("voxel keys: a key overflows")?;
        if (!keys.is_empty() && d == 0) || k >= limit {
            return Err(format!("voxel keys: key {k} repeated or out of range"));
        }
        if keys.len() as u64 == count {
            return Err(format!("voxel keys: more than {count}"));
        }
        keys.push(k);
        prev = k;
        (d, shift) = (0, 0);
    }
    if shift != 0 || keys.len() as u64 != count {
        return Err(format!("voxel keys: {} of {count}", keys.len()));
    }
    Ok(keys)
}

/// Most bytes a compressed blob may inflate to per stored byte (the blocks of the shared
/// assets inflate 2–3×); with [`MAX_BLOCK_BYTES`] it bounds what a damaged size field can
/// make a reader allocate.
pub const MAX_INFLATION: u64 = 1024;

/// Every block blob of a whole file as stored, level by level, voxel blocks before face
/// blocks (for tools that study the coding; readers go through [`Aggregate`]). The header and
/// the index are checked; the blobs are not.
pub fn stored_blocks(bytes: &[u8]) -> Result<Vec<&[u8]>, String> {
    let h = Header::parse(bytes).map_err(|e| e.to_string())?;
    let index = bytes
        .get(h.index_offset as usize..(h.index_offset + h.index_size) as usize)
        .ok_or("the index lies beyond the file")?;
    let index = flatbuffers::root::<fb::Index>(index).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for lv in index.levels().iter().flatten() {
        for r in lv
            .voxel_blocks()
            .iter()
            .flatten()
            .chain(lv.face_blocks().iter().flatten())
        {
            let at = r.offset() as usize..(r.offset() + r.size()) as usize;
            out.push(bytes.get(at).ok_or("a block lies beyond the file")?);
        }
    }
    Ok(out)
}

/// The FlatBuffer inside a compressed blob: its frame must state a content size of at most
/// [`MAX_BLOCK_BYTES`] and [`MAX_INFLATION`] times its own, and inflate to exactly that many
/// bytes.
pub fn inflate_block(blob: &[u8]) -> Result<Vec<u8>, String> {
    if let Some(frame) = blob.strip_prefix(&planar::PLANAR_MAGIC) {
        let mut out = inflate_frame(frame)?;
        planar::from_planes(&mut out, &read::verifier_options())?;
        return Ok(out);
    }
    if let Some(rest) = blob.strip_prefix(&planar::DERIVED_MAGIC) {
        let (&flags, frame) = rest
            .split_first()
            .ok_or("derived planar block without its flags")?;
        let mut out = inflate_frame(frame)?;
        planar::from_derived_planes(&mut out, flags, &read::verifier_options())?;
        return Ok(out);
    }
    inflate_frame(blob)
}

/// One Zstandard frame's content, within the limits of [`inflate_block`].
fn inflate_frame(blob: &[u8]) -> Result<Vec<u8>, String> {
    let limit = MAX_BLOCK_BYTES.min(MAX_INFLATION * blob.len() as u64);
    let size = match zstd::zstd_safe::get_frame_content_size(blob) {
        Ok(Some(n)) if n <= limit => n as usize,
        Ok(Some(n)) => return Err(format!("compressed block inflates to {n} bytes")),
        _ => return Err("compressed block without a readable content size".into()),
    };
    thread_local! {
        /// One decompression context per thread (creating one per block was 1.6% of a near
        /// view's first frame).
        static INFLATER: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
            const { std::cell::RefCell::new(None) };
    }
    let out = INFLATER
        .with(|d| {
            let mut d = d.borrow_mut();
            if d.is_none() {
                *d = Some(zstd::bulk::Decompressor::new()?);
            }
            d.as_mut().expect("just made").decompress(blob, size)
        })
        .map_err(|e| format!("compressed block: {e}"))?;
    if out.len() != size {
        return Err(format!(
            "compressed block inflates to {} bytes, its frame says {size}",
            out.len()
        ));
    }
    Ok(out)
}

/// Why a file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The file does not start with the `.agg` magic.
    #[error("not an .agg file (wrong identifier)")]
    NotAggregate,
    #[error("format version {found}.x is not supported (this build reads {MAJOR}.x); use a newer aggtool")]
    /// A major version this build does not read.
    UnsupportedMajor {
        /// The file's major version.
        found: u16,
    },
    #[error("truncated: the file should have {expected} bytes but has {actual}")]
    /// The file is shorter than its header says.
    Truncated {
        /// Bytes the file should have.
        expected: u64,
        /// Bytes it has.
        actual: u64,
    },
    #[error("{extra} bytes of trailing data after the end of the aggregate ({expected} bytes)")]
    /// Bytes follow the end the header records.
    Trailing {
        /// Bytes the aggregate has.
        expected: u64,
        /// Bytes after it.
        extra: u64,
    },
    /// Damaged: a checksum, structure or invariant check failed (which one is said).
    #[error("corrupt: {0}")]
    Corrupt(String),
    /// The file could not be read.
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// The decoded fixed header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    /// Major version.
    pub major: u16,
    /// Minor version.
    pub minor: u16,
    /// Where the index blob starts.
    pub index_offset: u64,
    /// Its length.
    pub index_size: u64,
    /// The whole file's length.
    pub file_size: u64,
    /// CRC-32 of the index.
    pub index_crc32: u32,
}

impl Header {
    /// The header's 64 bytes (with its checksum).
    pub fn to_bytes(&self) -> [u8; HEADER_SIZE] {
        let mut b = [0u8; HEADER_SIZE];
        b[0..8].copy_from_slice(&MAGIC);
        b[8..10].copy_from_slice(&self.major.to_le_bytes());
        b[10..12].copy_from_slice(&self.minor.to_le_bytes());
        b[12..16].copy_from_slice(&(HEADER_SIZE as u32).to_le_bytes());
        b[16..24].copy_from_slice(&self.index_offset.to_le_bytes());
        b[24..32].copy_from_slice(&self.index_size.to_le_bytes());
        b[32..40].copy_from_slice(&self.file_size.to_le_bytes());
        b[40..44].copy_from_slice(&self.index_crc32.to_le_bytes());
        let crc = crc32fast::hash(&b[0..60]);
        b[60..64].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses and checks the header of `data` (the whole file: its length is checked against
    /// the size the header records).
    pub fn parse(data: &[u8]) -> Result<Header, FormatError> {
        Self::parse_with(data, true)
    }

    /// [`Header::parse`], optionally without the checksum (for fuzzing).
    pub fn parse_with(data: &[u8], checksum: bool) -> Result<Header, FormatError> {
        let n = data.len().min(MAGIC.len());
        if data[..n] != MAGIC[..n] {
            return Err(FormatError::NotAggregate);
        }
        let u16_at = |o: usize| u16::from_le_bytes([data[o], data[o + 1]]);
        let u32_at = |o: usize| u32::from_le_bytes(data[o..o + 4].try_into().unwrap());
        let u64_at = |o: usize| u64::from_le_bytes(data[o..o + 8].try_into().unwrap());
        if data.len() >= 12 && u16_at(8) != MAJOR {
            return Err(FormatError::UnsupportedMajor { found: u16_at(8) });
        }
        if data.len() < HEADER_SIZE {
            // The size the header would give is unknown: report what a header needs.
            return Err(FormatError::Truncated {
                expected: HEADER_SIZE as u64,
                actual: data.len() as u64,
            });
        }
        if checksum && u32_at(60) != crc32fast::hash(&data[0..60]) {
            return Err(FormatError::Corrupt("header checksum mismatch".into()));
        }
        if u32_at(12) as usize != HEADER_SIZE {
            return Err(FormatError::Corrupt(format!("header size {}", u32_at(12))));
        }
        let h = Header {
            major: u16_at(8),
            minor: u16_at(10),
            index_offset: u64_at(16),
            index_size: u64_at(24),
            file_size: u64_at(32),
            index_crc32: u32_at(40),
        };
        let len = data.len() as u64;
        if len < h.file_size {
            return Err(FormatError::Truncated {
                expected: h.file_size,
                actual: len,
            });
        }
        if len > h.file_size {
            return Err(FormatError::Trailing {
                expected: h.file_size,
                extra: len - h.file_size,
            });
        }
        let end = h.index_offset.checked_add(h.index_size);
        if h.index_offset < HEADER_SIZE as u64 || end != Some(h.file_size) {
            return Err(FormatError::Corrupt(format!(
                "index at {}+{} in a file of {} bytes",
                h.index_offset, h.index_size, h.file_size
            )));
        }
        Ok(h)
    }
}

/// Streams blobs into a temporary file beside the destination; [`Writer::finish`] writes the
/// index and the header and renames the file into place. Dropped unfinished, it removes the
/// temporary file and leaves any existing file untouched.
pub struct Writer {
    file: Option<BufWriter<File>>,
    tmp: LiveTemp,
    dest: PathBuf,
    pos: u64,
    /// Zstandard level of [`Writer::write_block`] (0: blocks stored as they are).
    compression: i32,
}

/// A temporary file beside `dest` (its folder created if needed), named after it (`fallback`
/// when `dest` has no file name), for writes that are renamed into place when complete;
/// registered for removal on SIGTERM and SIGINT while it lives
/// ([`crate::util::LiveTemp`]).
pub(crate) fn temp_beside(
    dest: &Path,
    fallback: &str,
) -> std::io::Result<(LiveTemp, BufWriter<File>)> {
    let dir = dest
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let name = dest
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or(fallback);
    let tmp = LiveTemp::register(dir.join(format!(".{name}.{}.tmp", std::process::id())));
    let file = BufWriter::with_capacity(1 << 20, File::create(tmp.path())?);
    Ok((tmp, file))
}

impl Writer {
    /// Starts writing `dest` (through a temporary file beside it).
    pub fn create(dest: &Path) -> std::io::Result<Writer> {
        let (tmp, mut file) = temp_beside(dest, "out.agg")?;
        file.write_all(&[0u8; HEADER_SIZE])?;
        Ok(Writer {
            file: Some(file),
            tmp,
            dest: dest.to_path_buf(),
            pos: HEADER_SIZE as u64,
            compression: 0,
        })
    }

    /// Compresses the blocks [`Writer::write_block`] writes from now on at this Zstandard
    /// level (1 to 22; 0 stores them as they are).
    pub fn set_compression(&mut self, level: i32) {
        self.compression = level;
    }

    /// Appends a block's FlatBuffer, compressed (format 1.5) where that makes it smaller and
    /// compression is on ([`Writer::set_compression`]). The returned reference's CRC-32 is of
    /// the stored bytes.
    pub fn write_block(
        &mut self,
        block: &[u8],
        first_key: u64,
        last_key: u64,
        count: u32,
    ) -> std::io::Result<fb::BlobRef> {
        if self.compression > 0 {
            if let Some(z) = compress_block(block, self.compression) {
                return self.write_blob(&z, first_key, last_key, count);
            }
        }
        self.write_blob(block, first_key, last_key, count)
    }

    /// Appends a blob at the next aligned offset.
    pub fn write_blob(
        &mut self,
        bytes: &[u8],
        first_key: u64,
        last_key: u64,
        count: u32,
    ) -> std::io::Result<fb::BlobRef> {
        let file = self.file.as_mut().expect("writer already finished");
        let pad = (ALIGN - self.pos % ALIGN) % ALIGN;
        file.write_all(&[0u8; ALIGN as usize][..pad as usize])?;
        self.pos += pad;
        let offset = self.pos;
        file.write_all(bytes)?;
        self.pos += bytes.len() as u64;
        Ok(fb::BlobRef::new(
            offset,
            bytes.len() as u64,
            first_key,
            last_key,
            count,
            crc32fast::hash(bytes),
        ))
    }

    /// Writes the index and the header, syncs, and renames into place. Returns the file size.
    pub fn finish(mut self, index: &[u8]) -> std::io::Result<u64> {
        let result = self.finish_inner(index);
        if result.is_err() {
            self.file = None;
            let _ = std::fs::remove_file(self.tmp.path());
        }
        result
    }

    fn finish_inner(&mut self, index: &[u8]) -> std::io::Result<u64> {
        let r = self.write_blob(index, 0, 0, 0)?;
        let mut file = self.file.take().expect("writer already finished");
        let header = Header {
            major: MAJOR,
            minor: MINOR,
            index_offset: r.offset(),
            index_size: r.size(),
            file_size: self.pos,
            index_crc32: r.crc32(),
        };
        file.seek(SeekFrom::Start(0))?;
        file.write_all(&header.to_bytes())?;
        let file = file.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(self.tmp.path(), &self.dest)?;
        Ok(self.pos)
    }
}

impl Drop for Writer {
    fn drop(&mut self) {
        // Unfinished (or failed): the temporary file goes, the destination is untouched.
        if self.file.take().is_some() {
            let _ = std::fs::remove_file(self.tmp.path());
        }
    }
}

#[cfg(test)]
mod voxel_keys_tests {
    use super::{decode_voxel_keys, encode_voxel_keys};

    /// Keys round-trip, large gaps and key 0 included; damaged or inconsistent key bytes are
    /// refused with a reason, never a panic.
    #[test]
    fn voxel_keys_round_trip_and_refuse_damage() {
        let keys: Vec<u64> = vec![0, 1, 2, 300, 70_000, (1 << 40) + 5, (1 << 62) - 1];
        let limit = 1u64 << 62;
        let bytes = encode_voxel_keys(keys.iter().copied(), 19).unwrap();
        assert_eq!(
            decode_voxel_keys(&bytes, keys.len() as u64, limit).unwrap(),
            keys
        );
        assert_eq!(
            decode_voxel_keys(&encode_voxel_keys([], 3).unwrap(), 0, limit).unwrap(),
            Vec::<u64>::new()
        );
        // Wrong count, a key out of range, a repeated key, a truncated or damaged frame.
        assert!(decode_voxel_keys(&bytes, 6, limit).is_err());
        assert!(decode_voxel_keys(&bytes, 8, limit).is_err());
        assert!(decode_voxel_keys(&bytes, 7, 1 << 40).is_err());
        let repeated = encode_voxel_keys([3, 3], 3).unwrap();
        assert!(decode_voxel_keys(&repeated, 2, limit).is_err());
        assert!(decode_voxel_keys(&bytes[..bytes.len() - 3], 7, limit).is_err());
        assert!(decode_voxel_keys(&[], 0, limit).is_err());
        let mut flipped = bytes.clone();
        for i in 0..flipped.len() {
            flipped[i] ^= 0xa5;
            let _ = decode_voxel_keys(&flipped, 7, limit);
            flipped[i] ^= 0xa5;
        }
        // A varint longer than 64 bits.
        let mut c = zstd::bulk::Compressor::new(3).unwrap();
        c.include_contentsize(true).unwrap();
        let overlong = c.compress(&[0xff; 11]).unwrap();
        assert!(decode_voxel_keys(&overlong, 1, u64::MAX).is_err());
    }
}
