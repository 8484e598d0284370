//! What splitting a block's fields into streams would save before Zstandard (issue 42,
//! deliverable 3), measured on an existing `.agg` without changing the format: for every
//! block, the bytes of
//! - `flatbuffer`: the block's FlatBuffer compressed whole (what format 1.5 stores);
//! - `streams`: each vector's bytes one after another, compressed together;
//! - `planes`: each vector transposed into byte planes (byte k of every element, then byte
//!   k + 1, ...), the planes one after another, compressed together;
//! - `planes+delta`: as `planes`, with the sorted Morton keys replaced by their differences
//!   and the faces' voxel coordinates by theirs to the previous face;
//!
//! and, per vector, its bytes raw and in planes compressed alone. Each at the Zstandard level
//! given (default 19, the bake's), and the speed at which the file's blocks decode as stored.
//!
//! ```sh
//! cargo run --release -p aggtool-tools --bin stream_probe -- tree.agg [LEVEL]
//! ```

use std::collections::BTreeMap;

use aggtool::format::{fb, inflate_block, Header};

fn zstd_len(bytes: &[u8], level: i32) -> usize {
    zstd::bulk::compress(bytes, level).map_or(bytes.len(), |v| v.len())
}

/// `data` as byte planes of `stride`-byte elements.
fn planes(data: &[u8], stride: usize) -> Vec<u8> {
    if stride <= 1 || data.len() % stride != 0 {
        return data.to_vec();
    }
    let n = data.len() / stride;
    let mut out = vec![0u8; data.len()];
    for (i, e) in data.chunks_exact(stride).enumerate() {
        for (k, b) in e.iter().enumerate() {
            out[k * n + i] = *b;
        }
    }
    out
}

/// Little-endian u64s replaced by their wrapping differences to the previous one.
fn delta_u64(data: &[u8]) -> Vec<u8> {
    let mut prev = 0u64;
    let mut out = Vec::with_capacity(data.len());
    for c in data.chunks_exact(8) {
        let v = u64::from_le_bytes(c.try_into().unwrap());
        out.extend_from_slice(&v.wrapping_sub(prev).to_le_bytes());
        prev = v;
    }
    out
}

/// Faces (x, y, z, dir, ... as u32 words first) with x, y, z replaced by their differences
/// to the previous face.
fn delta_faces(data: &[u8], stride: usize) -> Vec<u8> {
    let mut out = data.to_vec();
    let mut prev = [0u32; 3];
    for (i, e) in data.chunks_exact(stride).enumerate() {
        for (k, p) in prev.iter_mut().enumerate() {
            let v = u32::from_le_bytes(e[4 * k..4 * k + 4].try_into().unwrap());
            let d = v.wrapping_sub(*p);
            out[i * stride + 4 * k..i * stride + 4 * k + 4].copy_from_slice(&d.to_le_bytes());
            *p = v;
        }
    }
    out
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = args
        .get(1)
        .ok_or_else(|| anyhow::anyhow!("usage: stream_probe FILE.agg [ZSTD_LEVEL]"))?;
    let level: i32 = args.get(2).map_or(Ok(19), |s| s.parse())?;
    let bytes = std::fs::read(path)?;
    let h = Header::parse(&bytes)?;
    let index = &bytes[h.index_offset as usize..(h.index_offset + h.index_size) as usize];
    let index = flatbuffers::root::<fb::Index>(index)?;
    let mut totals: BTreeMap<&str, usize> = BTreeMap::new();
    let mut per_vector: BTreeMap<&'static str, [usize; 3]> = BTreeMap::new();
    let t0 = std::time::Instant::now();
    let mut inflated_total = 0usize;
    let mut decode_seconds = 0f64;
    for lv in index.levels().iter().flatten() {
        let (vb, fbk) = (lv.voxel_blocks(), lv.face_blocks());
        let refs: Vec<&fb::BlobRef> = vb.iter().flatten().chain(fbk.iter().flatten()).collect();
        for r in refs {
            let blob = &bytes[r.offset() as usize..(r.offset() + r.size()) as usize];
            let t = std::time::Instant::now();
            let raw = inflate_block(blob).map_err(anyhow::Error::msg)?;
            decode_seconds += t.elapsed().as_secs_f64();
            inflated_total += raw.len();
            let b = flatbuffers::root::<fb::Block>(&raw)?;
            // Each vector's bytes and element size.
            let mut vecs: Vec<(&'static str, Vec<u8>, usize)> = Vec::new();
            macro_rules! take {
                ($name:literal, $v:expr, $t:ty) => {
                    if let Some(v) = $v {
                        let s = std::mem::size_of::<$t>();
                        vecs.push(($name, v.bytes().to_vec(), s));
                    }
                };
            }
            take!("keys", b.keys(), u64);
            take!("voxels", b.voxels(), fb::Voxel);
            take!("exposure", b.exposure(), f32);
            take!("faces", b.faces(), fb::Face);
            take!("qlobes", b.qlobes(), fb::QLobe);
            take!("qmoments", b.qmoments(), fb::QMoments);
            take!(
                "qdielectric",
                b.qdielectric_moments(),
                fb::QDielectricMoments
            );
            take!("aiv_qnodes", b.aiv_qnodes(), fb::QHaarNode);
            take!("abv_qnodes", b.abv_qnodes(), fb::QHaarNode);
            take!("lobes", b.lobes(), fb::Lobe);
            take!("moments", b.moments(), fb::Moments);
            take!("dielectric", b.dielectric_moments(), fb::DielectricMoments);
            take!("aiv_nodes", b.aiv_nodes(), fb::HaarNode);
            take!("abv_nodes", b.abv_nodes(), fb::HaarNode);
            *totals.entry("0 flatbuffer").or_default() += zstd_len(&raw, level);
            let streams: Vec<u8> = vecs.iter().flat_map(|v| v.1.clone()).collect();
            *totals.entry("1 streams").or_default() += zstd_len(&streams, level);
            let pl: Vec<u8> = vecs.iter().flat_map(|v| planes(&v.1, v.2)).collect();
            *totals.entry("2 planes").or_default() += zstd_len(&pl, level);
            let pd: Vec<u8> = vecs
                .iter()
                .flat_map(|v| match v.0 {
                    "keys" => planes(&delta_u64(&v.1), v.2),
                    "faces" => planes(&delta_faces(&v.1, v.2), v.2),
                    _ => planes(&v.1, v.2),
                })
                .collect();
            *totals.entry("3 planes+delta").or_default() += zstd_len(&pd, level);
            for (name, data, stride) in &vecs {
                let e = per_vector.entry(name).or_default();
                e[0] += data.len();
                e[1] += zstd_len(data, level);
                e[2] += zstd_len(&planes(data, *stride), level);
            }
        }
    }
    println!(
        "{path}: zstd level {level}, {} inflated bytes, {:.1} s; the file's blocks decode (as stored: \
         inflated, and turned back from byte planes where they are in them) at {:.0} MB/s of \
         inflated bytes, one thread",
        inflated_total,
        t0.elapsed().as_secs_f64(),
        inflated_total as f64 / decode_seconds.max(1e-9) / 1e6
    );
    println!("| coding | bytes | of the FlatBuffer's |");
    println!("|---|---|---|");
    let base = totals["0 flatbuffer"] as f64;
    for (k, v) in &totals {
        println!("| {} | {} | {:.3} |", &k[2..], v, *v as f64 / base);
    }
    println!("\n| vector | raw | zstd | planes + zstd |");
    println!("|---|---|---|---|");
    for (k, v) in &per_vector {
        println!("| {k} | {} | {} | {} |", v[0], v[1], v[2]);
    }
    Ok(())
}
