//! Cones per second through the Rust API on cones read from a file: the baseline for the
//! bindings' overhead (`benches/bindings.py` traces the same cones through the C ABI and the
//! Python module and runs this for the Rust figure).
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin cones_bench -- FILE.agg CONES.f32 [--repeat 5]
//! ```
//!
//! CONES.f32: little-endian f32, seven per cone (origin, direction, aperture). Cone i draws
//! stream i of seed 1, as `agg_trace_cones` and `Scene.trace` do. Prints the best of the
//! repeats.

use aggtool_tools as common;

use aggtool::lights::Lights;
use aggtool::runtime::{Cone, LodScene, TraceSettings};
use glam::Vec3;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (agg, file) = match (args.get(1), args.get(2)) {
        (Some(a), Some(f)) => (a, f),
        _ => return Err("usage: cones_bench FILE.agg CONES.f32 [--repeat N]".into()),
    };
    let repeat = common::flag_u32(&args, "--repeat", 5).max(1);
    let bytes = std::fs::read(file)?;
    let f: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let cones: Vec<Cone> = f
        .chunks_exact(7)
        .map(|c| {
            Cone::new(
                Vec3::new(c[0], c[1], c[2]),
                Vec3::new(c[3], c[4], c[5]),
                c[6],
            )
        })
        .collect();
    let scene = LodScene::open(std::path::Path::new(agg))?;
    let lights = Lights::constant(Vec3::ONE);
    let settings = TraceSettings::default();
    let mut out = vec![0f32; 4 * cones.len()];
    let mut best = f64::INFINITY;
    for _ in 0..repeat {
        let t = std::time::Instant::now();
        scene.trace_batch(&cones, &lights, &settings, 1, &mut out);
        best = best.min(t.elapsed().as_secs_f64());
    }
    let mean: f64 = out.iter().map(|&x| x as f64).sum::<f64>() / out.len().max(1) as f64;
    println!(
        "rust: {} cones in {best:.4} s (best of {repeat}): {:.3} M cones/s; mean {mean:.6}",
        cones.len(),
        cones.len() as f64 / best / 1e6
    );
    Ok(())
}
