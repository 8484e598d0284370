//! A dolly from far to near over an asset, rendered per frame with the reference path tracer
//! on the mesh and with the LoD, with continuous level of detail (the default) and with the
//! footprint's discrete level: does the LoD "pop" where the level changes?
//!
//! ```text
//! cargo run --release --example flythrough -- ASSET AGG [--frames 60] [--size 128] [--spp 16]
//!     [--zoom 16] [--out DIR]
//! ```
//!
//! The camera moves along the study's view direction (`eval::study_view`, lit by its sun
//! alone, so that the image's mean is the asset's light and no sky dilutes it) from `zoom`
//! times the framing distance to the framing distance, the distances in geometric progression,
//! so that the footprint's level log2(tan(θ/2)·t/s) falls linearly over the frames. The
//! camera keeps the asset in frame as it recedes: the image's side shrinks with the distance
//! and its field of view with it, so that a pixel subtends the same angle in every frame (the
//! footprint grows with the distance, as in a dolly), and the samples per pixel grow with the
//! square of the distance, so that every frame spends the same samples on the asset and its
//! noise stays the same. Each renderer keeps its seed from frame to frame.
//!
//! Per frame it prints each image's mean and, for each LoD, its bias against the reference,
//! e = mean / reference mean − 1. A level switch shows as a step in e from one frame to the
//! next (a "jump", |e_k − e_(k−1)|); the camera's own motion does not, since the reference
//! moves with it. A second reference with another seed, taken as a method, gives the jumps
//! that the reference's noise alone makes: the LoD pops visibly where its jumps exceed those.
//! Writes `flythrough.md` (the table and the summary), `strip.png` (eight frames: the
//! reference, the continuous LoD and the discrete LoD, one row each) and `bias.png` (e of
//! each against the footprint's level, where a pop is a step at a whole level) to `--out`.

mod common;

use std::path::{Path, PathBuf};

use aggtool::eval::plot::{line_plot, Series};
use aggtool::eval::{study_view, tile_png};
use aggtool::film::Image;
use aggtool::render::reference::{self, ReferenceSettings};
use aggtool::render::EnvironmentDesc;
use aggtool::runtime::{LodScene, TraceSettings};
use aggtool::trace::Accel;
use glam::Vec3;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (asset, agg) = match (args.get(1), args.get(2)) {
        (Some(a), Some(g)) => (PathBuf::from(a), PathBuf::from(g)),
        _ => {
            return Err(
                "usage: flythrough ASSET AGG [--frames 60] [--size 128] [--spp 16] \
                 [--zoom 16] [--out DIR]"
                    .into(),
            )
        }
    };
    let value = |flag: &str| common::flag_value(&args, flag);
    let frames: usize = value("--frames").map_or(Ok(60), |s| s.parse())?;
    let size: u32 = value("--size").map_or(Ok(128), |s| s.parse())?;
    let spp: u32 = value("--spp").map_or(Ok(16), |s| s.parse())?;
    let zoom: f32 = value("--zoom").map_or(Ok(16.0), |s| s.parse())?;
    let out = PathBuf::from(value("--out").unwrap_or_else(|| "flythrough".into()));
    if frames < 2 || size == 0 || spp == 0 || !(zoom >= 1.0) {
        return Err("--frames must be at least 2, --size and --spp positive, --zoom ≥ 1".into());
    }
    std::fs::create_dir_all(&out)?;

    let scene = aggtool::import::load(&asset, Default::default())?;
    let accel = Accel::build(&scene);
    let lod = LodScene::open(&agg)?;
    let mut view = study_view(&scene, size, spp);
    view.environment = Some(EnvironmentDesc::Constant {
        constant: aggtool::render::Rgb::Scalar(0.0),
    });
    let target = Vec3::from(view.camera.target);
    let eye = Vec3::from(view.camera.eye);
    let (near, dir) = ((eye - target).length(), (eye - target).normalize());
    let lights = view.lights()?;
    let tan_near = (0.5 * view.camera.fov_y_deg.to_radians()).tan();
    // The angle a pixel subtends (the cone's aperture) in every frame.
    let pixel = 2.0 * (tan_near / size as f32).atan();
    let continuous = TraceSettings::default();
    let discrete = TraceSettings {
        continuous_lod: false,
        ..Default::default()
    };
    struct Frame {
        distance: f32,
        side: u32,
        spp: u32,
        level: f32,
        means: [f64; 4],
        images: [Image; 4],
    }
    let mean = |img: &Image| {
        let m = img.mean();
        (m.x + m.y + m.z) as f64 / 3.0
    };
    let mut rows = Vec::with_capacity(frames);
    for k in 0..frames {
        let distance = near * zoom.powf(1.0 - k as f32 / (frames - 1) as f32);
        let side = ((size as f32 * near / distance).round() as u32).clamp(8, size);
        let spp = (spp as f32 * (size as f32 / side as f32).powi(2)).round() as u32;
        view.camera.eye = (target + dir * distance).to_array();
        view.camera.width = side;
        view.camera.height = side;
        view.camera.fov_y_deg = (2.0 * (tan_near * side as f32 / size as f32).atan()).to_degrees();
        let camera = view.camera();
        let reference_with = |seed| {
            reference::render(
                &accel,
                &camera,
                &lights,
                ReferenceSettings { spp, seed },
                &aggtool::util::no_progress,
            )
            .0
        };
        let lod_with = |settings: &TraceSettings| {
            aggtool::runtime::render(
                &lod,
                &camera,
                &lights,
                spp,
                0,
                settings,
                &aggtool::util::no_progress,
            )
            .0
        };
        let images = [
            reference_with(0),
            reference_with(1),
            lod_with(&continuous),
            lod_with(&discrete),
        ];
        let means = [
            mean(&images[0]),
            mean(&images[1]),
            mean(&images[2]),
            mean(&images[3]),
        ];
        let level = lod.fractional_level(pixel, distance);
        eprintln!("frame {k}: distance {distance:.3}, level {level:.2}, {side}² at {spp} spp");
        rows.push(Frame {
            distance,
            side,
            spp,
            level,
            means,
            images,
        });
    }

    // Bias against the reference (seed 0) of the second reference and of each LoD.
    // NaN where the reference saw nothing (too few samples on the asset): left out below.
    let bias = |f: &Frame, m: usize| {
        if f.means[0] > 0.0 {
            f.means[m] / f.means[0] - 1.0
        } else {
            f64::NAN
        }
    };
    let mut md = String::new();
    md.push_str(&format!(
        "`cargo run --release --example flythrough -- {} {} --frames {frames} --size {size} \
         --spp {spp} --zoom {zoom}`\n\n",
        asset.display(),
        agg.display()
    ));
    md.push_str(
        "| frame | distance | image | spp | level | reference mean | continuous mean | discrete mean \
         | e reference (seed 1) | e continuous | e discrete | jump continuous | jump discrete |\n",
    );
    md.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    let mut jumps = [Vec::new(), Vec::new(), Vec::new()];
    for (k, f) in rows.iter().enumerate() {
        let e = [bias(f, 1), bias(f, 2), bias(f, 3)];
        let j: Vec<f64> = if k == 0 {
            vec![f64::NAN; 3]
        } else {
            let p = &rows[k - 1];
            let ep = [bias(p, 1), bias(p, 2), bias(p, 3)];
            (0..3).map(|m| (e[m] - ep[m]).abs()).collect()
        };
        for m in 0..3 {
            if j[m].is_finite() {
                jumps[m].push(j[m]);
            }
        }
        let cell = |x: f64| {
            if x.is_nan() {
                "".to_string()
            } else {
                format!("{x:.4}")
            }
        };
        md.push_str(&format!(
            "| {k} | {:.3} | {}² | {} | {:.2} | {:.5} | {:.5} | {:.5} | {:+.4} | {:+.4} | {:+.4} | {} | {} |\n",
            f.distance,
            f.side,
            f.spp,
            f.level,
            f.means[0],
            f.means[2],
            f.means[3],
            e[0],
            e[1],
            e[2],
            cell(j[1]),
            cell(j[2]),
        ));
    }
    let summary = |v: &[f64]| {
        let max = v.iter().cloned().fold(0.0, f64::max);
        let rms = (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        (max, rms)
    };
    md.push_str("\n| frame-to-frame jump of e | max | RMS |\n|---|---|---|\n");
    for (name, m) in [
        ("reference, seed 1 (noise alone)", 0),
        ("LoD, continuous", 1),
        ("LoD, discrete", 2),
    ] {
        let (max, rms) = summary(&jumps[m]);
        md.push_str(&format!("| {name} | {max:.4} | {rms:.4} |\n"));
    }
    let mean_abs = |m: usize| {
        let e: Vec<f64> = rows
            .iter()
            .map(|f| bias(f, m).abs())
            .filter(|e| e.is_finite())
            .collect();
        e.iter().sum::<f64>() / e.len() as f64
    };
    md.push_str(&format!(
        "\nMean |e| over the frames: continuous {:.4}, discrete {:.4} (the reference's noise {:.4}).\n",
        mean_abs(2),
        mean_abs(3),
        mean_abs(1)
    ));
    print!("{md}");
    std::fs::write(out.join("flythrough.md"), &md)?;

    // Eight frames, evenly spaced, enlarged to `size` (nearest neighbour): reference,
    // continuous, discrete.
    let picks: Vec<usize> = (0..8).map(|i| i * (frames - 1) / 7).collect();
    let strip: Vec<Vec<Vec<u8>>> = [0usize, 2, 3]
        .iter()
        .map(|&m| {
            picks
                .iter()
                .map(|&k| {
                    let f = &rows[k];
                    let rgb = f.images[m].to_srgb8(1.0);
                    let mut big = vec![0u8; (size * size * 3) as usize];
                    for y in 0..size {
                        for x in 0..size {
                            let (sx, sy) = (x * f.side / size, y * f.side / size);
                            let s = ((sy * f.side + sx) * 3) as usize;
                            let d = ((y * size + x) * 3) as usize;
                            big[d..d + 3].copy_from_slice(&rgb[s..s + 3]);
                        }
                    }
                    big
                })
                .collect()
        })
        .collect();
    tile_png(&out.join("strip.png"), &strip, size, size)?;
    println!("wrote {}", Path::new(&out).join("strip.png").display());

    // e against the footprint's level: the discrete LoD's steps sit at whole levels.
    let series: Vec<Series> = [
        ("reference, seed 1", [150, 150, 150], 1),
        ("LoD, continuous", [40, 90, 200], 2),
        ("LoD, discrete", [200, 60, 40], 3),
    ]
    .iter()
    .map(|&(name, color, m)| Series {
        name: name.into(),
        color,
        points: rows.iter().map(|f| (f.level as f64, bias(f, m))).collect(),
    })
    .collect();
    line_plot(
        &out.join("bias.png"),
        &format!(
            "{}: image mean / reference mean - 1 per frame",
            asset.file_stem().unwrap_or_default().to_string_lossy()
        ),
        "footprint level log2(tan(a/2) t / s)",
        "e",
        &series,
    )?;
    println!("wrote {}", Path::new(&out).join("bias.png").display());
    Ok(())
}
