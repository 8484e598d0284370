//! Known-answer renders of the reference path tracer, and determinism.

mod common;

use std::f32::consts::PI;

use aggtool::film::{Camera, Image};
use aggtool::gen::glb::{MaterialData, NodeData, SceneData};
use aggtool::gen::shapes;
use aggtool::lights::{Environment, Lights, Sun};
use aggtool::render::reference::{render, ReferenceSettings};
use aggtool::scene::Scene;
use aggtool::trace::Accel;
use aggtool::util::no_progress;
use glam::{Mat4, Vec3};

fn lambert(rgb: [f32; 3]) -> MaterialData {
    let mut m = MaterialData::new("lambert", rgb, 0.0, 1.0);
    m.specular_factor = Some(0.0);
    m
}

fn one_mesh(mesh: aggtool::gen::glb::MeshData, mat: MaterialData) -> Scene {
    SceneData::single(mesh, mat).to_scene()
}

fn camera(eye: Vec3, target: Vec3, size: u32, fov: f32) -> Camera {
    Camera::look_at(eye, target, Vec3::Y, fov, size, size)
}

fn settings(spp: u32) -> ReferenceSettings {
    ReferenceSettings { spp, seed: 3 }
}

/// A Lambertian plane of albedo ρ under a constant environment L has radiance ρL (it sees the
/// whole upper hemisphere, and ∫ cos/π = 1). Mean over 1024 pixels at 64 spp: standard error
/// ~0.1%, tested at 1%; single pixels at 15%.
#[test]
fn lambertian_plane_under_constant_sky() {
    let rho = [0.6, 0.3, 0.1];
    let s = one_mesh(
        shapes::quad(Vec3::new(-1.0, 0.0, -1.0), Vec3::Z * 2.0, Vec3::X * 2.0, 2),
        lambert(rho),
    );
    let accel = Accel::build(&s);
    let lights = Lights {
        environment: Environment::Constant(Vec3::new(2.0, 1.0, 0.5)),
        sun: None,
    };
    // Looking down at the plane, which fills the image.
    let cam = camera(Vec3::new(0.0, 1.0, 0.01), Vec3::ZERO, 32, 40.0);
    let (img, stats) = render(&accel, &cam, &lights, settings(64), &no_progress);
    let expect = Vec3::from(rho) * Vec3::new(2.0, 1.0, 0.5);
    let mean = img.mean();
    assert!(
        ((mean - expect) / expect).abs().max_element() < 0.01,
        "{mean} vs {expect}"
    );
    for p in &img.pixels {
        assert!(
            ((*p - expect) / expect).abs().max_element() < 0.15,
            "{p} vs {expect}"
        );
    }
    assert_eq!(stats.invalid_samples, 0);
}

/// White furnace: a convex white Lambertian sphere under a unit environment is invisible
/// (radiance 1 everywhere), since direct lighting at each point integrates the unoccluded
/// hemisphere.
#[test]
fn white_furnace() {
    let s = one_mesh(
        shapes::sphere(Vec3::ZERO, 0.5, 64, |_| 0.0),
        lambert([1.0; 3]),
    );
    let accel = Accel::build(&s);
    let lights = Lights {
        environment: Environment::Constant(Vec3::ONE),
        sun: None,
    };
    let cam = camera(Vec3::new(0.0, 0.0, 2.0), Vec3::ZERO, 32, 35.0);
    let (img, _) = render(&accel, &cam, &lights, settings(64), &no_progress);
    let mean = img.mean();
    assert!((mean - Vec3::ONE).abs().max_element() < 0.01, "{mean}");
    for p in &img.pixels {
        assert!((*p - Vec3::ONE).abs().max_element() < 0.15, "{p}");
    }
}

/// A plane lit by a sun at 60° from its normal, black sky: L = ρ/π · E · cos 60°, exactly
/// (no random sampling contributes).
#[test]
fn sun_on_a_plane_is_exact() {
    let rho = 0.5;
    let s = one_mesh(
        shapes::quad(Vec3::new(-1.0, 0.0, -1.0), Vec3::Z * 2.0, Vec3::X * 2.0, 1),
        lambert([rho; 3]),
    );
    let accel = Accel::build(&s);
    let theta = 60f32.to_radians();
    let lights = Lights {
        environment: Environment::Constant(Vec3::ZERO),
        sun: Some(Sun {
            direction: Vec3::new(theta.sin(), theta.cos(), 0.0),
            irradiance: Vec3::splat(3.0),
        }),
    };
    let cam = camera(Vec3::new(0.0, 1.0, 0.01), Vec3::ZERO, 16, 40.0);
    let (img, _) = render(&accel, &cam, &lights, settings(4), &no_progress);
    let expect = rho / PI * 3.0 * theta.cos();
    for p in &img.pixels {
        assert!(
            (*p - Vec3::splat(expect)).abs().max_element() < 1e-5,
            "{p} vs {expect}"
        );
    }
}

/// A sphere in shadow of an occluder receives no sun.
#[test]
fn shadows_block_the_sun() {
    let mut scene = SceneData {
        meshes: vec![
            vec![(
                shapes::quad(Vec3::new(-1.0, 0.0, -1.0), Vec3::Z * 2.0, Vec3::X * 2.0, 1),
                0,
            )],
            vec![(
                shapes::quad(Vec3::new(-0.5, 1.0, -0.5), Vec3::X, Vec3::Z, 1),
                0,
            )],
        ],
        materials: vec![lambert([0.5; 3])],
        nodes: vec![],
    };
    for mesh in 0..2 {
        scene.nodes.push(NodeData {
            mesh,
            matrix: Mat4::IDENTITY,
            gpu_instances: vec![],
        });
    }
    let s = scene.to_scene();
    let accel = Accel::build(&s);
    let lights = Lights {
        environment: Environment::Constant(Vec3::ZERO),
        sun: Some(Sun {
            direction: Vec3::Y,
            irradiance: Vec3::ONE,
        }),
    };
    // Look at the ground's centre from below the blocker, at a grazing angle.
    let cam = camera(Vec3::new(0.0, 0.3, 0.9), Vec3::new(0.0, 0.0, 0.0), 8, 10.0);
    let (img, _) = render(&accel, &cam, &lights, settings(1), &no_progress);
    assert_eq!(img.get(4, 4), Vec3::ZERO);
}

fn foliage_render(threads: usize) -> (Image, aggtool::film::ImageStats) {
    let (_d, s) = common::generated("foliage", 3000, false);
    let accel = Accel::build(&s);
    let lights = Lights {
        environment: Environment::Constant(Vec3::new(0.5, 0.6, 0.8)),
        sun: Some(Sun {
            direction: Vec3::new(0.3, 1.0, 0.2).normalize(),
            irradiance: Vec3::splat(2.0),
        }),
    };
    let cam = camera(Vec3::new(0.0, 0.6, 2.5), Vec3::new(0.0, 0.6, 0.0), 24, 40.0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| render(&accel, &cam, &lights, settings(8), &no_progress))
}

#[test]
fn renders_are_deterministic_across_thread_counts() {
    let (a, sa) = foliage_render(1);
    let (b, sb) = foliage_render(2);
    let (c, sc) = foliage_render(2);
    assert_eq!(a, b);
    assert_eq!(b, c);
    for (s, threads) in [(sa, 1), (sb, 2), (sc, 2)] {
        common::assert_clean_render(&a, &s, &format!("{threads} threads"));
    }
}
