//! Criterion benchmarks of the hot paths: closest hit and occlusion through the two-level BVH,
//! and one reference radiance sample, on a generated foliage scene (cut-outs) and a generated
//! block of instanced buildings. `cargo bench --bench trace`.

use aggtool::gen::{generate, GenSettings};
use aggtool::lights::{Environment, Lights, Sun};
use aggtool::math::rng::Pcg32;
use aggtool::render::reference::radiance;
use aggtool::render::View;
use aggtool::trace::{Accel, Ray};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glam::{Vec2, Vec3};

fn bench(c: &mut Criterion) {
    for name in ["foliage", "buildings"] {
        let scene = generate(
            name,
            &GenSettings {
                triangles: 100_000,
                ..Default::default()
            },
        )
        .unwrap()
        .to_scene();
        let accel = Accel::build(&scene);
        let (center, r) = scene.bounding_sphere();
        let view = View::framing(center, r, 128, 128, 1);
        let cam = view.camera();
        let rays: Vec<Ray> = (0..128 * 128)
            .map(|i| {
                let (o, d) = cam.ray(Vec2::new((i % 128) as f32 + 0.5, (i / 128) as f32 + 0.5));
                Ray::new(o, d)
            })
            .collect();
        let mut g = c.benchmark_group(name);
        g.throughput(Throughput::Elements(rays.len() as u64));
        g.sample_size(10);
        g.bench_function("intersect", |b| {
            b.iter(|| rays.iter().filter(|r| accel.intersect(r).is_some()).count())
        });
        g.bench_function("occluded", |b| {
            b.iter(|| rays.iter().filter(|r| accel.occluded(r)).count())
        });
        let lights = Lights {
            environment: Environment::Constant(Vec3::splat(0.8)),
            sun: Some(Sun {
                direction: Vec3::Y,
                irradiance: Vec3::ONE,
            }),
        };
        g.bench_function("radiance sample", |b| {
            let mut rng = Pcg32::new(1, 1);
            let mut n = 0u64;
            b.iter(|| {
                rays.iter()
                    .map(|r| radiance(&accel, &lights, r, &mut rng, &mut n))
                    .sum::<Vec3>()
            })
        });
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
