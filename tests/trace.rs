//! The two-level BVH against brute force on random rays, with and without instances and
//! alpha cut-outs.

mod common;

use aggtool::math::rng::Pcg32;
use aggtool::math::sampling::square_to_uniform_sphere;
use aggtool::scene::Scene;
use aggtool::trace::{Accel, Ray};
use glam::{Vec2, Vec3};

/// Closest hit by testing every triangle of every instance in world space (t, instance, tri).
fn brute_force(scene: &Scene, ray: &Ray) -> Option<(f32, u32, u32)> {
    let mut best: Option<(f32, u32, u32)> = None;
    for (ii, inst) in scene.instances.iter().enumerate() {
        let m = &scene.meshes[inst.mesh as usize];
        let mat = &scene.materials[m.material as usize];
        for (ti, t) in m.triangles.iter().enumerate() {
            let [a, b, c] = t.map(|i| inst.transform.transform_point3(m.positions[i as usize]));
            // Möller–Trumbore in f64 for a trustworthy oracle.
            let (o, d) = (ray.origin.as_dvec3(), ray.dir.as_dvec3());
            let (a, b, c) = (a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
            let e1 = b - a;
            let e2 = c - a;
            let p = d.cross(e2);
            let det = e1.dot(p);
            if det.abs() < 1e-18 {
                continue;
            }
            let tv = o - a;
            let u = tv.dot(p) / det;
            let q = tv.cross(e1);
            let v = d.dot(q) / det;
            let tt = e2.dot(q) / det;
            if u < 0.0 || v < 0.0 || u + v > 1.0 || tt < ray.tmin as f64 || tt > ray.tmax as f64 {
                continue;
            }
            if mat.has_cutout() && !m.uvs.is_empty() {
                let uv = m.uvs[t[0] as usize] * (1.0 - u - v) as f32
                    + m.uvs[t[1] as usize] * u as f32
                    + m.uvs[t[2] as usize] * v as f32;
                if !mat.is_opaque_at(&scene.textures, uv) {
                    continue;
                }
            }
            if best.is_none_or(|(bt, _, _)| (tt as f32) < bt) {
                best = Some((tt as f32, ii as u32, ti as u32));
            }
        }
    }
    best
}

fn check_scene(scene: &Scene, rays: usize, seed: u64) {
    let accel = Accel::build(scene);
    let (c, r) = scene.bounding_sphere();
    let mut rng = Pcg32::new(seed, 77);
    let mut hits = 0;
    let mut mismatched = 0;
    for _ in 0..rays {
        let o = c + square_to_uniform_sphere(rng.next_2d()) * r * 1.5 * rng.next_f32();
        // Aim at a random point inside the bounds so that most rays hit something.
        let target = c + square_to_uniform_sphere(rng.next_2d()) * r * 0.5 * rng.next_f32();
        let ray = Ray::new(o, (target - o).normalize_or(Vec3::Y));
        let fast = accel.intersect(&ray);
        let slow = brute_force(scene, &ray);
        match (fast, slow) {
            (Some(f), Some((t, inst, tri))) => {
                hits += 1;
                let tol = 1e-4 * (1.0 + t.abs());
                if (f.t - t).abs() > tol {
                    mismatched += 1;
                } else if (f.instance, f.triangle) != (inst, tri) {
                    // Equal distances on two triangles (a shared edge) are a tie, not an error.
                    let sp = accel.surface(&ray, &f);
                    assert!(
                        (sp.p - ray.at(t)).length() < 1e-3 * (1.0 + r),
                        "different hit points"
                    );
                }
                assert!(f.bary.x >= -1e-3 && f.bary.y >= -1e-3 && f.bary.x + f.bary.y <= 1.001);
            }
            (None, None) => {}
            // Rays grazing an edge may go either way in f32 against f64.
            _ => mismatched += 1,
        }
        // The any-hit query agrees with the closest-hit one.
        assert_eq!(accel.occluded(&ray), fast.is_some());
    }
    // Edge-grazing disagreements between f32 and f64 must stay rare: under 0.5% of rays.
    assert!(
        mismatched * 200 <= rays,
        "{mismatched} of {rays} rays disagree"
    );
    assert!(
        hits * 4 > rays,
        "too few hits ({hits}) for a meaningful test"
    );
}

#[test]
fn single_level_matches_brute_force() {
    let (_d, s) = common::generated("lattice", 3000, false);
    check_scene(&s, 3000, 1);
}

#[test]
fn instances_match_brute_force() {
    let (_d, s) = common::generated("buildings", 2000, false);
    assert!(s.instances.len() > 100);
    check_scene(&s, 1500, 2);
}

#[test]
fn cutouts_match_brute_force() {
    let (_d, s) = common::generated("foliage", 3000, false);
    assert!(s.materials.iter().any(|m| m.has_cutout()));
    check_scene(&s, 3000, 3);
}

/// A ray through a cut-out part of a leaf passes; through the opaque part it stops.
#[test]
fn cutout_lets_rays_through() {
    let (_d, s) = common::generated("foliage", 200, false);
    let accel = Accel::build(&s);
    let leaves = s
        .meshes
        .iter()
        .position(|m| s.materials[m.material as usize].has_cutout())
        .unwrap();
    let m = &s.meshes[leaves];
    let mat = &s.materials[m.material as usize];
    let mut through = 0;
    let mut blocked = 0;
    // Rays straight at points of the first leaf quad, at uv corners (cut) and centre (opaque).
    let [a, b, c] = m.triangle(0);
    let n = (b - a).cross(c - a).normalize();
    for (w, expect_opaque) in [([0.02f32, 0.02], false), ([0.1, 0.5], true)] {
        let [i0, i1, i2] = m.triangles[0];
        let _ = (i0, i1, i2);
        // Point by barycentrics (w[0], w[1]) of vertices 1 and 2.
        let p = a * (1.0 - w[0] - w[1]) + b * w[0] + c * w[1];
        let uv = m.uvs[i0 as usize] * (1.0 - w[0] - w[1])
            + m.uvs[i1 as usize] * w[0]
            + m.uvs[i2 as usize] * w[1];
        assert_eq!(mat.is_opaque_at(&s.textures, uv), expect_opaque, "uv {uv}");
        let ray = Ray {
            origin: p + n * 1e-3,
            dir: -n,
            tmin: 0.0,
            tmax: 2e-3,
        };
        if accel.occluded(&ray) {
            blocked += 1;
        } else {
            through += 1;
        }
    }
    assert_eq!((through, blocked), (1, 1));
    let _ = Vec2::ZERO;
}
