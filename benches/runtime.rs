//! Criterion benchmarks of the LoD runtime: cones per second through the foliage (generated,
//! 1M triangles) and Japanese maple aggregates baked at 64³, for the walk alone, the walk with
//! exact coverage weights, and `trace` (reservoir shading; with PCG numbers and with the image
//! loop's stratified ones), at the quality study's 64² view; and `trace` with every cone forced
//! to each level in turn (cones per second per level).
//! `cargo bench --bench runtime`.
//!
//! The aggregates are baked on first use into `target/aggtool-bench/` (a few minutes each) and
//! reused; `AGGTOOL_BENCH_AGG=a.agg,b.agg` benchmarks given files instead.

use std::path::PathBuf;

use aggtool::film::Stratified;
use aggtool::math::rng::Pcg32;
use aggtool::runtime::{Cone, LodScene, TraceSettings};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glam::Vec2;

/// The bench's aggregates: given ones, or the two baked here once.
fn aggregates() -> Vec<(String, PathBuf)> {
    if let Ok(list) = std::env::var("AGGTOOL_BENCH_AGG") {
        return list
            .split(',')
            .map(|p| (p.to_string(), PathBuf::from(p)))
            .collect();
    }
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/aggtool-bench");
    std::fs::create_dir_all(&dir).expect("bench folder");
    let settings = aggtool::bake::BakeSettings {
        max_res: 64,
        ..Default::default()
    };
    let mut out = Vec::new();
    let foliage = dir.join("foliage-1m-64.agg");
    if !foliage.exists() {
        let scene = aggtool::gen::generate(
            "foliage",
            &aggtool::gen::GenSettings {
                triangles: 1_000_000,
                ..Default::default()
            },
        )
        .expect("foliage")
        .to_scene();
        eprintln!("baking {} (once)", foliage.display());
        aggtool::bake::bake_to_file(
            &scene,
            "foliage",
            &settings,
            &foliage,
            &aggtool::util::no_progress,
        )
        .expect("bake");
    }
    out.push(("foliage 1M 64³".into(), foliage));
    let maple_obj = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets/sh3d_japanese_maple_scopia/japaneseMaple.obj");
    let maple = dir.join("maple-64.agg");
    if !maple.exists() && maple_obj.exists() {
        let scene = aggtool::import::load(&maple_obj, Default::default()).expect("maple");
        eprintln!("baking {} (once)", maple.display());
        aggtool::bake::bake_to_file(
            &scene,
            "japaneseMaple.obj",
            &settings,
            &maple,
            &aggtool::util::no_progress,
        )
        .expect("bake");
    }
    if maple.exists() {
        out.push(("maple 64³".into(), maple));
    } else {
        eprintln!("skipping the maple: ../shared/assets is absent");
    }
    out
}

fn bench(c: &mut Criterion) {
    for (name, path) in aggregates() {
        let scene = LodScene::open(&path).expect("an aggregate");
        let (lo, hi) = scene.bounds().expect("bounds");
        let centre = 0.5 * (lo + hi);
        let radius = 0.5 * (hi - lo).length() / 3f32.sqrt();
        let view = aggtool::render::View::framing(centre, radius, 64, 64, 1);
        let cam = view.camera();
        let lights = aggtool::lights::Lights {
            environment: aggtool::lights::Environment::Constant(glam::Vec3::new(0.3, 0.4, 0.6)),
            sun: Some(aggtool::lights::Sun {
                direction: glam::Vec3::new(0.4, 1.0, 0.3).normalize(),
                irradiance: glam::Vec3::splat(3.0),
            }),
        };
        let mut rng = Pcg32::new(1, 1);
        let cones: Vec<Cone> = (0..64 * 64 * 4)
            .map(|i| {
                let px = i / 4;
                let (o, d) = cam.ray(Vec2::new((px % 64) as f32, (px / 64) as f32) + rng.next_2d());
                Cone::new(o, d, cam.pixel_angle())
            })
            .collect();
        let s = TraceSettings::default();
        // Prepare the levels and build the ABSDFs outside the measurement.
        for c in &cones {
            let _ = scene.trace(c, &lights, &s, &mut rng);
        }
        let mut g = c.benchmark_group(name);
        g.throughput(Throughput::Elements(cones.len() as u64));
        g.sample_size(10);
        g.bench_function("walk", |b| {
            b.iter(|| {
                cones
                    .iter()
                    .map(|c| scene.transmittance(c, &s))
                    .sum::<f32>()
            })
        });
        g.bench_function("walk with exact weights", |b| {
            b.iter(|| {
                cones
                    .iter()
                    .map(|c| scene.hits(c, &s).map(|h| h.weight).sum::<f32>())
                    .sum::<f32>()
            })
        });
        g.bench_function("trace", |b| {
            let mut rng = Pcg32::new(2, 2);
            b.iter(|| {
                cones
                    .iter()
                    .map(|c| scene.trace(c, &lights, &s, &mut rng).radiance.x)
                    .sum::<f32>()
            })
        });
        // The image loop's sampler: sample i % 4 of pixel i / 4 (the cost of its shuffled and
        // shifted low-discrepancy numbers against PCG's).
        g.bench_function("trace, stratified", |b| {
            let mut rng = Pcg32::new(2, 2);
            b.iter(|| {
                cones
                    .iter()
                    .enumerate()
                    .map(|(i, c)| {
                        let mut s4 = Stratified::new(&mut rng, i as u32 % 4, (i / 4) as u32);
                        scene.trace(c, &lights, &s, &mut s4).radiance.x
                    })
                    .sum::<f32>()
            })
        });
        // Cones per second per level: every cone forced to level l (0 = finest), the blocks
        // it needs prepared before the measurement.
        for l in 0..scene.level_count() {
            let forced = TraceSettings {
                level: Some(l),
                ..s
            };
            for c in &cones {
                let _ = scene.trace(c, &lights, &forced, &mut rng);
            }
            let res = scene.grid(l).res;
            g.bench_function(format!("trace at level {l} ({res}³)"), |b| {
                let mut rng = Pcg32::new(3, 3);
                b.iter(|| {
                    cones
                        .iter()
                        .map(|c| scene.trace(c, &lights, &forced, &mut rng).radiance.x)
                        .sum::<f32>()
                })
            });
        }
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
