//! `aggtool demo`, the main job on a built-in scene: generate a tree, bake it, render the LoD
//! and the reference renderer at equal time, and compare both with a converged reference in
//! one captioned picture (`side-by-side.png`: reference | LoD | reference at equal time | the
//! two differences on one scale).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Result;
use serde::Serialize;

use crate::bake::{bake_to_file, BakeSettings};
use crate::film::ImageStats;
use crate::gen::{self, GenSettings};
use crate::render::compare::{compare, difference_image};
use crate::render::label::with_caption;
use crate::render::reference::{self, ReferenceSettings};
use crate::render::{EnvironmentDesc, Rgb, SunDesc, View};
use crate::runtime::{LodScene, TraceSettings};
use crate::trace::Accel;
use crate::util::Progress;

/// What the demo generates, bakes and renders.
#[derive(Clone, Debug)]
pub struct DemoSettings {
    /// Triangles of the generated tree (`gen foliage`).
    pub triangles: usize,
    /// The bake (the default: 64³ finest, 8³ coarsest, 32² boundary maps, to stay within
    /// the demo's two minutes, whose cells may average centred windows,
    /// [`BakeSettings::abv_windows`]). With blocks alone the tree's 32² maps let 7.8% too
    /// little sky through the crown, where a cone comes in (0.1879 against the mesh's 0.2039,
    /// `tools/src/bin/cone_weights_probe.rs`); with windows 0.2032, the LoD's RMSE 0.0177
    /// instead of 0.0187 for 1.29× the file and the same bake time
    /// (`docs/src/studies/2026-12-07-transmittance-through-foliage.md`).
    pub bake: BakeSettings,
    /// Image side in pixels (128: a finest voxel about 1.3 pixels wide at the target).
    pub image: u32,
    /// Cones per pixel of the LoD.
    pub lod_spp: u32,
    /// Samples per pixel of the converged reference both are judged against.
    pub truth_spp: u32,
}

impl Default for DemoSettings {
    fn default() -> Self {
        DemoSettings {
            triangles: 40_000,
            bake: BakeSettings {
                max_res: 64,
                min_res: 8,
                abv_res: 32,
                abv_windows: true,
                ..Default::default()
            },
            image: 128,
            lod_spp: 64,
            truth_spp: 1024,
        }
    }
}

/// What the demo did and measured.
#[derive(Clone, Debug, Serialize)]
pub struct DemoReport {
    /// The generated asset.
    pub asset: PathBuf,
    /// Triangles of the generated asset.
    pub triangles: usize,
    /// Import warnings of the generated asset (none expected).
    pub warnings: Vec<String>,
    /// Bake wall seconds.
    pub bake_seconds: f64,
    /// Levels baked.
    pub levels: usize,
    /// Bytes of the `.agg` file.
    pub bytes: u64,
    /// The LoD render (its `stats:` figures).
    pub lod: ImageStats,
    /// Wall seconds of the LoD, opening the file included.
    pub lod_seconds: f64,
    /// The reference renderer at about the LoD's time: its spp.
    pub reference_spp: u32,
    /// The reference render's figures.
    pub reference: ImageStats,
    /// RMSE of the LoD against the converged reference.
    pub lod_rmse: f64,
    /// RMSE of the reference at that spp against the converged one.
    pub reference_rmse: f64,
    /// The picture.
    pub picture: PathBuf,
    /// Wall seconds of the whole demo.
    pub seconds: f64,
    /// Cones per pixel of the LoD.
    pub lod_spp: u32,
    /// Samples per pixel of the converged reference both are judged against.
    pub truth_spp: u32,
}

/// Runs the demo into `output` (created if needed): `foliage.glb`, `foliage.agg`, `view.json`,
/// `reference-1024spp.exr`, `lod.exr`, `reference-equal-time.exr` and `side-by-side.png`.
pub fn demo(output: &Path, settings: &DemoSettings, progress: Progress) -> Result<DemoReport> {
    let t_all = Instant::now();
    std::fs::create_dir_all(output)?;
    let gen_settings = GenSettings {
        triangles: settings.triangles,
        ..GenSettings::default()
    };
    let (asset, triangles) =
        gen::write("foliage", &gen_settings, output, false).map_err(anyhow::Error::msg)?;
    let scene = crate::import::load(&asset, Default::default())?;
    // Bake.
    let agg_path = output.join("foliage.agg");
    let t = Instant::now();
    let report = bake_to_file(&scene, "foliage.glb", &settings.bake, &agg_path, progress)?;
    let bake_seconds = t.elapsed().as_secs_f64();
    // One view, a sun and a blue sky.
    let (c, r) = scene.bounding_sphere();
    let mut view = View::framing(c, r, settings.image, settings.image, settings.lod_spp);
    view.sun = Some(SunDesc {
        direction: [0.4, 1.0, 0.3],
        irradiance: Rgb::Scalar(3.0),
    });
    view.environment = Some(EnvironmentDesc::Constant {
        constant: Rgb::Rgb([0.3, 0.4, 0.6]),
    });
    std::fs::write(
        output.join("view.json"),
        serde_json::to_string_pretty(&view)?,
    )?;
    let lights = view.lights()?;
    let camera = view.camera();
    let accel = Accel::build(&scene);
    let render_ref = |spp: u32, seed: u64| {
        reference::render(
            &accel,
            &camera,
            &lights,
            ReferenceSettings { spp, seed },
            progress,
        )
    };
    // The converged reference the two are judged against.
    let truth_spp = settings.truth_spp;
    let (truth, truth_stats) = render_ref(truth_spp, 7);
    truth.write_exr(&output.join(format!("reference-{truth_spp}spp.exr")))?;
    // The LoD, then the reference in the same time.
    let lod_spp = settings.lod_spp;
    let t = Instant::now();
    let lod = LodScene::open(&agg_path)?;
    let (lod_img, lod_stats) = crate::runtime::render(
        &lod,
        &camera,
        &lights,
        lod_spp,
        1,
        &TraceSettings::default(),
        progress,
    );
    let lod_s = t.elapsed().as_secs_f64();
    let per_spp = truth_stats.seconds / truth_spp as f64;
    let mut ref_spp = ((lod_s / per_spp).floor() as u32).max(1);
    let (mut ref_img, mut ref_stats) = render_ref(ref_spp, 1);
    if ref_stats.seconds > 1.2 * lod_s && ref_spp > 1 {
        ref_spp = ((ref_spp as f64 * lod_s / ref_stats.seconds).floor() as u32).max(1);
        (ref_img, ref_stats) = render_ref(ref_spp, 1);
    }
    lod_img.write_exr(&output.join("lod.exr"))?;
    ref_img.write_exr(&output.join("reference-equal-time.exr"))?;
    let lod_cmp = compare(&lod_img, &truth).map_err(anyhow::Error::msg)?;
    let ref_cmp = compare(&ref_img, &truth).map_err(anyhow::Error::msg)?;
    // The picture: five captioned panels side by side.
    let (lod_diff, scale) = difference_image(&lod_img, &truth, None);
    let (ref_diff, _) = difference_image(&ref_img, &truth, Some(scale));
    let picture = output.join("side-by-side.png");
    let captions = [
        ["reference".to_string(), format!("{truth_spp} spp")],
        [
            format!("lod {lod_spp} spp {lod_s:.2} s"),
            format!("rmse {:.4}", lod_cmp.rmse),
        ],
        [
            format!("ref {ref_spp} spp {:.2} s", ref_stats.seconds),
            format!("rmse {:.4}", ref_cmp.rmse),
        ],
        ["lod difference".to_string(), format!("white = {scale:.3}")],
        ["ref difference".to_string(), "same scale".to_string()],
    ];
    let (w, h) = (truth.width, truth.height);
    let panels: Vec<(Vec<u8>, u32)> = [
        &truth.to_srgb8(0.0),
        &lod_img.to_srgb8(0.0),
        &ref_img.to_srgb8(0.0),
        &lod_diff.to_srgb8(0.0),
        &ref_diff.to_srgb8(0.0),
    ]
    .iter()
    .zip(&captions)
    .map(|(img, c)| with_caption(img, w, h, &[&c[0], &c[1]], 1))
    .collect();
    crate::film::side_by_side(
        &picture,
        &panels.iter().map(|p| p.0.as_slice()).collect::<Vec<_>>(),
        w,
        panels[0].1,
    )?;
    Ok(DemoReport {
        asset,
        triangles,
        warnings: scene.warnings.clone(),
        bake_seconds,
        levels: report.levels.len(),
        bytes: report.bytes,
        lod: lod_stats,
        lod_seconds: lod_s,
        reference_spp: ref_spp,
        reference: ref_stats,
        lod_rmse: lod_cmp.rmse,
        reference_rmse: ref_cmp.rmse,
        picture,
        seconds: t_all.elapsed().as_secs_f64(),
        lod_spp: settings.lod_spp,
        truth_spp: settings.truth_spp,
    })
}

impl std::fmt::Display for DemoReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self;
        writeln!(
            f,
            "input: generated {} ({} triangles)",
            r.asset.display(),
            r.triangles
        )?;
        for w in &r.warnings {
            writeln!(f, "warning: {w}")?;
        }
        writeln!(
            f,
            "stats: bake {:.1} s, {} levels, {}",
            r.bake_seconds,
            r.levels,
            crate::report::mib(r.bytes)
        )?;
        writeln!(f, "{}", r.lod.line("LoD"))?;
        writeln!(f, "{}", r.reference.line("reference"))?;
        writeln!(
            f,
            "stats: equal time: LoD {:.2} s at {} spp, RMSE {:.4}; reference {:.2} s at {} spp, RMSE {:.4} (against the reference at {} spp)",
            r.lod_seconds, r.lod_spp, r.lod_rmse, r.reference.seconds, r.reference_spp, r.reference_rmse, r.truth_spp
        )?;
        write!(
            f,
            "output: {} (reference {} spp | LoD | reference at equal time | differences), in {:.0} s",
            r.picture.display(),
            r.truth_spp,
            r.seconds
        )
    }
}
