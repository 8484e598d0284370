//! Measures the bake's first stages on an asset, level by level: voxelization with exact
//! areas, per-voxel surface sampling, ABSDF statistics, and interior visibility for a subset of
//! voxels (to extrapolate the cost of a full level).
//!
//! ```text
//! cargo run --release --example bake_probe -- [ASSET] [--max-res 256] [--samples 16] [--rays 16] [--aiv-voxels 2000]
//! ```

use std::time::Instant;

use aggtool::absdf::estimate::{estimate, EstimateSettings};
use aggtool::bake::sampling::{pieces_by_voxel, sample_voxel};
use aggtool::bake::visibility::aiv_map;
use aggtool::bake::voxelize::Grid;
use aggtool::trace::Accel;
use rayon::prelude::*;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let get = |flag: &str, default: u32| -> u32 {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let max_res = get("--max-res", 256);
    let samples = get("--samples", 16);
    let rays = get("--rays", 16);
    let aiv_voxels = get("--aiv-voxels", 2000) as usize;
    let default = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets/sh3d_chandelier_scopia/chandelier-lamp.obj");
    let path = args
        .iter()
        .find(|a| !a.starts_with("--") && a.parse::<u32>().is_err())
        .map(std::path::PathBuf::from)
        .unwrap_or(default);
    let scene = aggtool::import::load(&path, Default::default())?;
    println!("input: {}: {}", path.display(), scene.summary());
    let accel = Accel::build(&scene);
    let (lo, hi) = scene.bounds();
    let mut res = max_res;
    while res >= 8 {
        let grid = Grid::around(lo, hi, res);
        let t0 = Instant::now();
        let pieces = pieces_by_voxel(&scene, &grid);
        let t_vox = t0.elapsed().as_secs_f64();
        // Samples per voxel inversely proportional to res² (paper §7.1), `samples` at max_res.
        let per_voxel = ((samples as f64) * (max_res as f64 / res as f64).powi(2))
            .round()
            .max(1.0) as u32;
        let keys: Vec<(&u64, &Vec<_>)> = pieces.iter().collect();
        let t1 = Instant::now();
        let stats: Vec<_> = keys
            .par_iter()
            .map(|(k, list)| {
                let s = sample_voxel(&scene, list, per_voxel, **k as u32);
                let surf: Vec<_> = s.iter().map(|p| p.surface).collect();
                (s, estimate(&surf, &EstimateSettings::default()))
            })
            .collect();
        let t_stats = t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        let n_aiv = aiv_voxels.min(stats.len());
        let step = (stats.len() / n_aiv.max(1)).max(1);
        let traced: u64 = stats
            .par_iter()
            .step_by(step)
            .take(n_aiv)
            .map(|(s, _)| aiv_map(&accel, s, 32, rays, 1).1)
            .sum();
        let t_aiv = t2.elapsed().as_secs_f64();
        let est_aiv = t_aiv * stats.len() as f64 / n_aiv.max(1) as f64;
        println!(
            "level {res:>4}^3: {:>8} voxels ({:.3}% occupied), voxelize {:.2} s, {per_voxel} samples/voxel + statistics {:.2} s, AIV {:.2} s for {n_aiv} voxels ({traced} rays, {:.2} Mrays/s) -> {:.0} s for the level",
            stats.len(),
            100.0 * stats.len() as f64 / (res as f64).powi(3),
            t_vox,
            t_stats,
            t_aiv,
            traced as f64 / t_aiv.max(1e-9) / 1e6,
            est_aiv
        );
        res /= 2;
    }
    Ok(())
}
