//! Rewrites an `.agg` in format 1.4's quantized layout (or, with `--lossless`, the float one)
//! without baking again, and measures what quantization changes: bytes per component and, per
//! level, the largest and the RMS error of every AIV and ABV cell, of the lobes' SGGX matrices
//! and of the moments against the input.
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin requantize -- IN.agg OUT.agg [--lossless] [--bytes-only]
//!     [--compression-level N]
//! ```
//!
//! `--compression-level N` compresses the blocks with Zstandard at level N (format 1.5; 0 for
//! none; the default is the bake's). `--bytes-only` skips the error figures (they evaluate every cell of every map: minutes at
//! 256³); `SIMULATE_8BIT=1` adds what an 8-bit fixed point would give the trees and unorm8 the
//! moments.
//!
//! The bake's encoder writes the voxels and faces it baked; here it writes the ones read back
//! from a float file, which are the same values (tests/format.rs `round_trip_and_rejection`),
//! so the output has the bytes a bake of the same settings would write.

use std::path::PathBuf;

use aggtool::absdf::{MaterialMoments, Moments};
use aggtool::format::encode::{self, ComponentBytes, Counts, IndexEntry, LevelEntry};
use aggtool::format::{Aggregate, LevelData, Writer};
use aggtool::math::haar::SparseHaar;
use aggtool::math::sggx::Sggx;

/// Largest and sum of squares of a set of errors.
#[derive(Default)]
struct Err {
    max: f64,
    sq: f64,
    n: u64,
}

impl Err {
    fn add(&mut self, e: f64) {
        self.max = self.max.max(e.abs());
        self.sq += e * e;
        self.n += 1;
    }
    fn show(&self) -> String {
        format!(
            "max {:.3e} rms {:.3e} (n {})",
            self.max,
            (self.sq / self.n.max(1) as f64).sqrt(),
            self.n
        )
    }
}

fn trees(a: &SparseHaar, b: &SparseHaar, e: &mut Err) {
    if a.nodes.is_empty() && b.nodes.is_empty() {
        return;
    }
    for y in 0..a.n {
        for x in 0..a.n {
            e.add((a.eval(x, y).clamp(0.0, 1.0) - b.eval(x, y).clamp(0.0, 1.0)) as f64);
        }
    }
}

/// The tree with its details rounded to `steps` per unit of h/s (format 1.4 stores 65534; a
/// byte would give 254): what a coarser fixed point would cost, simulated.
fn coarser(t: &SparseHaar, steps: f32) -> SparseHaar {
    let sizes = aggtool::math::haar::node_sizes(t.n, t.nodes.len(), |i| {
        (t.nodes[i].children, t.nodes[i].subtree)
    });
    let mut out = t.clone();
    for (nd, s) in out.nodes.iter_mut().zip(sizes) {
        let k = steps / s as f32;
        let lim = (steps / 2.0).floor();
        nd.details = nd.details.map(|d| (d * k).round().clamp(-lim, lim) / k);
    }
    out
}

fn sets(m: &Moments) -> Vec<MaterialMoments> {
    match m {
        Moments::Constant(c) => vec![*c],
        Moments::Directional {
            diffuse, specular, ..
        } => diffuse.iter().chain(specular).copied().collect(),
    }
}

fn compare(a: &LevelData, b: &LevelData) -> [Err; 4] {
    let (mut aiv, mut abv, mut lobes, mut moments) = (
        Err::default(),
        Err::default(),
        Err::default(),
        Err::default(),
    );
    for (u, v) in a.voxels.iter().zip(&b.voxels) {
        trees(&u.aiv, &v.aiv, &mut aiv);
        for (p, q) in u.appearance.lobes.iter().zip(&v.appearance.lobes) {
            let (s, t) = (
                Sggx::from_frame_roughness(p.frame, p.alpha),
                Sggx::from_frame_roughness(q.frame, q.alpha),
            );
            let big = s.xx.max(s.yy).max(s.zz).max(1e-12) as f64;
            for (x, y) in [
                (s.xx, t.xx),
                (s.yy, t.yy),
                (s.zz, t.zz),
                (s.xy, t.xy),
                (s.xz, t.xz),
                (s.yz, t.yz),
            ] {
                lobes.add((x - y) as f64 / big);
            }
        }
        for (p, q) in sets(&u.appearance.moments)
            .iter()
            .zip(&sets(&v.appearance.moments))
        {
            let (x, y) = (
                [p.c.x, p.c.y, p.c.z, p.s, p.f90, p.m],
                [q.c.x, q.c.y, q.c.z, q.s, q.f90, q.m],
            );
            for (x, y) in x.iter().zip(y) {
                moments.add((x - y) as f64);
            }
        }
    }
    for (u, v) in a.faces.iter().zip(&b.faces) {
        trees(&u.abv, &v.abv, &mut abv);
    }
    [aiv, abv, lobes, moments]
}

/// Errors an 8-bit fixed point would give the trees (254 steps per unit of h/s) and unorm8
/// the moments, against the input.
fn simulate_8bit(a: &LevelData) -> [Err; 3] {
    let (mut aiv, mut abv, mut moments) = (Err::default(), Err::default(), Err::default());
    for v in &a.voxels {
        trees(&v.aiv, &coarser(&v.aiv, 254.0), &mut aiv);
        for m in sets(&v.appearance.moments) {
            for x in [m.c.x, m.c.y, m.c.z, m.s, m.f90] {
                moments.add((x - (x.clamp(0.0, 1.0) * 255.0).round() / 255.0) as f64);
            }
        }
    }
    for f in &a.faces {
        trees(&f.abv, &coarser(&f.abv, 254.0), &mut abv);
    }
    [aiv, abv, moments]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let lossless = args.iter().any(|a| a == "--lossless");
    let bytes_only = args.iter().any(|a| a == "--bytes-only");
    let compression = match args.iter().position(|a| a == "--compression-level") {
        Some(i) => args
            .get(i + 1)
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| anyhow::anyhow!("--compression-level needs a number"))?,
        None => aggtool::format::DEFAULT_COMPRESSION,
    };
    let paths: Vec<PathBuf> = args
        .iter()
        .enumerate()
        .filter(|(i, a)| !a.starts_with("--") && (*i == 0 || args[i - 1] != "--compression-level"))
        .map(|(_, a)| PathBuf::from(a))
        .collect();
    let [input, output] = paths.as_slice() else {
        anyhow::bail!(
            "usage: requantize IN.agg OUT.agg [--lossless] [--bytes-only] [--compression-level N]"
        );
    };
    let agg = Aggregate::open(input)?;
    let mut settings = agg.settings().clone();
    settings.lossless = lossless;
    settings.compression = compression;
    let mut writer = Writer::create(output)?;
    writer.set_compression(compression);
    let mut entries = Vec::new();
    let mut sizes = ComponentBytes::default();
    for l in 0..agg.level_count() {
        let lv = agg.read_level(l);
        let mut counts = Counts::default();
        let mut voxel_blocks = Vec::new();
        for chunk in lv.voxels.chunks(aggtool::bake::BLOCK_VOXELS) {
            let blob = encode::voxel_block(
                l as u32,
                chunk,
                settings.keep_all_effects,
                lossless,
                &mut counts,
                &mut sizes,
            );
            let (first, last) = (chunk[0].key, chunk[chunk.len() - 1].key);
            voxel_blocks.push(writer.write_block(&blob, first, last, chunk.len() as u32)?);
        }
        let mut face_blocks = Vec::new();
        for chunk in lv.faces.chunks(aggtool::bake::BLOCK_FACES) {
            let blob = encode::face_block(l as u32, chunk, lossless, &mut counts, &mut sizes);
            let (first, last) = (
                encode::face_key(&chunk[0]),
                encode::face_key(&chunk[chunk.len() - 1]),
            );
            face_blocks.push(writer.write_block(&blob, first, last, chunk.len() as u32)?);
        }
        entries.push(LevelEntry {
            res: lv.grid.res,
            origin: lv.grid.origin,
            size: lv.grid.size,
            voxel_blocks,
            face_blocks,
            counts,
            voxel_keys: aggtool::format::encode_voxel_keys(
                lv.voxels.iter().map(|v| v.key),
                compression,
            ),
        });
    }
    let (tables_version, tables_crc32) = agg.tables();
    let index = encode::index(&IndexEntry {
        generator: agg.generator(),
        source: agg.source(),
        bounds: agg.bounds(),
        settings: &settings,
        tables_version,
        tables_crc32,
        levels: &entries,
    });
    let bytes = writer.finish(&index)?;
    println!(
        "output: {} ({} bytes; input {} bytes, {:.3}×)",
        output.display(),
        bytes,
        agg.header().file_size,
        agg.header().file_size as f64 / bytes as f64
    );
    let out = Aggregate::open(output)?;
    for l in 0..agg.level_count() {
        let (a, b) = (agg.component_bytes(l).0, out.component_bytes(l).0);
        println!(
            "level {}³: records {} -> {}, lobes {} -> {}, moments {} -> {}, AIV nodes {} -> {}, faces {} -> {}, ABV nodes {} -> {}",
            agg.grid(l).res,
            a.voxels,
            b.voxels,
            a.lobes,
            b.lobes,
            a.moments + a.dielectric_moments,
            b.moments + b.dielectric_moments,
            a.aiv_nodes,
            b.aiv_nodes,
            a.faces,
            b.faces,
            a.abv_nodes,
            b.abv_nodes
        );
        if bytes_only {
            continue;
        }
        let [aiv, abv, lobes, moments] = compare(&agg.read_level(l), &out.read_level(l));
        println!(
            "  error: AIV cells {}; ABV cells {}; SGGX entries / largest diagonal {}; moments {}",
            aiv.show(),
            abv.show(),
            lobes.show(),
            moments.show()
        );
        if std::env::var_os("SIMULATE_8BIT").is_some() {
            let [aiv, abv, moments] = simulate_8bit(&agg.read_level(l));
            println!(
                "  8-bit (simulated): AIV cells {}; ABV cells {}; unorm8 moments {}",
                aiv.show(),
                abv.show(),
                moments.show()
            );
        }
    }
    Ok(())
}
