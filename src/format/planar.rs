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
