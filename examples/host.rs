//! A host renderer on the runtime's traversal layer: it opens an `.agg`, makes its own pinhole
//! camera and its own random numbers, and shades the voxels the cones meet with its own
//! lighting code (a sun and a sky colour, no importance sampling), the way a production
//! renderer links the library and keeps its own integrator.
//!
//! ```text
//! cargo run --release --example host -- [FILE.agg] [-o out.ppm] [--size 96] [--spp 8]
//! ```
//!
//! Without a file it bakes a small generated tree into a temporary folder first. It prints the
//! image's mean, its coverage and the time, and writes a binary PPM (sRGB, clamped).

mod common;

use std::path::PathBuf;

use aggtool::bsdf::Bsdf;
use aggtool::math::sampling::Sampler;
use aggtool::runtime::{Cone, LodScene, TraceSettings};
use glam::{Vec2, Vec3};

/// The host's own random numbers: a 64-bit xorshift*, one stream per pixel.
struct XorShift(u64);

impl Sampler for XorShift {
    fn next_1d(&mut self) -> f32 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let x = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d);
        (x >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// The host's own lighting: a sun and a uniform sky, the sky estimated with one uniformly
/// sampled direction per hit.
struct HostLights {
    sun_dir: Vec3,
    sun: Vec3,
    sky: Vec3,
}

impl HostLights {
    /// Radiance the voxel reflects towards `wo`: the sun through the voxel's incident
    /// visibility, and one sky direction over the sphere (pdf 1/4π).
    fn shade(&self, hit: &aggtool::runtime::Hit, wo: Vec3, rng: &mut XorShift) -> Vec3 {
        let v = &hit.voxel;
        let mut l = v.eval(self.sun_dir, wo) * self.sun * v.incident_visibility(self.sun_dir);
        let u = rng.next_2d();
        let z = 1.0 - 2.0 * u.x;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = std::f32::consts::TAU * u.y;
        let wi = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        l += v.eval(wi, wo) * self.sky * v.incident_visibility(wi) * (4.0 * std::f32::consts::PI);
        l
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let size = common::flag_u32(&args, "--size", 96);
    let spp = common::flag_u32(&args, "--spp", 8).max(1);
    let out = args
        .iter()
        .position(|a| a == "-o")
        .and_then(|i| args.get(i + 1))
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("aggtool-host.ppm"));
    let tmp = tempfile::tempdir()?;
    let path = match args.iter().find(|a| a.ends_with(".agg")) {
        Some(p) => PathBuf::from(p),
        None => {
            // A small generated tree, baked at 32³.
            let scene = aggtool::gen::generate(
                "foliage",
                &aggtool::gen::GenSettings {
                    triangles: 3000,
                    ..Default::default()
                },
            )
            .expect("a generated scene")
            .to_scene();
            let p = tmp.path().join("tree.agg");
            let settings = aggtool::bake::BakeSettings {
                max_res: 32,
                min_res: 4,
                samples: 8,
                aiv_rays: 8,
                aiv_res: 16,
                abv_res: 16,
                ..Default::default()
            };
            aggtool::bake::bake_to_file(
                &scene,
                "tree",
                &settings,
                &p,
                &aggtool::util::no_progress,
            )?;
            p
        }
    };
    let t0 = std::time::Instant::now();
    let scene = LodScene::open(&path)?;
    let (lo, hi) = scene.bounds().ok_or("an empty aggregate")?;
    // The host's own pinhole camera, framing the aggregate from the front and a little above.
    let centre = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length();
    let eye = centre + Vec3::new(0.3, 0.4, 1.0).normalize() * radius * 2.6;
    let forward = (centre - eye).normalize();
    let right = forward.cross(Vec3::Y).normalize();
    let up = right.cross(forward);
    let tan_half = (25f32.to_radians() * 0.5).tan();
    let aperture = 2.0 * tan_half / size as f32;
    let lights = HostLights {
        sun_dir: Vec3::new(0.4, 1.0, 0.3).normalize(),
        sun: Vec3::splat(2.5),
        sky: Vec3::new(0.3, 0.4, 0.6),
    };
    let settings = TraceSettings::default();
    let mut pixels = vec![Vec3::ZERO; (size * size) as usize];
    let mut coverage = 0.0f64;
    for y in 0..size {
        for x in 0..size {
            let mut rng = XorShift(0x9e37_79b9_7f4a_7c15 ^ ((y as u64) << 32 | x as u64) | 1);
            let mut sum = Vec3::ZERO;
            for _ in 0..spp {
                let p = Vec2::new(x as f32, y as f32) + rng.next_2d();
                let sx = (2.0 * p.x / size as f32 - 1.0) * tan_half;
                let sy = (1.0 - 2.0 * p.y / size as f32) * tan_half;
                let dir = (forward + sx * right + sy * up).normalize();
                let cone = Cone::new(eye, dir, aperture);
                // Eq. 30 with the host's shading: every voxel met adds its radiance times its
                // coverage weight; the sky shows through the boundary visibility; the whole is
                // divided by the sum of the weights, as the runtime's own shading does
                // (TraceSettings::normalize).
                let mut hits = scene.hits(&cone, &settings);
                let (mut l, mut weights) = (Vec3::ZERO, 0.0f32);
                for h in &mut hits {
                    l += lights.shade(&h, -dir, &mut rng) * h.weight;
                    weights += h.weight;
                }
                let total = weights + hits.transmittance();
                let norm = if total > 0.0 { 1.0 / total } else { 1.0 };
                coverage += (weights * norm) as f64;
                sum += (l + lights.sky * hits.transmittance()) * norm;
            }
            pixels[(y * size + x) as usize] = sum / spp as f32;
        }
    }
    let seconds = t0.elapsed().as_secs_f64();
    let mean = pixels.iter().copied().sum::<Vec3>() / pixels.len() as f32;
    // Binary PPM, sRGB.
    let mut ppm = format!("P6\n{size} {size}\n255\n").into_bytes();
    for p in &pixels {
        for c in p.to_array() {
            let s = aggtool::math::color::linear_to_srgb(c);
            ppm.push((s.clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
        }
    }
    aggtool::util::write_bytes_atomic(&out, &ppm)?;
    println!(
        "host: {} ({} levels), {size}×{size} at {spp} cones/pixel in {seconds:.2} s; mean {:.4} {:.4} {:.4}, mean coverage {:.3}; levels prepared {:?}",
        path.display(),
        scene.level_count(),
        mean.x,
        mean.y,
        mean.z,
        coverage / (size * size * spp) as f64,
        scene.prepared()
    );
    println!("output: {}", out.display());
    if !mean.is_finite() || mean.max_element() <= 0.0 {
        return Err("the image is empty or not finite".into());
    }
    Ok(())
}
