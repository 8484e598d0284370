//! The baked AIV against the visibility traced from each voxel's real surfaces (the oracle of
//! `aggtool eval --budget`), on random (voxel, direction) pairs of one level:
//!
//! ```sh
//! cargo run --release -p aggtool-tools --bin aiv_probe -- ASSET ASSET.agg [LEVEL] [PAIRS] [SAMPLES] [--estimators] [--chosen]
//! ```
//!
//! Prints the mean and RMS of baked − traced, their correlation, the same for the baked value
//! of the opposite direction (a mirrored map would show there), and the error by how the
//! traced value falls (0, between, 1).

use aggtool::eval::budget::{aiv_pairs, Truth};
use aggtool::runtime::LodScene;
use aggtool::trace::Accel;

/// A (voxel key, direction, baked V̂, traced V̂) pair.
type Pair = (u64, glam::Vec3, f32, f32);

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 3 {
        anyhow::bail!("usage: aiv_probe ASSET ASSET.agg [LEVEL] [PAIRS] [SAMPLES]");
    }
    let scene = aggtool::import::load(std::path::Path::new(&a[1]), Default::default())?;
    let lod = LodScene::open(std::path::Path::new(&a[2]))?;
    let level: usize = a.get(3).map_or(Ok(0), |s| s.parse())?;
    let n: usize = a.get(4).map_or(Ok(20000), |s| s.parse())?;
    let samples: u32 = a.get(5).map_or(Ok(64), |s| s.parse())?;
    let accel = Accel::build(&scene);
    let truth = Truth::new(&accel, lod.grid(level), level, samples);
    let pairs = aiv_pairs(&lod, &truth, n, 1);
    let stats = |f: &dyn Fn(&Pair) -> (f32, f32)| {
        let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0f64, 0f64, 0f64, 0f64, 0f64);
        for p in &pairs {
            let (x, y) = f(p);
            let (x, y) = (x as f64, y as f64);
            sa += x;
            sb += y;
            saa += x * x;
            sbb += y * y;
            sab += x * y;
        }
        let k = pairs.len() as f64;
        let (ma, mb) = (sa / k, sb / k);
        let cov = sab / k - ma * mb;
        let corr = cov / ((saa / k - ma * ma) * (sbb / k - mb * mb)).sqrt();
        let rms = ((saa - 2.0 * sab + sbb) / k).sqrt();
        (ma, mb, rms, corr)
    };
    let (ma, mb, rms, corr) = stats(&|p| (p.2, p.3));
    println!(
        "{} pairs: baked mean {ma:.4}, traced mean {mb:.4}, RMS(baked − traced) {rms:.4}, correlation {corr:.3}",
        pairs.len()
    );
    let (ma, _, rms, corr) = stats(&|p| {
        let v = lod.voxel(level, p.0).unwrap();
        (v.aiv(-p.1), p.3)
    });
    println!("opposite direction: baked mean {ma:.4}, RMS {rms:.4}, correlation {corr:.3}");
    for (name, lo, hi) in [
        ("traced = 0", -1.0, 1e-6),
        ("between", 1e-6, 0.999_999),
        ("traced = 1", 0.999_999, 2.0),
    ] {
        let sel: Vec<_> = pairs.iter().filter(|p| p.3 >= lo && p.3 < hi).collect();
        if sel.is_empty() {
            continue;
        }
        let k = sel.len() as f64;
        let bias: f64 = sel.iter().map(|p| (p.2 - p.3) as f64).sum::<f64>() / k;
        let rms = (sel
            .iter()
            .map(|p| ((p.2 - p.3) as f64).powi(2))
            .sum::<f64>()
            / k)
            .sqrt();
        println!(
            "{name}: {} pairs, mean baked − traced {bias:+.4}, RMS {rms:.4}",
            sel.len()
        );
    }
    if a.iter().any(|x| x == "--estimators") {
        estimators(&scene, &accel, &lod, &truth, level)?;
    }
    if a.iter().any(|x| x == "--chosen") {
        chosen(&scene, &accel, &lod, level);
    }
    Ok(())
}

/// Which AIV bandwidth the cross-validation chose, on (up to) 1500 voxels of the level (the
/// bake's samples, rays and seed; settings of the default preset at the level's resolution).
/// The bake reports the same over every voxel (`stats:` lines, `--report`).
fn chosen(scene: &aggtool::scene::Scene, accel: &Accel, lod: &LodScene, level: usize) {
    use aggtool::bake::sampling::{pieces_by_voxel, sample_voxel};
    use aggtool::bake::visibility::{aiv_map, AIV_BANDWIDTHS};
    let grid = lod.grid(level);
    let settings = aggtool::bake::BakeSettings {
        max_res: lod.grid(0).res,
        ..Default::default()
    };
    let spv = settings.samples_at(grid.res);
    let pieces = pieces_by_voxel(scene, &grid);
    let mut keys: Vec<u64> = pieces.keys().copied().collect();
    keys.sort_unstable();
    let keys: Vec<u64> = keys
        .into_iter()
        .step_by((pieces.len() / 1500).max(1))
        .collect();
    let mut counts = vec![0usize; AIV_BANDWIDTHS.len() + 1];
    let mut denoise = std::collections::BTreeMap::new();
    for &key in &keys {
        let seed = aggtool::bake::level::voxel_seed(key);
        let samples = sample_voxel(scene, &pieces[&key], spv, seed);
        if samples.is_empty() {
            continue;
        }
        let (res, rays) = (settings.aiv_res, settings.aiv_rays);
        let est = aiv_map(accel, &samples, res, rays, 0, true, seed);
        *denoise.entry(format!("{}", est.denoise)).or_insert(0usize) += 1;
        let k = AIV_BANDWIDTHS
            .iter()
            .position(|&b| b == est.bandwidth)
            .unwrap_or(AIV_BANDWIDTHS.len());
        counts[k] += 1;
    }
    let total: usize = counts.iter().sum();
    print!(
        "chosen AIV bandwidth over {total} voxels of the {}³ level:",
        grid.res
    );
    for (b, c) in AIV_BANDWIDTHS.iter().zip(&counts) {
        print!(" {b} {:.1}%,", 100.0 * *c as f64 / total.max(1) as f64);
    }
    println!(" other {}", counts[AIV_BANDWIDTHS.len()]);
    println!("chosen shrinkage (multiples of the noise σ): {denoise:?}");
}

/// The bake's AIV estimator rerun on (up to) 1500 voxels of the level with variants of its
/// denoising and truncation, each compared with the traced value in 16 random directions.
fn estimators(
    scene: &aggtool::scene::Scene,
    accel: &Accel,
    lod: &LodScene,
    truth: &Truth,
    level: usize,
) -> anyhow::Result<()> {
    use aggtool::bake::sampling::{pieces_by_voxel, sample_voxel};
    use aggtool::bake::visibility::{aiv_map, aiv_rays_per_cell, map_noise_sigma};
    use aggtool::math::haar::{forward, inverse, shrink, truncate};
    use aggtool::math::sphere_maps::{equal_area_sphere_to_square, grid_cell};
    let grid = lod.grid(level);
    let pieces = pieces_by_voxel(scene, &grid);
    let keys: Vec<u64> = pieces
        .keys()
        .copied()
        .step_by((pieces.len() / 1500).max(1))
        .collect();
    let variants = [
        "raw",
        "denoise",
        "truncate",
        "denoise+truncate (bake)",
        "denoise σ/2+truncate",
        "truncate keep 25%",
    ];
    // (map resolution, samples, rays per sample, fewest rays per cell: 0 cross-validated).
    for (res, spv, rays, min_rays) in [
        (32u32, 16u32, 16u32, 1u32),
        (32, 16, 16, 0),
        (4, 16, 16, 1),
        (8, 16, 16, 1),
        (32, 64, 16, 1),
        (16, 64, 16, 1),
        (8, 64, 16, 1),
        (32, 256, 16, 1),
        (16, 256, 16, 1),
    ] {
        let mut err = vec![(0f64, 0usize); variants.len()];
        let mut rng = aggtool::math::rng::Pcg32::new(3, 0);
        for &key in &keys {
            let seed = aggtool::bake::level::voxel_seed(key);
            let samples = sample_voxel(scene, &pieces[&key], spv, seed);
            if samples.is_empty() {
                continue;
            }
            let map = aiv_map(accel, &samples, res, rays, min_rays, false, seed).map;
            let per_cell = aiv_rays_per_cell(samples.len() as u64 * rays as u64, res);
            let mean = map.iter().sum::<f32>() / map.len() as f32;
            let sigma = map_noise_sigma(mean, per_cell);
            let mut maps = Vec::new();
            for v in 0..variants.len() {
                let (c, mut d) = forward(&map, res as usize);
                match v {
                    1 => {
                        shrink(&mut d, sigma, res as usize);
                    }
                    2 => {
                        truncate(c, &mut d, 0.1, 0.95);
                    }
                    3 => {
                        shrink(&mut d, sigma, res as usize);
                        truncate(c, &mut d, 0.1, 0.95);
                    }
                    4 => {
                        shrink(&mut d, 0.5 * sigma, res as usize);
                        truncate(c, &mut d, 0.1, 0.95);
                    }
                    5 => {
                        truncate(c, &mut d, 0.25, 0.99);
                    }
                    _ => {}
                }
                maps.push(inverse(c, &d, res as usize));
            }
            for _ in 0..16 {
                let dir = aggtool::math::sampling::square_to_uniform_sphere(rng.next_2d());
                let Some(t) = truth.traced(key, dir) else {
                    continue;
                };
                let cell = grid_cell(equal_area_sphere_to_square(dir), res) as usize;
                for (e, m) in err.iter_mut().zip(&maps) {
                    e.0 += ((m[cell] - t) as f64).powi(2);
                    e.1 += 1;
                }
            }
        }
        println!("{res}² map, {spv} samples × {rays} rays, at least {min_rays} rays a cell (0: cross-validated):");
        for (name, (se, n)) in variants.iter().zip(&err) {
            println!(
                "  {name:<26} RMS {:.4} ({n} pairs)",
                (se / *n as f64).sqrt()
            );
        }
    }
    Ok(())
}
