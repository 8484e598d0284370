//! Ray throughput of the reference renderer beside the limit: obvhs' raw closest-hit traversal
//! over the same world-space triangles (one level, no instance transform, no cut-out test, no
//! shading), on the same camera rays.
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin trace_throughput -- [ASSET] [--size 512] [--spp 16]
//! ```
//!
//! Without ASSET it uses the chandelier from ../shared/assets, or a generated foliage scene
//! when that folder is absent. All three figures use rayon over the same cores.

use std::time::{Duration, Instant};

use aggtool::lights::{Environment, Lights, Sun};
use aggtool::render::reference::{render, ReferenceSettings};
use aggtool::render::View;
use aggtool::trace::{Accel, Ray};
use glam::{Vec2, Vec3};
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray as BvhRay, RayHit};
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;
use rayon::prelude::*;

use aggtool_tools as common;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let get = |flag: &str, default: u32| common::flag_u32(&args, flag, default);
    let size = get("--size", 512);
    let spp = get("--spp", 16);
    let asset = args
        .iter()
        .find(|a| !a.starts_with("--") && a.parse::<u32>().is_err())
        .cloned();
    let default = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets/sh3d_chandelier_scopia/chandelier-lamp.obj");
    let _tmp;
    let path = match asset {
        Some(a) => std::path::PathBuf::from(a),
        None if default.exists() => default,
        None => {
            _tmp = tempfile::tempdir()?;
            let s = aggtool::gen::GenSettings {
                triangles: 200_000,
                ..Default::default()
            };
            aggtool::gen::write("foliage", &s, _tmp.path(), false)
                .map_err(anyhow::Error::msg)?
                .0
        }
    };
    let scene = aggtool::import::load(&path, Default::default())?;
    println!("input: {}: {}", path.display(), scene.summary());
    let (c, r) = scene.bounding_sphere();
    let view = View::framing(c, r, size, size, spp);
    let camera = view.camera();

    // The same camera rays for both traversals: one per pixel centre.
    let rays: Vec<Ray> = (0..size * size)
        .map(|i| {
            let (o, d) = camera.ray(Vec2::new((i % size) as f32 + 0.5, (i / size) as f32 + 0.5));
            Ray::new(o, d)
        })
        .collect();

    // Raw obvhs: every instance's triangles in world space, one CwBvh.
    let mut tris = Vec::with_capacity(scene.instanced_triangle_count());
    for inst in &scene.instances {
        let m = &scene.meshes[inst.mesh as usize];
        for t in 0..m.triangles.len() {
            let [a, b, cc] = m
                .triangle(t)
                .map(|p| inst.transform.transform_point3a(p.into()));
            tris.push(Triangle {
                v0: a,
                v1: b,
                v2: cc,
            });
        }
    }
    let bvh = build_cwbvh_from_tris(
        &tris,
        BvhBuildParams::medium_build(),
        &mut Duration::default(),
    );
    let ordered: Vec<Triangle> = bvh
        .primitive_indices
        .iter()
        .map(|&i| tris[i as usize])
        .collect();
    let accel = Accel::build(&scene);

    let reps = 8;
    let time = |f: &(dyn Fn() -> usize + Sync)| {
        f(); // warm up
        let t = Instant::now();
        let mut hits = 0;
        for _ in 0..reps {
            hits = f();
        }
        (t.elapsed().as_secs_f64(), hits)
    };
    let (raw_s, raw_hits) = time(&|| {
        rays.par_iter()
            .filter(|r| {
                let mut hit = RayHit::none();
                bvh.ray_traverse(
                    BvhRay::new(r.origin.into(), r.dir.into(), 0.0, f32::INFINITY),
                    &mut hit,
                    |ray, id| ordered[id].intersect(ray),
                )
            })
            .count()
    });
    let (ours_s, ours_hits) = time(&|| {
        rays.par_iter()
            .filter(|r| accel.intersect(r).is_some())
            .count()
    });
    let n = (rays.len() * reps) as f64;
    let raw = n / raw_s;
    let ours = n / ours_s;
    println!(
        "stats: camera rays {} x {reps}, hits raw {raw_hits} ours {ours_hits}",
        rays.len()
    );
    println!("raw obvhs closest hit:       {:8.2} Mrays/s", raw / 1e6);
    println!(
        "aggtool Accel::intersect:    {:8.2} Mrays/s ({:.2} of raw)",
        ours / 1e6,
        ours / raw
    );

    let lights = Lights {
        environment: Environment::Constant(Vec3::new(0.6, 0.7, 0.9)),
        sun: Some(Sun {
            direction: Vec3::new(0.4, 1.0, 0.3).normalize(),
            irradiance: Vec3::splat(3.0),
        }),
    };
    let (_, stats) = render(
        &accel,
        &camera,
        &lights,
        ReferenceSettings { spp, seed: 0 },
        &aggtool::util::no_progress,
    );
    println!(
        "reference renderer:          {:8.2} Mrays/s ({:.2} of raw; {} rays incl. shadow and BSDF rays, {:.2} s at {size}x{size}, {spp} spp)",
        stats.rays_per_second() / 1e6,
        stats.rays_per_second() / raw,
        stats.rays,
        stats.seconds
    );
    println!("threads: {}", rayon::current_num_threads());
    Ok(())
}
