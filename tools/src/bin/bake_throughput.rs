//! Bake throughput: bakes an asset (to a temporary file) and sets the visibility rays per second
//! the bake reached against the raw throughput of the same BVH on rays of the same kind
//! (`Accel::occluded` from random surface points in uniform directions, all threads), and
//! prints where the time went per level.
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin bake_throughput -- [ASSET] [--max-res 64] [--rays 1000000]
//! ```

use std::time::Instant;

use aggtool::bake::{bake_to_file, BakeSettings};
use aggtool::math::rng::Pcg32;
use aggtool::math::sampling::{square_to_triangle, square_to_uniform_sphere};
use aggtool::trace::{offset_origin, Accel, Ray};
use rayon::prelude::*;

use aggtool_tools as common;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let get = |flag: &str, default: u32| common::flag_u32(&args, flag, default);
    let max_res = get("--max-res", 64);
    let n_rays = get("--rays", 1_000_000) as usize;
    let default = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets/sh3d_chandelier_scopia/chandelier-lamp.obj");
    let path = args
        .iter()
        .find(|a| !a.starts_with("--") && a.parse::<u32>().is_err())
        .map(std::path::PathBuf::from)
        .unwrap_or(default);
    let scene = aggtool::import::load(&path, Default::default())?;
    println!("input: {}: {}", path.display(), scene.summary());

    // Raw BVH throughput on surface-to-anywhere rays.
    let accel = Accel::build(&scene);
    let tris: Vec<[glam::Vec3; 3]> = scene
        .instances
        .iter()
        .flat_map(|inst| {
            let m = &scene.meshes[inst.mesh as usize];
            (0..m.triangles.len())
                .map(move |t| m.triangle(t).map(|p| inst.transform.transform_point3(p)))
        })
        .collect();
    let mut rng = Pcg32::new(1, 2);
    let rays: Vec<Ray> = (0..n_rays)
        .map(|_| {
            let t = tris[rng.next_u32() as usize % tris.len()];
            let b = square_to_triangle(rng.next_2d());
            let p = t[0] * (1.0 - b.x - b.y) + t[1] * b.x + t[2] * b.y;
            let ng = (t[1] - t[0]).cross(t[2] - t[0]).normalize_or_zero();
            let d = square_to_uniform_sphere(rng.next_2d());
            Ray::new(offset_origin(p, ng, d), d)
        })
        .collect();
    let t0 = Instant::now();
    let blocked = rays.par_iter().filter(|r| accel.occluded(r)).count();
    let raw = n_rays as f64 / t0.elapsed().as_secs_f64();
    println!(
        "raw BVH: {:.2} Mrays/s occluded() on {} surface rays ({:.0}% blocked), all threads",
        raw / 1e6,
        n_rays,
        100.0 * blocked as f64 / n_rays as f64
    );

    let dir = tempfile::tempdir()?;
    let out = dir.path().join("probe.agg");
    let settings = BakeSettings {
        max_res,
        ..Default::default()
    };
    let r = bake_to_file(
        &scene,
        "probe",
        &settings,
        &out,
        &aggtool::util::no_progress,
    )?;
    println!(
        "bake: {:.1} s, {} bytes, {} visibility rays at {:.2} Mrays/s over the voxel and face stages = {:.2} of raw",
        r.total_seconds,
        r.bytes,
        r.rays,
        r.rays_per_second / 1e6,
        r.rays_per_second / raw
    );
    let threads = rayon::current_num_threads() as f64;
    for l in &r.levels {
        // AIV rays over the CPU time of the AIV part alone, as a rate of all threads.
        let aiv_rate = l.aiv_rays as f64 / (l.cpu_aiv / threads).max(1e-9);
        let abv_rate = l.abv_rays as f64 / l.seconds.faces.max(1e-9);
        println!(
            "level {:>4}³: {:>7} voxels {:>7} faces | voxelize {:>6.2} s | voxels {:>7.2} s (cpu: statistics {:>6.1} s, AIV {:>6.1} s; AIV {:.2} Mrays/s = {:.2} of raw) | faces {:>7.2} s (ABV {:.2} Mrays/s)",
            l.res,
            l.voxels,
            l.faces,
            l.seconds.voxelize,
            l.seconds.voxels,
            l.cpu_statistics,
            l.cpu_aiv,
            aiv_rate / 1e6,
            aiv_rate / raw,
            l.seconds.faces,
            abv_rate / 1e6
        );
    }
    Ok(())
}
