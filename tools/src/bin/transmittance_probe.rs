//! Checks the aggregate's background transmittance against the mesh: from a camera framing a
//! scene, the mean background weight of the LoD runtime (ABV where the ray met a primitive,
//! 1 elsewhere) and of the exponential-volume baseline, against the fraction of the same rays
//! that escape the real geometry. A bias here is a bias in every render of partial coverage.
//!
//!   cargo run --release -p aggtool-tools --bin transmittance_probe -- [SCENE] [RES]
//! SCENE: a hard-case name (default lattice) or an asset path; RES: the level to probe (32);
//! BAKE: the bake's finest resolution (RES), to probe a level that is not the finest.

use aggtool::bake::{bake_to_file, BakeSettings};
use aggtool::format::Aggregate;
use aggtool::math::rng::Pcg32;
use aggtool::runtime::{LodScene, PrimitiveKind, TraceSettings};
use aggtool::trace::Accel;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).map(String::as_str).unwrap_or("lattice");
    let res: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(32);
    let bake_res: u32 = args
        .get(3)
        .and_then(|s| s.parse().ok())
        .unwrap_or(res)
        .max(res);
    let level = (bake_res / res).max(1).trailing_zeros() as usize;
    let scene = match aggtool::gen::generate(
        name,
        &aggtool::gen::GenSettings {
            triangles: 20_000,
            ..Default::default()
        },
    ) {
        Some(s) => s.to_scene(),
        None => aggtool::import::load(std::path::Path::new(name), Default::default())?,
    };
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("p.agg");
    let bake = BakeSettings {
        max_res: bake_res,
        ..Default::default()
    };
    bake_to_file(&scene, name, &bake, &path, &aggtool::util::no_progress)?;
    let lod = LodScene::new(Aggregate::open(&path)?);
    let accel = Accel::build(&scene);
    let view = aggtool::eval::study_view(&scene, res, 1);
    let lights = view.lights()?;
    let cam = view.camera();
    let mut rng = Pcg32::new(9, 9);
    let (mut t_mesh, mut t_ours, mut t_vol, mut n, mut p_plus) =
        (0.0f64, 0.0f64, 0.0f64, 0u64, 0u64);
    let (mut l_ref, mut l_ours, mut l_vol) =
        (glam::DVec3::ZERO, glam::DVec3::ZERO, glam::DVec3::ZERO);
    let mut count = 0u64;
    let mut cov = 0.0f64;
    for y in 0..res {
        for x in 0..res {
            for _ in 0..16 {
                let p = glam::Vec2::new(x as f32, y as f32) + rng.next_2d();
                let (o, d) = cam.ray(p);
                let ray = aggtool::trace::Ray::new(o, d);
                let cone = aggtool::runtime::Cone::new(o, d, cam.pixel_angle());
                let ours = lod.trace(
                    &cone,
                    &lights,
                    &TraceSettings {
                        level: Some(level),
                        ..Default::default()
                    },
                    &mut rng,
                );
                let vol = lod.trace(
                    &cone,
                    &lights,
                    &TraceSettings {
                        level: Some(level),
                        primitive: PrimitiveKind::Volume,
                        ..Default::default()
                    },
                    &mut rng,
                );
                if ours.primitives == 0 && accel.intersect(&ray).is_none() {
                    continue; // outside everything: not informative
                }
                n += 1;
                p_plus += (ours.primitives > 0) as u64;
                t_mesh += accel.intersect(&ray).is_none() as u64 as f64;
                t_ours += ours.transmittance as f64;
                t_vol += vol.transmittance as f64;
                l_ref += aggtool::render::reference::radiance(
                    &accel, &lights, &ray, &mut rng, &mut count,
                )
                .as_dvec3();
                l_ours += ours.radiance.as_dvec3();
                cov += ours.coverage as f64;
                l_vol += vol.radiance.as_dvec3();
            }
        }
    }
    let n = n.max(1) as f64;
    println!(
        "{name} {res}³ (level {level} of a {bake_res}³ bake): {n} rays meeting a primitive or the mesh; P+ {:.3}; background weight: mesh {:.4}, ours {:.4}, volume {:.4}",
        p_plus as f64 / n,
        t_mesh / n,
        t_ours / n,
        t_vol / n
    );
    println!(
        "ours: coverage {:.4} + transmittance {:.4} = {:.4} (1 when consistent)",
        cov / n,
        t_ours / n,
        (cov + t_ours) / n
    );
    println!(
        "mean radiance over those rays: reference {:.4?}, ours {:.4?}, volume {:.4?}",
        l_ref / n,
        l_ours / n,
        l_vol / n
    );
    Ok(())
}
