//! Cost of the factorized ABSDF: ns per `eval` and per `sample` on the validation voxels.
//! `cargo bench --bench absdf`.

use aggtool::absdf::cases::{case_samples, sphere_grid, CASES};
use aggtool::absdf::estimate::{estimate, EstimateSettings};
use aggtool::absdf::Absdf;
use aggtool::bsdf::Bsdf;
use aggtool::tables::Tables;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glam::Vec2;

fn bench(c: &mut Criterion) {
    let dirs = sphere_grid(8);
    let mut g = c.benchmark_group("absdf");
    g.throughput(Throughput::Elements(dirs.len() as u64));
    for &name in CASES {
        let app = estimate(
            &case_samples(name, 4096).unwrap(),
            &EstimateSettings::default(),
        )
        .unwrap();
        let a = Absdf::new(&app, Tables::embedded());
        let wo = dirs[5];
        g.bench_function(format!("eval/{name}"), |b| {
            b.iter(|| dirs.iter().map(|&wi| a.eval(wi, wo).x).sum::<f32>())
        });
        g.bench_function(format!("sample/{name}"), |b| {
            b.iter(|| {
                (0..dirs.len())
                    .filter_map(|k| {
                        a.sample(
                            wo,
                            (k as f32 + 0.5) / dirs.len() as f32,
                            Vec2::new(0.37, (k as f32 * 0.618).fract()),
                        )
                    })
                    .count()
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
