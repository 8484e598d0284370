//! What splitting a block's fields into streams would save before Zstandard (issue 42,
//! deliverable 3), measured on an existing `.agg` without changing the format: for every
//! block, the bytes of
//! - `flatbuffer`: the block's FlatBuffer compressed whole (what format 1.5 stores);
//! - `streams`: each vector's bytes one after another, compressed together;
//! - `planes`: each vector transposed into byte planes (byte k of every element, then byte
//!   k + 1, ...), the planes one after another, compressed together;
//! - `planes+delta`: as `planes`, with the sorted Morton keys replaced by their differences
//!   and the faces' voxel coordinates by theirs to the previous face;
//! - `planes+derived`: as `planes`, with the fields a reader can recompute zeroed (the
//!   voxels' and faces' start indices where they are running sums of the counts, the
//!   quantized trees' subtree counts, which the child masks imply);
//! - `planes+derived+subband`: and the trees' details ordered by depth;
//! - `derived planes (format 1.8)`: what the format stores, through the library's own
//!   transform (float trees included);
//!
//! and, per vector, its bytes raw and in planes compressed alone. Each at the Zstandard level
//! given (default 19, the bake's), and the speed at which the file's blocks decode as stored.
//!
//! ```sh
//! cargo run --release -p aggtool-tools --bin stream_probe -- tree.agg [LEVEL]
//! cargo run --release -p aggtool-tools --bin stream_probe -- tree.agg --decode   # speed only
//! cargo run --release -p aggtool-tools --bin stream_probe -- tree.agg --coding   # 1.6 vs 1.8
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

/// Elements of `stride` bytes as little-endian u16 lanes, each replaced by its wrapping
/// difference to the same lane of the previous element.
fn delta_u16_lanes(data: &[u8], stride: usize) -> Vec<u8> {
    let mut out = data.to_vec();
    if stride % 2 != 0 {
        return out;
    }
    for i in (1..data.len() / stride).rev() {
        for k in (0..stride).step_by(2) {
            let at = i * stride + k;
            let v = u16::from_le_bytes([data[at], data[at + 1]]);
            let p = u16::from_le_bytes([data[at - stride], data[at - stride + 1]]);
            out[at..at + 2].copy_from_slice(&v.wrapping_sub(p).to_le_bytes());
        }
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

/// Parses the quantized Haar trees stored back to back in `nodes` (6-byte `QHaarNode`s) from
/// their child masks alone; returns each node's depth and whether every stored subtree count
/// equals the one the masks imply.
fn qtree_depths(nodes: &[u8]) -> (Vec<u8>, bool) {
    let n = nodes.len() / 6;
    let links = |i: usize| u16::from_le_bytes([nodes[6 * i], nodes[6 * i + 1]]);
    let mut depth = vec![0u8; n];
    let mut ok = true;
    // Returns the subtree size of the node at i.
    fn walk(
        i: usize,
        d: u8,
        n: usize,
        links: &dyn Fn(usize) -> u16,
        depth: &mut [u8],
        ok: &mut bool,
    ) -> usize {
        if i >= n {
            *ok = false;
            return 1;
        }
        depth[i] = d;
        let mask = links(i) >> 12;
        let mut size = 1;
        for q in 0..4 {
            if mask & (1 << q) != 0 {
                size += walk(i + size, d + 1, n, links, depth, ok);
            }
        }
        if (links(i) & 0x0fff) as usize != size {
            *ok = false;
        }
        size
    }
    let mut i = 0;
    while i < n {
        i += walk(i, 0, n, &links, &mut depth, &mut ok);
    }
    (depth, ok)
}

/// `QHaarNode`s with the subtree counts zeroed (the masks imply them) and, with `subband`,
/// the h, v, d bytes in planes ordered by depth (the root's of every tree first).
/// Order-0 entropy in bytes of the h, v, d bytes of the trees in `nodes`: (whole, per depth,
/// per depth and the parent's same coefficient's magnitude bucket).
fn qnode_entropy(nodes: &[u8]) -> [f64; 3] {
    let (depth, _) = qtree_depths(nodes);
    let n = depth.len();
    // Parent of each node: the last node before it one level up.
    let mut parent = vec![usize::MAX; n];
    let mut last = [usize::MAX; 16];
    for i in 0..n {
        let d = depth[i] as usize;
        if d > 0 {
            parent[i] = last[d - 1];
        }
        last[d] = i;
    }
    let bucket = |q: i8| match q.unsigned_abs() {
        0 => 0usize,
        1 => 1,
        2..=3 => 2,
        4..=8 => 3,
        _ => 4,
    };
    let mut h = [0f64; 3];
    for ctx_kind in 0..3 {
        let mut counts: BTreeMap<(usize, usize, u8), f64> = BTreeMap::new();
        for i in 0..n {
            for k in 2..5 {
                let b = nodes[6 * i + k];
                let ctx = match ctx_kind {
                    0 => 0,
                    1 => depth[i] as usize,
                    _ => {
                        let p = parent[i];
                        let pb = if p == usize::MAX {
                            5
                        } else {
                            bucket(nodes[6 * p + k] as i8)
                        };
                        depth[i] as usize * 8 + pb
                    }
                };
                *counts.entry((ctx, k, b)).or_default() += 1.0;
            }
        }
        let mut tot: BTreeMap<(usize, usize), f64> = BTreeMap::new();
        for ((c, k, _), v) in &counts {
            *tot.entry((*c, *k)).or_default() += v;
        }
        for ((c, k, _), v) in &counts {
            h[ctx_kind] -= v * (v / tot[&(*c, *k)]).log2();
        }
        h[ctx_kind] /= 8.0;
    }
    h
}

fn qnodes_derived(nodes: &[u8], subband: bool) -> Vec<u8> {
    let (depth, ok) = qtree_depths(nodes);
    let mut v = nodes.to_vec();
    if ok {
        for c in v.chunks_exact_mut(6) {
            c[0] = 0;
            c[1] &= 0xf0;
        }
    }
    let mut p = planes(&v, 6);
    if subband && ok {
        let n = depth.len();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&i| depth[i]);
        for k in 2..5 {
            let plane: Vec<u8> = order.iter().map(|&i| p[k * n + i]).collect();
            p[k * n..(k + 1) * n].copy_from_slice(&plane);
        }
    }
    p
}

/// Byte offset of the u32 field `set` writes in a struct of `size` bytes.
fn field_offset<T: Copy>(zero: T, set: impl Fn(&mut T)) -> usize {
    let mut t = zero;
    set(&mut t);
    let b = unsafe {
        std::slice::from_raw_parts(&t as *const T as *const u8, std::mem::size_of::<T>())
    };
    b.windows(4)
        .position(|w| w == 0xA1B2_C3D4u32.to_le_bytes())
        .expect("marker")
}

/// Zeroes the u32 at `start_at` of every element where it equals the running sum of the u32
/// at `count_at` (what a reader can recompute); all or nothing.
fn zero_starts(data: &[u8], stride: usize, starts: &[(usize, usize)]) -> Vec<u8> {
    let mut out = data.to_vec();
    for &(s, c) in starts {
        let rd = |e: &[u8], at: usize| u32::from_le_bytes(e[at..at + 4].try_into().unwrap());
        let mut sum = 0u32;
        let ok = data.chunks_exact(stride).all(|e| {
            let r = rd(e, s) == sum;
            sum = sum.wrapping_add(rd(e, c));
            r
        });
        if ok {
            for e in out.chunks_exact_mut(stride) {
                e[s..s + 4].fill(0);
            }
        }
    }
    out
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = args
        .get(1)
        .ok_or_else(|| anyhow::anyhow!("usage: stream_probe FILE.agg [ZSTD_LEVEL]"))?;
    let bytes = std::fs::read(path)?;
    let h = Header::parse(&bytes)?;
    let index = &bytes[h.index_offset as usize..(h.index_offset + h.index_size) as usize];
    let index = flatbuffers::root::<fb::Index>(index)?;
    if args.get(2).map(String::as_str) == Some("--decode") {
        // Decoding speed only: every block as stored, five times, the fastest pass.
        let blobs = aggtool::format::stored_blocks(&bytes).map_err(anyhow::Error::msg)?;
        let mut best = f64::MAX;
        let mut inflated = 0;
        for _ in 0..5 {
            let t = std::time::Instant::now();
            inflated = 0;
            for b in &blobs {
                inflated += inflate_block(b).map_err(anyhow::Error::msg)?.len();
            }
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!(
            "{path}: {inflated} inflated bytes in {:.1} ms: {:.0} MB/s, one thread (best of 5)",
            best * 1e3,
            inflated as f64 / best / 1e6
        );
        return Ok(());
    }
    if args.get(2).map(String::as_str) == Some("--coding") {
        // The blocks' bytes as format 1.6/1.7 codes them (planes) and as 1.8 does (derived
        // fields left out), both at the bake's Zstandard level, on the same blocks.
        let (mut planar, mut derived, mut inflated) = (0usize, 0usize, 0usize);
        {
            for blob in aggtool::format::stored_blocks(&bytes).map_err(anyhow::Error::msg)? {
                let raw = inflate_block(blob).map_err(anyhow::Error::msg)?;
                inflated += raw.len();
                let l = aggtool::format::DEFAULT_COMPRESSION;
                planar += 4 + zstd_len(&aggtool::format::planar::to_planes(&raw), l);
                derived += 5 + zstd_len(&aggtool::format::planar::to_derived_planes(&raw).1, l);
            }
        }
        println!(
            "{path}: blocks {inflated} inflated, {planar} in planes (1.6), {derived} derived (1.8): {:.3}",
            derived as f64 / planar as f64
        );
        return Ok(());
    }
    let level: i32 = args.get(2).map_or(Ok(19), |s| s.parse())?;
    let mut totals: BTreeMap<&str, usize> = BTreeMap::new();
    let mut per_vector: BTreeMap<&'static str, [usize; 4]> = BTreeMap::new();
    let t0 = std::time::Instant::now();
    let mut inflated_total = 0usize;
    let mut decode_seconds = 0f64;
    let mut entropy: BTreeMap<(&str, usize), f64> = BTreeMap::new();
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
            let vx = std::mem::size_of::<fb::Voxel>();
            let z = fb::Voxel::default();
            let vstarts = [
                (
                    field_offset(z, |v| v.set_lobe_start(0xA1B2_C3D4)),
                    field_offset(z, |v| v.set_lobe_count(0xA1B2_C3D4)),
                ),
                (
                    field_offset(z, |v| v.set_moment_start(0xA1B2_C3D4)),
                    field_offset(z, |v| v.set_moment_count(0xA1B2_C3D4)),
                ),
                (
                    field_offset(z, |v| v.set_aiv_start(0xA1B2_C3D4)),
                    field_offset(z, |v| v.set_aiv_count(0xA1B2_C3D4)),
                ),
            ];
            let fz = fb::Face::default();
            let fstarts = [(
                field_offset(fz, |v| v.set_abv_start(0xA1B2_C3D4)),
                field_offset(fz, |v| v.set_abv_count(0xA1B2_C3D4)),
            )];
            for (name, subband) in [
                ("4 planes+derived", false),
                ("5 planes+derived+subband", true),
            ] {
                if subband {
                    // What format 1.8 stores (`format::planar::to_derived_planes`).
                    let (_, d) = aggtool::format::planar::to_derived_planes(&raw);
                    *totals.entry("6 derived planes (format 1.8)").or_default() +=
                        zstd_len(&d, level);
                }
                let pd: Vec<u8> = vecs
                    .iter()
                    .flat_map(|v| match v.0 {
                        "voxels" => planes(&zero_starts(&v.1, vx, &vstarts), v.2),
                        "faces" => planes(&zero_starts(&v.1, v.2, &fstarts), v.2),
                        "aiv_qnodes" | "abv_qnodes" => qnodes_derived(&v.1, subband),
                        _ => planes(&v.1, v.2),
                    })
                    .collect();
                *totals.entry(name).or_default() += zstd_len(&pd, level);
            }
            for (name, data, _) in &vecs {
                if *name == "aiv_qnodes" || *name == "abv_qnodes" {
                    let h = qnode_entropy(data);
                    for (j, x) in h.iter().enumerate() {
                        *entropy.entry((name, j)).or_default() += x;
                    }
                }
            }
            for (name, data, stride) in &vecs {
                let e = per_vector.entry(name).or_default();
                e[0] += data.len();
                e[1] += zstd_len(data, level);
                e[2] += zstd_len(&planes(data, *stride), level);
                e[3] += zstd_len(&planes(&delta_u16_lanes(data, *stride), *stride), level);
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
    println!("\n| vector | raw | zstd | planes + zstd | u16 lanes as deltas, planes + zstd |");
    println!("|---|---|---|---|---|");
    for (k, v) in &per_vector {
        println!("| {k} | {} | {} | {} | {} |", v[0], v[1], v[2], v[3]);
    }
    println!("\n| trees | order-0 entropy of h, v, d | per depth | per depth and parent |");
    println!("|---|---|---|---|");
    for name in ["aiv_qnodes", "abv_qnodes"] {
        let g = |j| entropy.get(&(name, j)).copied().unwrap_or(0.0);
        println!("| {name} | {:.0} | {:.0} | {:.0} |", g(0), g(1), g(2));
    }
    Ok(())
}
