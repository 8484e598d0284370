//! What lazy opening costs: open time, time to first pixel, the levels a view touches and the
//! resident memory, for one `.agg` viewed from near and from afar (issue 15's open-time
//! figures).
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin open_profile -- FILE.agg [--size 128] [--spp 4] [--far 40]
//! ```
//!
//! Each view runs in a fresh process (this program re-executes itself with `--view near` or
//! `--view far`), so that the resident memory of one view does not include the other's. Near:
//! the camera at 1.5 bounding radii, the finest level by footprint; far: at `--far` radii
//! (default 40), where the footprint picks coarse levels. Resident memory is VmRSS and VmHWM
//! from /proc/self/status (Linux), which counts the mapped file's pages that were touched.

use aggtool_tools as common;

use std::path::Path;
use std::time::Instant;

use aggtool::film::Camera;
use aggtool::lights::Lights;
use aggtool::runtime::{Cone, LodScene, TraceSettings};
use glam::{Vec2, Vec3};

/// VmRSS and VmHWM in MiB, or zeros where /proc is absent.
fn rss_mib() -> (f64, f64) {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        s.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .map_or(0.0, |kb| kb / 1024.0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

fn view(path: &Path, far: bool, size: u32, spp: u32, radii: f32) -> Result<(), String> {
    let (rss0, _) = rss_mib();
    let t0 = Instant::now();
    let scene = LodScene::open(path).map_err(|e| e.to_string())?;
    let open = t0.elapsed().as_secs_f64();
    let (rss_open, _) = rss_mib();
    let (lo, hi) = scene.bounds().ok_or("an empty aggregate")?;
    let centre = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length();
    let d = if far { radii } else { 1.5 };
    let eye = centre + Vec3::new(0.3, 0.35, 1.0).normalize() * radius * d;
    // Near: the asset fills the frame; far: the same field of view, so the asset is small.
    let fov = 2.0 * (1.0 / 1.5f32).asin().to_degrees();
    let camera = Camera::look_at(eye, centre, Vec3::Y, fov, size, size);
    let lights = Lights::constant(Vec3::ONE);
    let settings = TraceSettings::default();
    let aperture = camera.pixel_angle();
    let mut rng = aggtool::math::rng::Pcg32::new(7, 0);
    // First pixel: the centre pixel's first cone, which prepares the level(s) it needs.
    let t1 = Instant::now();
    let (o, dir) = camera.ray(Vec2::splat(size as f32 * 0.5));
    let _ = scene.trace(&Cone::new(o, dir, aperture), &lights, &settings, &mut rng);
    let first = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let (img, stats) = aggtool::runtime::render(
        &scene,
        &camera,
        &lights,
        spp,
        1,
        &settings,
        &aggtool::util::no_progress,
    );
    let frame = t2.elapsed().as_secs_f64();
    let (rss, hwm) = rss_mib();
    let prepared: Vec<String> = scene
        .prepared()
        .iter()
        .enumerate()
        .filter(|(_, p)| **p)
        .map(|(l, _)| format!("{}³", scene.grid(l).res))
        .collect();
    let file_mib = std::fs::metadata(path).map_or(0.0, |m| m.len() as f64 / (1 << 20) as f64);
    println!(
        "{}: {:.1} MiB file, open {:.2} ms, first pixel {:.1} ms, {size}² × {spp} spp in {:.2} s; levels prepared [{}]; RSS before open {:.1} MiB, after open {:.1}, after the frame {:.1} (peak {:.1}); mean {:.4}; {}",
        if far { "far " } else { "near" },
        file_mib,
        open * 1e3,
        first * 1e3,
        frame,
        prepared.join(", "),
        rss0,
        rss_open,
        rss,
        hwm,
        img.mean().x,
        stats.line("LoD"),
    );
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let file = args
        .iter()
        .skip(1)
        .find(|a| a.ends_with(".agg"))
        .ok_or("usage: open_profile FILE.agg [--size N] [--spp N] [--far RADII]")?;
    let size = common::flag_u32(&args, "--size", 128);
    let spp = common::flag_u32(&args, "--spp", 4).max(1);
    let radii = common::flag_u32(&args, "--far", 40) as f32;
    if let Some(i) = args.iter().position(|a| a == "--view") {
        let far = args.get(i + 1).map(String::as_str) == Some("far");
        return Ok(view(Path::new(file), far, size, spp, radii)?);
    }
    for which in ["near", "far"] {
        let status = std::process::Command::new(&args[0])
            .args(&args[1..])
            .args(["--view", which])
            .status()?;
        if !status.success() {
            return Err(format!("the {which} view failed").into());
        }
    }
    Ok(())
}
