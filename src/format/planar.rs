//! Planar blocks (format 1.6): before Zstandard, every vector of a block's FlatBuffer whose
//! elements are wider than a byte is transposed into byte planes (byte 0 of every element,
//! then byte 1, ...), so that the slowly varying high bytes of keys, quantized coefficients,
//! halves and indices sit together and the entropy coder sees runs instead of interleaved
//! noise. The table, its vtable and every offset stay where they were, so a reader finds the
//! vectors in the planar buffer (after the FlatBuffers verifier has bounded them) and turns
//! them back in place; the block it then checks and reads zero-copy is the FlatBuffer the
//! bake built, byte for byte.
//!
//! Measured on the maple's default 64³ file (`tools/src/bin/stream_probe.rs`, Zstandard 19):
//! the blocks take 0.875 of their bytes as whole FlatBuffers (10.81 → 9.45 MB); the deltas of
//! the sorted keys and of the faces' coordinates add nothing measurable (0.874), so they are
//! not done.
//!
//! A planar blob is [`PLANAR_MAGIC`] followed by one Zstandard frame (with its content size)
//! of the planar FlatBuffer. Its first four bytes read as a FlatBuffer's root offset would
//! point beyond any block a reader accepts, and they are not a Zstandard frame's magic, so a
//! 1.5 reader refuses such a blob as damaged instead of misreading it.

use super::fb;

/// The first four bytes of a planar blob (format 1.6).
pub const PLANAR_MAGIC: [u8; 4] = [0xa6, 0x67, 0x67, 0xf1];

/// What a vector of a block holds, as far as the derived fields of format 1.8 care.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Kind {
    Plain,
    Voxels,
    Faces,
    /// Haar trees: quantized (`QHaarNode`) or not, and the AIV's or the ABV's.
    Trees {
        quantized: bool,
        aiv: bool,
    },
}

/// One vector of a block stored in planes: where it is in the buffer, its length in bytes,
/// its element size and what it holds.
#[derive(Clone, Copy, Debug)]
struct Span {
    at: usize,
    len: usize,
    stride: usize,
    kind: Kind,
}

/// Every vector of `block` that is stored in planes, in the order of the schema's fields.
/// `buf` is the buffer `block` was read from.
fn vectors(buf: &[u8], block: &fb::Block) -> Vec<Span> {
    let base = buf.as_ptr() as usize;
    let mut out = Vec::with_capacity(14);
    let mut add = |bytes: Option<&[u8]>, stride: usize, kind: Kind| {
        if let Some(b) = bytes {
            if stride > 1 && !b.is_empty() {
                out.push(Span {
                    at: b.as_ptr() as usize - base,
                    len: b.len(),
                    stride,
                    kind,
                });
            }
        }
    };
    use std::mem::size_of;
    use Kind::*;
    add(block.keys().map(|v| v.bytes()), size_of::<u64>(), Plain);
    add(
        block.voxels().map(|v| v.bytes()),
        size_of::<fb::Voxel>(),
        Voxels,
    );
    add(
        block.lobes().map(|v| v.bytes()),
        size_of::<fb::Lobe>(),
        Plain,
    );
    add(
        block.moments().map(|v| v.bytes()),
        size_of::<fb::Moments>(),
        Plain,
    );
    add(
        block.dielectric_moments().map(|v| v.bytes()),
        size_of::<fb::DielectricMoments>(),
        Plain,
    );
    let (float, quantized) = (false, true);
    add(
        block.aiv_nodes().map(|v| v.bytes()),
        size_of::<fb::HaarNode>(),
        Trees {
            quantized: float,
            aiv: true,
        },
    );
    add(
        block.faces().map(|v| v.bytes()),
        size_of::<fb::Face>(),
        Faces,
    );
    add(
        block.abv_nodes().map(|v| v.bytes()),
        size_of::<fb::HaarNode>(),
        Trees {
            quantized: float,
            aiv: false,
        },
    );
    add(block.exposure().map(|v| v.bytes()), size_of::<f32>(), Plain);
    add(
        block.qlobes().map(|v| v.bytes()),
        size_of::<fb::QLobe>(),
        Plain,
    );
    add(
        block.qmoments().map(|v| v.bytes()),
        size_of::<fb::QMoments>(),
        Plain,
    );
    add(
        block.qdielectric_moments().map(|v| v.bytes()),
        size_of::<fb::QDielectricMoments>(),
        Plain,
    );
    add(
        block.aiv_qnodes().map(|v| v.bytes()),
        size_of::<fb::QHaarNode>(),
        Trees {
            quantized,
            aiv: true,
        },
    );
    add(
        block.abv_qnodes().map(|v| v.bytes()),
        size_of::<fb::QHaarNode>(),
        Trees {
            quantized,
            aiv: false,
        },
    );
    out
}

/// Transposes `len` bytes at `at` of `buf` from elements of `stride` bytes into planes
/// (`forward`) or back. Eight elements at a time, so that each plane is read or written a
/// machine word at a time and the loops carry no branch: about twice the speed of a byte
/// loop (0.09 against 0.17 ms for 300 kB, strides 4 to 100), which mattered because every
/// block a render loads passes through here after Zstandard.
fn transpose(
    buf: &mut [u8],
    at: usize,
    len: usize,
    stride: usize,
    forward: bool,
    tmp: &mut Vec<u8>,
) {
    let n = len / stride;
    let span = &mut buf[at..at + n * stride];
    tmp.clear();
    tmp.extend_from_slice(span);
    if forward {
        elements_to_planes(tmp, span, stride);
    } else {
        planes_to_elements(tmp, span, stride);
    }
}

/// Writes the `elems.len() / stride` elements of `elems` into `out` as byte planes.
fn elements_to_planes(elems: &[u8], out: &mut [u8], stride: usize) {
    let n = elems.len() / stride;
    let full = n / 8 * 8;
    for i in (0..full).step_by(8) {
        let e = &elems[i * stride..(i + 8) * stride];
        for k in 0..stride {
            let w = (0..8).fold(0u64, |w, j| w | (e[j * stride + k] as u64) << (8 * j));
            out[k * n + i..k * n + i + 8].copy_from_slice(&w.to_le_bytes());
        }
    }
    for i in full..n {
        for k in 0..stride {
            out[k * n + i] = elems[i * stride + k];
        }
    }
}

/// Writes the byte planes of `planes` (`stride` planes) back into `out` as elements.
fn planes_to_elements(planes: &[u8], out: &mut [u8], stride: usize) {
    let n = planes.len() / stride;
    let full = n / 8 * 8;
    for i in (0..full).step_by(8) {
        let o = &mut out[i * stride..(i + 8) * stride];
        for k in 0..stride {
            let mut w = [0u8; 8];
            w.copy_from_slice(&planes[k * n + i..k * n + i + 8]);
            for (j, b) in w.into_iter().enumerate() {
                o[j * stride + k] = b;
            }
        }
    }
    for i in full..n {
        for k in 0..stride {
            out[i * stride + k] = planes[k * n + i];
        }
    }
}

/// The block FlatBuffer `block` (as the bake built it) with its vectors in planes.
pub fn to_planes(block: &[u8]) -> Vec<u8> {
    let mut out = block.to_vec();
    // The bake's own buffer: verified all the same, it costs little and trusts nothing.
    let Ok(b) = flatbuffers::root::<fb::Block>(block) else {
        return out;
    };
    let mut tmp = Vec::new();
    for v in vectors(block, &b) {
        transpose(&mut out, v.at, v.len, v.stride, true, &mut tmp);
    }
    out
}

/// Turns a planar block back into its FlatBuffer, in place. The buffer's structure is
/// verified first (the vectors' bounds come from it); an error says why it is not a block.
pub fn from_planes(buf: &mut [u8], opts: &flatbuffers::VerifierOptions) -> Result<(), String> {
    let spans = {
        let b = flatbuffers::root_with_opts::<fb::Block>(opts, buf)
            .map_err(|e| format!("planar block: {e}"))?;
        vectors(buf, &b)
    };
    let mut tmp = Vec::new();
    for v in spans {
        transpose(buf, v.at, v.len, v.stride, false, &mut tmp);
    }
    Ok(())
}

/// The first four bytes of a derived planar blob (format 1.8): one byte of [`derived`] flags
/// follows, then one Zstandard frame (with its content size) of the planar FlatBuffer with
/// the fields the flags name left out (zeroed). A 1.6 or 1.7 reader refuses it as damaged, as
/// a 1.5 reader refuses a planar one.
pub const DERIVED_MAGIC: [u8; 4] = [0xa6, 0x67, 0x67, 0xf2];

/// What a derived planar blob leaves out, for the reader to recompute (format 1.8). Each is
/// left out only where the block's bytes are what the reader recomputes, so the block a
/// reader ends with is the FlatBuffer the bake built, byte for byte.
///
/// Measured on the maple's default 64³ file: 9,388,960 bytes in 1.7, 8,619,936 (0.918) with
/// the derived fields left out, decoding at 0.8 of 1.7's speed (the counts are recomputed).
/// Storing the trees' details by subband as well (every root first, then every node of depth
/// 1, ...) gave 8,524,640 (0.908) but halved the decoding speed (the permutation), so it is
/// not done; `tools/src/bin/stream_probe.rs` measures both.
pub mod derived {
    /// Every voxel's `lobe_start`: the sum of the `lobe_count`s of the voxels before it.
    pub const LOBE_START: u8 = 1;
    /// Every voxel's `moment_start`, likewise from `moment_count`.
    pub const MOMENT_START: u8 = 2;
    /// Every voxel's `aiv_start`, likewise from `aiv_count`.
    pub const AIV_START: u8 = 4;
    /// Every face's `abv_start`, likewise from `abv_count`.
    pub const ABV_START: u8 = 8;
    /// The AIV trees (`aiv_qnodes` or `aiv_nodes`), stored back to back in preorder: their
    /// subtree counts follow from the child masks and are left out.
    pub const AIV_TREES: u8 = 16;
    /// The ABV trees (`abv_qnodes` or `abv_nodes`), as [`AIV_TREES`].
    pub const ABV_TREES: u8 = 32;
    /// Every flag a 1.8 reader knows; a blob with another is refused.
    pub const ALL: u8 = 63;
}

/// Byte offsets of a (start, count) pair of u32 fields in `Voxel` and `Face` (checked against
/// the generated structs by a test).
const VOXEL_LOBES: (usize, usize) = (68, 72);
const VOXEL_MOMENTS: (usize, usize) = (76, 80);
const VOXEL_AIV: (usize, usize) = (88, 92);
const FACE_ABV: (usize, usize) = (16, 20);

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// Whether the u32 `start` of every `stride`-byte element of `elems` is the (wrapping) sum
/// of the u32 `count` of the elements before it.
fn starts_are_running_sums(elems: &[u8], stride: usize, (start, count): (usize, usize)) -> bool {
    let mut sum = 0u32;
    elems.chunks_exact(stride).all(|e| {
        let ok = u32_at(e, start) == sum;
        sum = sum.wrapping_add(u32_at(e, count));
        ok
    })
}

/// Writes the running sums of [`starts_are_running_sums`] into the `start` fields, or zeroes
/// them (`clear`).
fn write_starts(elems: &mut [u8], stride: usize, (start, count): (usize, usize), clear: bool) {
    let mut sum = 0u32;
    for e in elems.chunks_exact_mut(stride) {
        let v = if clear { 0 } else { sum };
        e[start..start + 4].copy_from_slice(&v.to_le_bytes());
        sum = sum.wrapping_add(u32_at(e, count));
    }
}

/// The start fields of a span's elements that [`derived`] flags may leave out.
fn start_fields(kind: Kind) -> &'static [(u8, (usize, usize))] {
    match kind {
        Kind::Voxels => &[
            (derived::LOBE_START, VOXEL_LOBES),
            (derived::MOMENT_START, VOXEL_MOMENTS),
            (derived::AIV_START, VOXEL_AIV),
        ],
        Kind::Faces => &[(derived::ABV_START, FACE_ABV)],
        _ => &[],
    }
}

/// Node `i`'s stored subtree count.
fn subtree(planes: &[u8], n: usize, i: usize, quantized: bool) -> u32 {
    if quantized {
        planes[i] as u32 | ((planes[n + i] & 0x0f) as u32) << 8
    } else {
        u32::from_le_bytes([
            planes[12 * n + i],
            planes[13 * n + i],
            planes[14 * n + i],
            planes[15 * n + i],
        ])
    }
}

/// Writes node `i`'s subtree count (0 clears it).
fn set_subtree(planes: &mut [u8], n: usize, i: usize, quantized: bool, v: u32) {
    if quantized {
        planes[i] = v as u8;
        planes[n + i] = (planes[n + i] & 0xf0) | ((v >> 8) as u8 & 0x0f);
    } else {
        for (k, b) in v.to_le_bytes().into_iter().enumerate() {
            planes[(12 + k) * n + i] = b;
        }
    }
}

/// The subtree counts of trees stored back to back in preorder, from their child masks
/// alone: `WRITE` stores them in the nodes; otherwise whether every stored count is the one
/// the masks imply. An error if the last tree runs past the vector, or a quantized subtree
/// holds more nodes than its 12 bits count.
///
/// Backwards, as prefix notation is evaluated, with no branch that a mask decides: a node's
/// count is one more than the sum of its children's, which are the top `children` entries of
/// a stack of finished subtrees; kept as running sums, that is one subtraction. A stack that
/// would go below zero is a tree that runs past the vector.
fn subtree_counts<const WRITE: bool>(
    planes: &mut [u8],
    n: usize,
    quantized: bool,
    scratch: &mut Scratch,
) -> Result<bool, String> {
    // Children per mask (the build's baseline has no popcount instruction).
    const CHILDREN: [u8; 16] = [0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4];
    let masks = if quantized {
        &planes[n..2 * n]
    } else {
        &planes[16 * n..17 * n]
    };
    let shift = if quantized { 4 } else { 0 };
    // sums[k]: the node count of the first k finished subtrees on the stack.
    let Scratch { sums, size } = scratch;
    sums.clear();
    sums.resize(n + 1, 0);
    size.clear();
    size.resize(n, 0);
    let (mut top, mut underflow) = (0usize, false);
    for i in (0..n).rev() {
        let children = CHILDREN[((masks[i] >> shift) & 0x0f) as usize] as usize;
        underflow |= children > top;
        let t = top.saturating_sub(children);
        let s = 1 + sums[top] - sums[t];
        size[i] = s;
        sums[t + 1] = sums[t] + s;
        top = t + 1;
    }
    if underflow {
        return Err("a Haar tree runs past its vector".into());
    }
    let largest = size.iter().copied().max().unwrap_or(0);
    if quantized && largest > 0x0fff {
        return Err(format!("a quantized Haar tree of {largest} nodes"));
    }
    if !WRITE {
        return Ok((0..n).all(|i| subtree(planes, n, i, quantized) == size[i]));
    }
    if quantized {
        let (lo, rest) = planes.split_at_mut(n);
        for ((l, h), &s) in lo.iter_mut().zip(&mut rest[..n]).zip(size.iter()) {
            *l = s as u8;
            *h = (*h & 0xf0) | (s >> 8) as u8 & 0x0f;
        }
    } else {
        for (i, &s) in size.iter().enumerate() {
            set_subtree(planes, n, i, false, s);
        }
    }
    Ok(true)
}

/// Reusable buffers of [`subtree_counts`].
#[derive(Default)]
struct Scratch {
    sums: Vec<u32>,
    size: Vec<u32>,
}

/// Leaves a tree vector's subtree counts out, if they are what the masks imply; whether it
/// did.
fn derive_trees(planes: &mut [u8], n: usize, quantized: bool, scratch: &mut Scratch) -> bool {
    if subtree_counts::<false>(planes, n, quantized, scratch) != Ok(true) {
        return false;
    }
    for i in 0..n {
        set_subtree(planes, n, i, quantized, 0);
    }
    true
}

/// The block FlatBuffer `block` in planes with every field [`derived`] allows left out: the
/// flags of those left out, and the buffer. [`from_derived_planes`] gives `block` back.
pub fn to_derived_planes(block: &[u8]) -> (u8, Vec<u8>) {
    let mut out = block.to_vec();
    let Ok(b) = flatbuffers::root::<fb::Block>(block) else {
        return (0, out);
    };
    let spans = vectors(block, &b);
    let mut flags = 0u8;
    let (mut tmp, mut scratch) = (Vec::new(), Scratch::default());
    for v in &spans {
        let elems = &mut out[v.at..v.at + v.len];
        for &(bit, field) in start_fields(v.kind) {
            if starts_are_running_sums(elems, v.stride, field) {
                write_starts(elems, v.stride, field, true);
                flags |= bit;
            }
        }
        transpose(&mut out, v.at, v.len, v.stride, true, &mut tmp);
    }
    // A block holds one layout of each kind of tree; both would share one flag.
    let trees = |aiv: bool| {
        spans
            .iter()
            .filter(|v| matches!(v.kind, Kind::Trees { aiv: a, .. } if a == aiv))
            .count()
    };
    for v in &spans {
        if let Kind::Trees { quantized, aiv } = v.kind {
            let n = v.len / v.stride;
            if trees(aiv) == 1
                && derive_trees(&mut out[v.at..v.at + v.len], n, quantized, &mut scratch)
            {
                flags |= if aiv {
                    derived::AIV_TREES
                } else {
                    derived::ABV_TREES
                };
            }
        }
    }
    (flags, out)
}

/// Turns a derived planar block back into its FlatBuffer, in place: verifies its structure,
/// recomputes the fields `flags` names and transposes the planes back. An error says why it
/// is not a block.
pub fn from_derived_planes(
    buf: &mut [u8],
    flags: u8,
    opts: &flatbuffers::VerifierOptions,
) -> Result<(), String> {
    if flags & !derived::ALL != 0 {
        return Err(format!(
            "derived planar block with unknown flags {flags:#04x}"
        ));
    }
    let spans = {
        let b = flatbuffers::root_with_opts::<fb::Block>(opts, buf)
            .map_err(|e| format!("planar block: {e}"))?;
        vectors(buf, &b)
    };
    thread_local! {
        static SCRATCH: std::cell::RefCell<Scratch> = Default::default();
    }
    for v in &spans {
        if let Kind::Trees { quantized, aiv } = v.kind {
            let bit = if aiv {
                derived::AIV_TREES
            } else {
                derived::ABV_TREES
            };
            if flags & bit != 0 {
                let n = v.len / v.stride;
                let span = &mut buf[v.at..v.at + v.len];
                SCRATCH.with_borrow_mut(|s| subtree_counts::<true>(span, n, quantized, s))?;
            }
        }
    }
    let mut tmp = Vec::new();
    for v in &spans {
        transpose(buf, v.at, v.len, v.stride, false, &mut tmp);
        for &(bit, field) in start_fields(v.kind) {
            if flags & bit != 0 {
                write_starts(&mut buf[v.at..v.at + v.len], v.stride, field, false);
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    /// The word-at-a-time transposes agree with the definition (byte k of element i is byte
    /// i of plane k) for every stride the format uses and counts around the eight-element
    /// steps, and they are each other's inverse.
    #[test]
    fn transposes_match_the_definition() {
        for stride in [2usize, 4, 6, 8, 10, 14, 20, 22, 28, 44, 48, 100] {
            for n in [0usize, 1, 7, 8, 9, 17, 64] {
                let elems: Vec<u8> = (0..n * stride).map(|i| (i * 131 + 7) as u8).collect();
                let mut planes = vec![0u8; n * stride];
                super::elements_to_planes(&elems, &mut planes, stride);
                for i in 0..n {
                    for k in 0..stride {
                        assert_eq!(planes[k * n + i], elems[i * stride + k], "{stride} {n}");
                    }
                }
                let mut back = vec![0u8; n * stride];
                super::planes_to_elements(&planes, &mut back, stride);
                assert_eq!(back, elems);
            }
        }
    }

    use super::derived;

    /// The block FlatBuffers of a committed test file, inflated where they are stored coded.
    fn blocks_of(name: &str) -> Vec<Vec<u8>> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name);
        let bytes = std::fs::read(path).unwrap();
        let blobs = super::super::stored_blocks(&bytes).unwrap();
        blobs
            .into_iter()
            .map(|blob| {
                if super::super::is_coded(blob) {
                    super::super::inflate_block(blob).unwrap()
                } else {
                    blob.to_vec()
                }
            })
            .collect()
    }

    /// The (start, count) offsets the derived fields use are those of the generated structs.
    #[test]
    fn derived_field_offsets_match_the_structs() {
        fn at<T: Copy>(mut t: T, set: impl Fn(&mut T)) -> usize {
            set(&mut t);
            let b = unsafe {
                std::slice::from_raw_parts(&t as *const T as *const u8, std::mem::size_of::<T>())
            };
            b.windows(4)
                .position(|w| w == 0xA1B2_C3D4u32.to_le_bytes())
                .unwrap()
        }
        let m = 0xA1B2_C3D4;
        let v = super::fb::Voxel::default();
        assert_eq!(
            super::VOXEL_LOBES,
            (
                at(v, |v| v.set_lobe_start(m)),
                at(v, |v| v.set_lobe_count(m))
            )
        );
        assert_eq!(
            super::VOXEL_MOMENTS,
            (
                at(v, |v| v.set_moment_start(m)),
                at(v, |v| v.set_moment_count(m))
            )
        );
        assert_eq!(
            super::VOXEL_AIV,
            (at(v, |v| v.set_aiv_start(m)), at(v, |v| v.set_aiv_count(m)))
        );
        let f = super::fb::Face::default();
        assert_eq!(
            super::FACE_ABV,
            (at(f, |f| f.set_abv_start(m)), at(f, |f| f.set_abv_count(m)))
        );
    }

    /// Every block of the committed float (1.3) and quantized (1.4) files leaves out every
    /// derived field its kind has, and comes back byte for byte, directly and through a
    /// compressed blob.
    #[test]
    fn derived_planes_round_trip() {
        for name in ["foliage-1.3.agg", "foliage-1.4.agg"] {
            let blocks = blocks_of(name);
            assert!(blocks.len() >= 4, "{name}");
            for block in blocks {
                let b = flatbuffers::root::<super::fb::Block>(&block).unwrap();
                let want = if b.faces().is_some_and(|f| !f.is_empty()) {
                    derived::ABV_START | derived::ABV_TREES
                } else {
                    derived::LOBE_START
                        | derived::MOMENT_START
                        | derived::AIV_START
                        | derived::AIV_TREES
                };
                let (flags, mut p) = super::to_derived_planes(&block);
                assert_eq!(flags, want, "{name}");
                assert_ne!(p, block);
                super::from_derived_planes(&mut p, flags, &Default::default()).unwrap();
                assert_eq!(p, block, "{name}");
                let blob = super::super::compress_block(&block, 3).unwrap();
                assert!(blob.starts_with(&super::DERIVED_MAGIC));
                assert_eq!(blob[4], want);
                assert_eq!(super::super::inflate_block(&blob).unwrap(), block);
            }
        }
    }

    /// The subtree counts the masks imply: a forest of two trees and a chain of 300 nodes
    /// are counted; a tree that runs past its vector and a quantized one of more nodes than
    /// 12 bits count are refused, as are unknown flags.
    #[test]
    fn subtree_counts_from_masks() {
        // Quantized planes of n nodes with the given masks.
        let q = |masks: &[u8]| {
            let n = masks.len();
            let mut p = vec![0u8; 6 * n];
            for (i, m) in masks.iter().enumerate() {
                p[n + i] = m << 4;
            }
            p
        };
        let counts = |masks: &[u8]| {
            let (n, mut p) = (masks.len(), q(masks));
            super::subtree_counts::<true>(&mut p, n, true, &mut Default::default()).map(|_| {
                (0..n)
                    .map(|i| super::subtree(&p, n, i, true))
                    .collect::<Vec<_>>()
            })
        };
        // A root with two children, of which one is present.
        assert!(counts(&[0b0011, 0]).unwrap_err().contains("runs past"));
        assert_eq!(counts(&[0b0101, 0b0001, 0, 0, 0]).unwrap(), [4, 2, 1, 1, 1]);
        let chain: Vec<u8> = (0..300).map(|i| if i < 299 { 0b1000 } else { 0 }).collect();
        assert_eq!(
            counts(&chain).unwrap(),
            (1..=300).rev().collect::<Vec<u32>>()
        );
        // A full quadtree of depth 6: 5,461 nodes, more than 12 bits count.
        fn full(d: u32, out: &mut Vec<u8>) {
            out.push(if d == 0 { 0 } else { 0b1111 });
            if d > 0 {
                for _ in 0..4 {
                    full(d - 1, out);
                }
            }
        }
        let mut wide = Vec::new();
        full(6, &mut wide);
        assert!(counts(&wide).unwrap_err().contains("5461 nodes"));
        let block = &blocks_of("foliage-1.4.agg")[0];
        let (flags, mut p) = super::to_derived_planes(block);
        let e = super::from_derived_planes(&mut p, flags | 0x40, &Default::default()).unwrap_err();
        assert!(e.contains("unknown flags"), "{e}");
    }

    /// Planes and back give the same bytes; planes differ where a vector has wide elements.
    #[test]
    fn planes_round_trip() {
        for keys in [
            vec![],
            vec![7u64],
            (0..300u64).map(|k| k * 37 + 5).collect(),
        ] {
            let mut b = flatbuffers::FlatBufferBuilder::new();
            let k = b.create_vector(&keys);
            let e = b.create_vector(&vec![0.5f32; keys.len()]);
            let block = super::fb::Block::create(
                &mut b,
                &super::fb::BlockArgs {
                    level: 3,
                    keys: Some(k),
                    exposure: Some(e),
                    ..Default::default()
                },
            );
            b.finish(block, Some(super::super::BLOCK_ID));
            let fbuf = b.finished_data().to_vec();
            let mut p = super::to_planes(&fbuf);
            assert_eq!(p.len(), fbuf.len());
            if keys.len() > 1 {
                assert_ne!(p, fbuf);
            }
            super::from_planes(&mut p, &Default::default()).unwrap();
            assert_eq!(p, fbuf);
        }
    }
}
