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

/// The (offset, length in bytes, element size) of every vector of `block` that is stored in
/// planes, in the order of the schema's fields. `buf` is the buffer `block` was read from.
fn vectors(buf: &[u8], block: &fb::Block) -> Vec<(usize, usize, usize)> {
    let base = buf.as_ptr() as usize;
    let mut out = Vec::with_capacity(14);
    let mut add = |bytes: Option<&[u8]>, stride: usize| {
        if let Some(b) = bytes {
            if stride > 1 && !b.is_empty() {
                out.push((b.as_ptr() as usize - base, b.len(), stride));
            }
        }
    };
    use std::mem::size_of;
    add(block.keys().map(|v| v.bytes()), size_of::<u64>());
    add(block.voxels().map(|v| v.bytes()), size_of::<fb::Voxel>());
    add(block.lobes().map(|v| v.bytes()), size_of::<fb::Lobe>());
    add(block.moments().map(|v| v.bytes()), size_of::<fb::Moments>());
    add(
        block.dielectric_moments().map(|v| v.bytes()),
        size_of::<fb::DielectricMoments>(),
    );
    add(
        block.aiv_nodes().map(|v| v.bytes()),
        size_of::<fb::HaarNode>(),
    );
    add(block.faces().map(|v| v.bytes()), size_of::<fb::Face>());
    add(
        block.abv_nodes().map(|v| v.bytes()),
        size_of::<fb::HaarNode>(),
    );
    add(block.exposure().map(|v| v.bytes()), size_of::<f32>());
    add(block.qlobes().map(|v| v.bytes()), size_of::<fb::QLobe>());
    add(
        block.qmoments().map(|v| v.bytes()),
        size_of::<fb::QMoments>(),
    );
    add(
        block.qdielectric_moments().map(|v| v.bytes()),
        size_of::<fb::QDielectricMoments>(),
    );
    add(
        block.aiv_qnodes().map(|v| v.bytes()),
        size_of::<fb::QHaarNode>(),
    );
    add(
        block.abv_qnodes().map(|v| v.bytes()),
        size_of::<fb::QHaarNode>(),
    );
    out
}

/// Transposes `len` bytes at `at` of `buf` from elements of `stride` bytes into planes
/// (`forward`) or back.
fn transpose(
    buf: &mut [u8],
    at: usize,
    len: usize,
    stride: usize,
    forward: bool,
    tmp: &mut Vec<u8>,
) {
    let n = len / stride;
    let src = &buf[at..at + n * stride];
    tmp.clear();
    tmp.resize(n * stride, 0);
    for i in 0..n {
        for k in 0..stride {
            if forward {
                tmp[k * n + i] = src[i * stride + k];
            } else {
                tmp[i * stride + k] = src[k * n + i];
            }
        }
    }
    buf[at..at + n * stride].copy_from_slice(tmp);
}

/// The block FlatBuffer `block` (as the bake built it) with its vectors in planes.
pub fn to_planes(block: &[u8]) -> Vec<u8> {
    let mut out = block.to_vec();
    // The bake's own buffer: verified all the same, it costs little and trusts nothing.
    let Ok(b) = flatbuffers::root::<fb::Block>(block) else {
        return out;
    };
    let mut tmp = Vec::new();
    for (at, len, stride) in vectors(block, &b) {
        transpose(&mut out, at, len, stride, true, &mut tmp);
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
    for (at, len, stride) in spans {
        transpose(buf, at, len, stride, false, &mut tmp);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
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
