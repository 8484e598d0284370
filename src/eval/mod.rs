//! The quality and speed studies of the runtime (paper §8, Table 3, Fig. 13 and Fig. 17),
//! behind `aggtool eval`.
//!
//! Quality: per scene, one bake; per LoD resolution r (32³, 64³ by default) an image of r²
//! pixels (one voxel about one pixel) rendered by
//! - **ours**: the aggregate at that level (truncated ellipsoids, AIV, ABV; Eq. 30),
//! - **cube**: the same with the voxel cube as primitive (the Fig. 6 ablation),
//! - **volume**: the voxels as an exponential-transmittance medium (the traditional volumetric
//!   model, [`crate::runtime::PrimitiveKind::Volume`]),
//! - **mesh**: the asset simplified by meshoptimizer to the memory of that level, rendered by the
//!   reference renderer ([`simplify`]),
//! - **ref@spp**: the original mesh at the methods' sample count: the noise floor at equal spp,
//!
//! each against the reference renderer on the original mesh at a high sample count: RMSE,
//! memory, render time, and a picture of images and differences.
//!
//! Speed: equal-spp render time of the LoD against the reference renderer, and the RMSE each
//! reaches in the same time (Fig. 17).

pub mod budget;
pub mod demo;
pub mod plot;
pub mod run;
pub mod simplify;
pub mod sweep;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;

use crate::bake::{bake_to_file, BakeSettings};
use crate::film::write_rgb8_png;
use crate::film::Image;
use crate::format::Aggregate;
use crate::render::compare::{compare, difference_image};
use crate::render::reference::{self, ReferenceSettings};
use crate::render::{EnvironmentDesc, Rgb, SunDesc, View};
use crate::runtime::{LodScene, PrimitiveKind, TraceSettings};
use crate::scene::Scene;
use crate::trace::Accel;
use crate::util::Progress;

/// Settings of the quality study.
#[derive(Clone, Debug)]
pub struct StudySettings {
    /// LoD resolutions; each gives an image of res² pixels.
    pub resolutions: Vec<u32>,
    /// Samples per pixel of every method.
    pub spp: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// Bake settings (`max_res` is raised to the largest resolution).
    pub bake: BakeSettings,
    /// Where bakes are kept and reused, as NAME-RES.agg with RES the finest resolution
    /// studied (`aggtool eval --agg-dir`); `None` bakes every scene again into the output
    /// folder. A reused file is taken as it is: its settings are the ones it records.
    pub agg_dir: Option<PathBuf>,
    /// [`TraceSettings::normalize`] of the LoD methods (ours, cube, volume).
    pub normalize: bool,
    /// The image's side in pixels (`aggtool eval --image`); `None`: each resolution's own
    /// (res² pixels, one voxel a pixel). A larger image shows the finest level as users
    /// render it, several pixels a voxel.
    pub image: Option<u32>,
    /// [`TraceSettings::samples_per_walk`] of the LoD methods (0: the runtime's choice).
    pub samples_per_walk: u32,
}

impl Default for StudySettings {
    fn default() -> Self {
        StudySettings {
            resolutions: vec![32, 64],
            spp: 64,
            reference_spp: 1024,
            bake: BakeSettings {
                max_res: 64,
                ..Default::default()
            },
            agg_dir: None,
            normalize: true,
            image: None,
            samples_per_walk: 0,
        }
    }
}

/// One method's figures on one scene at one resolution.
#[derive(Clone, Debug, Serialize)]
pub struct MethodResult {
    /// The method: "ours", "cube", "volume", "mesh" or "ref@spp".
    pub method: String,
    /// RMSE against the high-spp reference.
    pub rmse: f64,
    /// Relative MSE against the reference.
    pub relmse: f64,
    /// The error on the asset's own pixels (those the mesh covers at least half of, from 4 × 4
    /// primary rays a pixel): mean ratio and relative RMSE against the reference there.
    pub object: crate::render::compare::ObjectComparison,
    /// Bytes the method needs for this LoD (see [`level_bytes`] and [`simplify`]).
    pub memory_bytes: u64,
    /// Wall seconds of the method's render.
    pub render_seconds: f64,
    /// What the method did (e.g. the simplified mesh's triangles); empty for most.
    pub note: String,
}

/// One scene at one resolution.
#[derive(Clone, Debug, Serialize)]
pub struct SceneResult {
    /// The scene's name.
    pub scene: String,
    /// The LoD resolution r.
    pub res: u32,
    /// The image's side in pixels (r unless the study set another).
    pub image: u32,
    /// Triangles of the original asset.
    pub triangles: usize,
    /// Wall seconds of the bake.
    pub bake_seconds: f64,
    /// Wall seconds of the high-spp reference.
    pub reference_seconds: f64,
    /// One result per method.
    pub methods: Vec<MethodResult>,
    /// The picture of the images over their differences.
    pub picture: PathBuf,
}

/// The study's lights: a sun and a blue sky, the same for every method.
pub fn study_view(scene: &Scene, res: u32, spp: u32) -> View {
    let (c, r) = scene.bounding_sphere();
    let mut view = View::framing(c, r, res, res, spp);
    view.sun = Some(SunDesc {
        direction: [0.4, 1.0, 0.3],
        irradiance: Rgb::Scalar(3.0),
    });
    view.environment = Some(EnvironmentDesc::Constant {
        constant: Rgb::Rgb([0.3, 0.4, 0.6]),
    });
    view
}

/// Bytes of level `l` in an aggregate: its voxel blocks (records, AIV trees) and face blocks
/// (ABV trees), all a renderer reads to draw that level.
pub fn level_bytes(agg: &Aggregate, l: usize) -> u64 {
    let (v, f) = agg.level_bytes(l);
    v + f
}

/// Bytes the volume baseline needs for level `l`: the voxel records and keys, no trees.
pub fn volume_bytes(agg: &Aggregate, l: usize) -> u64 {
    agg.counts(l).voxels * (std::mem::size_of::<crate::format::fb::Voxel>() as u64 + 8)
}

fn reference_render(accel: &Accel, view: &View, spp: u32, seed: u64) -> Result<(Image, f64)> {
    let lights = view.lights()?;
    let (img, stats) = reference::render(
        accel,
        &view.camera(),
        &lights,
        ReferenceSettings { spp, seed },
        &crate::util::no_progress,
    );
    Ok((img, stats.seconds))
}

fn lod_render(
    lod: &LodScene,
    view: &View,
    spp: u32,
    seed: u64,
    settings: &TraceSettings,
) -> Result<(Image, f64)> {
    let lights = view.lights()?;
    let (img, stats) = crate::runtime::render(
        lod,
        &view.camera(),
        &lights,
        spp,
        seed,
        settings,
        &crate::util::no_progress,
    );
    Ok((img, stats.seconds))
}

/// Nearest-neighbour enlargement of an sRGB8 image by `k`.
fn enlarge(rgb: &[u8], w: u32, h: u32, k: u32) -> Vec<u8> {
    let mut out = vec![0u8; (w * k * h * k * 3) as usize];
    for y in 0..h * k {
        for x in 0..w * k {
            let s = (((y / k) * w + x / k) * 3) as usize;
            let d = ((y * w * k + x) * 3) as usize;
            out[d..d + 3].copy_from_slice(&rgb[s..s + 3]);
        }
    }
    out
}

/// Writes rows of equally sized sRGB8 tiles as one PNG with 4-pixel gaps.
pub fn tile_png(path: &Path, rows: &[Vec<Vec<u8>>], w: u32, h: u32) -> Result<()> {
    let gap = 4u32;
    let cols = rows.iter().map(|r| r.len()).max().unwrap_or(0) as u32;
    let (tw, th) = (
        cols * w + (cols.saturating_sub(1)) * gap,
        rows.len() as u32 * h + (rows.len() as u32).saturating_sub(1) * gap,
    );
    let mut rgb = vec![255u8; (tw * th * 3) as usize];
    for (r, row) in rows.iter().enumerate() {
        for (c, tile) in row.iter().enumerate() {
            let (ox, oy) = (c as u32 * (w + gap), r as u32 * (h + gap));
            for y in 0..h {
                let src = &tile[(y * w * 3) as usize..((y + 1) * w * 3) as usize];
                let d = (((oy + y) * tw + ox) * 3) as usize;
                rgb[d..d + src.len()].copy_from_slice(src);
            }
        }
    }
    write_rgb8_png(path, tw, th, &rgb)?;
    Ok(())
}

/// Runs the quality study on one scene: bakes it into `dir` (or reuses its bake in
/// `settings.agg_dir`), renders every method at every resolution, writes one picture per
/// resolution, and returns the figures.
pub fn study_scene(
    name: &str,
    scene: &Scene,
    settings: &StudySettings,
    dir: &Path,
    progress: Progress,
) -> Result<Vec<SceneResult>> {
    std::fs::create_dir_all(dir)?;
    let max_res = settings.resolutions.iter().copied().max().unwrap_or(64);
    let bake = BakeSettings {
        max_res: settings.bake.max_res.max(max_res),
        ..settings.bake.clone()
    };
    let agg_path = match &settings.agg_dir {
        Some(d) => d.join(format!("{name}-{}.agg", bake.max_res)),
        None => dir.join(format!("{name}.agg")),
    };
    let t = Instant::now();
    if settings.agg_dir.is_none() || !agg_path.exists() {
        bake_to_file(scene, name, &bake, &agg_path, progress)
            .with_context(|| format!("baking {name}"))?;
    }
    let bake_seconds = t.elapsed().as_secs_f64();
    let lod = LodScene::new(Aggregate::open(&agg_path)?);
    let agg = lod.aggregate();
    let accel = Accel::build(scene);
    let full_bytes = simplify::scene_bytes(scene) as u64;
    let mut results = Vec::new();
    for &res in &settings.resolutions {
        let Some(l) = (0..agg.level_count()).find(|&l| agg.grid(l).res == res) else {
            eprintln!("warning: {name}: no {res}³ level, skipped");
            continue;
        };
        let image = settings.image.unwrap_or(res);
        let view = study_view(scene, image, settings.spp);
        let (truth, reference_seconds) =
            reference_render(&accel, &view, settings.reference_spp, 7)?;
        let coverage = crate::render::reference::coverage(&accel, &view.camera(), 4);
        let mut images: Vec<(String, Image)> = Vec::new();
        let mut methods = Vec::new();
        let mut push = |method: &str, img: Image, bytes: u64, secs: f64, note: String| {
            let c = compare(&img, &truth).expect("same size");
            let object = crate::render::compare::compare_on_object(&img, &truth, &coverage)
                .expect("same size");
            methods.push(MethodResult {
                method: method.to_string(),
                rmse: c.rmse,
                relmse: c.relmse,
                object,
                memory_bytes: bytes,
                render_seconds: secs,
                note,
            });
            images.push((method.to_string(), img));
        };
        let ours_bytes = level_bytes(&agg, l);
        for (method, kind, bytes) in [
            ("ours", PrimitiveKind::TruncatedEllipsoid, ours_bytes),
            ("cube", PrimitiveKind::Cube, ours_bytes),
            ("volume", PrimitiveKind::Volume, volume_bytes(&agg, l)),
        ] {
            let ts = TraceSettings {
                level: Some(l),
                primitive: kind,
                normalize: settings.normalize,
                samples_per_walk: settings.samples_per_walk,
                ..Default::default()
            };
            let (img, secs) = lod_render(&lod, &view, settings.spp, 1, &ts)?;
            push(method, img, bytes, secs, String::new());
        }
        let simp = simplify::simplify_to_budget(scene, ours_bytes as usize);
        let simp_accel = Accel::build(&simp.scene);
        let (img, secs) = reference_render(&simp_accel, &view, settings.spp, 1)?;
        let note = if simp.unchanged {
            format!(
                "mesh ({} tris) already within budget: not simplified",
                simp.triangles_before
            )
        } else {
            format!("{} → {} tris", simp.triangles_before, simp.triangles_after)
        };
        push("mesh", img, simp.bytes_after as u64, secs, note);
        let (img, secs) = reference_render(&accel, &view, settings.spp, 1)?;
        push("ref@spp", img, full_bytes, secs, "original mesh".into());
        // Picture: images over their differences, all differences on one scale; captions.
        let k = (256 / image).max(1);
        let (side, scale_px) = (image * k, if image * k >= 200 { 2 } else { 1 });
        let scale = {
            let (_, s) = difference_image(&images[0].1, &truth, None);
            s
        };
        let caption = |img: &[u8], lines: &[&str]| -> Vec<u8> {
            crate::render::label::with_caption(img, side, side, lines, scale_px).0
        };
        let ref_lines = [
            "reference".to_string(),
            format!("{} spp", settings.reference_spp),
            format!("{reference_seconds:.2} s"),
        ];
        let mut top = vec![caption(
            &enlarge(&truth.to_srgb8(0.0), image, image, k),
            &ref_lines.iter().map(String::as_str).collect::<Vec<_>>(),
        )];
        let mut bottom = vec![caption(
            &vec![0u8; (side * side * 3) as usize],
            &["difference", &format!("white = {scale:.3}"), ""],
        )];
        for ((name, img), m) in images.iter().zip(&methods) {
            let lines = [
                name.clone(),
                format!("rmse {:.4}", m.rmse),
                format!(
                    "{:.2} mib {:.2} s",
                    m.memory_bytes as f64 / 1048576.0,
                    m.render_seconds
                ),
            ];
            top.push(caption(
                &enlarge(&img.to_srgb8(0.0), image, image, k),
                &lines.iter().map(String::as_str).collect::<Vec<_>>(),
            ));
            let (d, _) = difference_image(img, &truth, Some(scale));
            bottom.push(caption(
                &enlarge(&d.to_srgb8(0.0), image, image, k),
                &[name, "", ""],
            ));
        }
        let tile_h = side + 3 * crate::render::label::line_height(scale_px) + 4 * scale_px;
        let picture = if image == res {
            dir.join(format!("{name}-{res}.png"))
        } else {
            dir.join(format!("{name}-{res}-{image}px.png"))
        };
        tile_png(&picture, &[top, bottom], side, tile_h)?;
        results.push(SceneResult {
            scene: name.to_string(),
            res,
            image,
            triangles: scene.instanced_triangle_count(),
            bake_seconds,
            reference_seconds,
            methods,
            picture,
        });
    }
    drop(lod);
    // A bake made in the output folder is scratch; one kept in `agg_dir` is what the caller
    // asked to keep (and may be a link to a bake of theirs).
    if settings.agg_dir.is_none() {
        std::fs::remove_file(&agg_path).ok();
    }
    Ok(results)
}

/// The head of a study table: scene, LoD, the `extra` columns (each "NAME | "), then the
/// `columns` of each method of the first result.
fn table_head(results: &[SceneResult], extra: &str, columns: &[&str]) -> String {
    let names: Vec<&str> = results
        .first()
        .map(|r| r.methods.iter().map(|m| m.method.as_str()).collect())
        .unwrap_or_default();
    let mut s = format!("| scene | LoD | {extra}");
    for n in &names {
        for c in columns {
            s += &format!("{n} {c} | ");
        }
    }
    s += "\n|---|---|";
    s += &"---|".repeat(extra.matches('|').count() + names.len() * columns.len());
    s += "\n";
    s
}

/// A table's resolution cell: "64³", or "128³ at 256²" where the image is not one voxel a
/// pixel.
fn res_label(res: u32, image: u32) -> String {
    if image == res {
        format!("{res}³")
    } else {
        format!("{res}³ at {image}²")
    }
}

/// The study's Markdown table: one row per scene and resolution, RMSE / memory / time per
/// method, the lowest RMSE in bold.
pub fn markdown_table(results: &[SceneResult]) -> String {
    let mut s = table_head(results, "", &["RMSE", "MiB", "s"]);
    for r in results {
        // The best of the four LoD methods (not the equal-spp reference on the full mesh).
        let best = r
            .methods
            .iter()
            .filter(|m| m.method != "ref@spp")
            .map(|m| m.rmse)
            .fold(f64::INFINITY, f64::min);
        s += &format!("| {} | {} | ", r.scene, res_label(r.res, r.image));
        for m in &r.methods {
            let rm = if m.rmse == best {
                format!("**{:.4}**", m.rmse)
            } else {
                format!("{:.4}", m.rmse)
            };
            s += &format!(
                "{rm} | {:.2} | {:.2} | ",
                m.memory_bytes as f64 / 1048576.0,
                m.render_seconds
            );
        }
        s += "\n";
    }
    s
}

/// The study's errors on the assets' own pixels ([`MethodResult::object`]): per scene and
/// resolution, each method's mean ratio and relative RMSE where the mesh covers the pixel, so
/// that the sky around an asset cannot hide a wrong asset.
pub fn object_table(results: &[SceneResult]) -> String {
    let mut s = table_head(results, "pixels | ", &["mean ratio", "rel. RMSE"]);
    for r in results {
        let pixels = r.methods.first().map_or(0, |m| m.object.pixels);
        s += &format!(
            "| {} | {} | {pixels} | ",
            r.scene,
            res_label(r.res, r.image)
        );
        for m in &r.methods {
            s += &format!(
                "{:.3} | {:.3} | ",
                m.object.mean_ratio, m.object.relative_rmse
            );
        }
        s += "\n";
    }
    s
}

/// The study's medians per resolution (and image size): ours over ref@spp (RMSE over the
/// image), and on the assets' own pixels ours' and ref@spp's mean ratio and relative RMSE;
/// the hard cases count like any scene.
pub fn summary_table(results: &[SceneResult]) -> String {
    let mut groups: Vec<(u32, u32)> = results.iter().map(|r| (r.res, r.image)).collect();
    groups.sort_unstable();
    groups.dedup();
    let median = |mut v: Vec<f64>| -> f64 {
        v.retain(|x| x.is_finite());
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(f64::total_cmp);
        let n = v.len();
        if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        }
    };
    let mut s = String::from(
        "| LoD | scenes | median ours / ref@spp | own pixels: ours mean ratio | ours rel. RMSE | ref@spp mean ratio | ref@spp rel. RMSE |\n|---|---|---|---|---|---|---|\n",
    );
    for (res, image) in groups {
        let rows: Vec<&SceneResult> = results
            .iter()
            .filter(|r| (r.res, r.image) == (res, image))
            .collect();
        let method = |r: &SceneResult, name: &str| -> Option<MethodResult> {
            r.methods.iter().find(|m| m.method == name).cloned()
        };
        let pairs: Vec<(MethodResult, MethodResult)> = rows
            .iter()
            .filter_map(|r| Some((method(r, "ours")?, method(r, "ref@spp")?)))
            .collect();
        let ratio = median(pairs.iter().map(|(o, r)| o.rmse / r.rmse).collect());
        let of = |f: &dyn Fn(&(MethodResult, MethodResult)) -> f64| {
            median(pairs.iter().map(f).collect())
        };
        s += &format!(
            "| {} | {} | {ratio:.2} | {:.3} | {:.3} | {:.3} | {:.3} |\n",
            res_label(res, image),
            pairs.len(),
            of(&|p| p.0.object.mean_ratio),
            of(&|p| p.0.object.relative_rmse),
            of(&|p| p.1.object.mean_ratio),
            of(&|p| p.1.object.relative_rmse),
        );
    }
    s
}

/// Figures of the speed study on one scene.
#[derive(Clone, Debug, Serialize)]
pub struct SpeedResult {
    /// The scene's name.
    pub scene: String,
    /// Triangles of the asset.
    pub triangles: usize,
    /// Image side in pixels.
    pub res: u32,
    /// The bake's finest resolution.
    pub bake_res: u32,
    /// Samples per pixel of both renders.
    pub spp: u32,
    /// Seconds the bake took (0 when an existing file was reused).
    pub bake_seconds: f64,
    /// Bytes of the `.agg` file.
    pub agg_bytes: u64,
    /// Whole commands at equal spp, wall seconds: the LoD opens the file and renders (the
    /// reference imports the asset, builds its BVH and renders).
    pub lod_seconds: f64,
    /// Whole reference command, wall seconds.
    pub reference_seconds: f64,
    /// The LoD's render loop alone, at equal spp.
    pub lod_render_seconds: f64,
    /// The reference's render loop alone.
    pub reference_render_seconds: f64,
    /// CPU seconds (user + system, all threads) of the same whole commands: the figures the
    /// ratios and the equal-time budget use, since wall time on a shared machine depends on
    /// what else runs.
    pub lod_cpu_seconds: f64,
    /// The reference's CPU seconds.
    pub reference_cpu_seconds: f64,
    /// The levels the LoD touched (resolutions).
    pub lod_levels: Vec<u32>,
    /// RMSE of the LoD against the converged reference.
    pub lod_rmse: f64,
    /// RMSE of the reference at equal spp.
    pub reference_rmse: f64,
    /// Equal time: the reference's spp whose whole command takes the LoD's whole CPU time (at
    /// least 1).
    pub equal_time_reference_spp: u32,
    /// The equal-time reference's CPU seconds.
    pub equal_time_reference_seconds: f64,
    /// The equal-time reference's RMSE.
    pub equal_time_reference_rmse: f64,
    /// Non-finite values counted in the LoD render (zero when healthy).
    pub lod_non_finite: u64,
    /// Peak resident memory in bytes of the whole commands `aggtool render` and `aggtool
    /// reference` at equal spp, each run as a process of its own (`None` when the study does
    /// not run from the `aggtool` binary, as in the library's tests): the LoD's.
    pub lod_peak_rss: Option<u64>,
    /// The reference's peak resident memory.
    pub reference_peak_rss: Option<u64>,
    /// The picture of the renders and their differences.
    pub picture: PathBuf,
}

/// Peak resident memory of the whole commands `aggtool render AGG` and `aggtool reference
/// ASSET` on `view` (saved beside the study's outputs), each a child process of this
/// executable when it is the `aggtool` binary; `None` otherwise or when a command fails.
fn peak_rss_of_commands(
    view: &crate::render::View,
    asset: &Path,
    agg: &Path,
    dir: &Path,
    name: &str,
) -> (Option<u64>, Option<u64>) {
    let Ok(exe) = std::env::current_exe() else {
        return (None, None);
    };
    if exe.file_stem().and_then(|s| s.to_str()) != Some("aggtool") {
        return (None, None);
    }
    let v = dir.join(format!("{name}-{}-view.json", view.camera.width));
    let Ok(json) = serde_json::to_string_pretty(view) else {
        return (None, None);
    };
    if std::fs::write(&v, json).is_err() {
        return (None, None);
    }
    let run = |args: &[&std::ffi::OsStr]| {
        let mut cmd = std::process::Command::new(&exe);
        cmd.args(args);
        crate::util::process::measure(&mut cmd)
            .ok()
            .filter(|m| m.success)
            .map(|m| m.max_rss)
    };
    let out = |what: &str| dir.join(format!("{name}-{}-{what}-rss.exr", view.camera.width));
    let (lod_out, ref_out) = (out("lod"), out("reference"));
    let lod = run(&[
        "render".as_ref(),
        agg.as_os_str(),
        "--view".as_ref(),
        v.as_os_str(),
        "-o".as_ref(),
        lod_out.as_os_str(),
    ]);
    let reference = run(&[
        "reference".as_ref(),
        asset.as_os_str(),
        "--view".as_ref(),
        v.as_os_str(),
        "-o".as_ref(),
        ref_out.as_os_str(),
    ]);
    for p in [&v, &lod_out, &ref_out] {
        let _ = std::fs::remove_file(p);
        let _ = std::fs::remove_file(p.with_extension("png"));
    }
    (lod, reference)
}

/// A scene for the speed study: an asset file (imported the way `aggtool reference` does) and
/// its aggregate (baked into `dir` if missing).
pub struct SpeedInput<'a> {
    /// The scene's name in the table.
    pub name: &'a str,
    /// The asset file.
    pub asset: &'a Path,
    /// Its aggregate.
    pub agg: &'a Path,
}

/// The speed study on one scene (paper Table 3's times, Fig. 17's equal-time comparison): an
/// image of `res`² pixels with LoD chosen by footprint from the aggregate, at `spp`, against the
/// reference at `reference_spp`. Whole commands are timed in process, as `aggtool render` and
/// `aggtool reference` spend them (opening or importing, BVH, render; not writing images).
pub fn speed_scene(
    input: &SpeedInput,
    bake: &BakeSettings,
    res: u32,
    spp: u32,
    reference_spp: u32,
    dir: &Path,
    progress: Progress,
) -> Result<SpeedResult> {
    std::fs::create_dir_all(dir)?;
    let name = input.name;
    let mut bake_seconds = 0.0;
    if !input.agg.exists() {
        let scene = crate::import::load(input.asset, Default::default())?;
        let t = Instant::now();
        bake_to_file(&scene, name, bake, input.agg, progress)?;
        bake_seconds = t.elapsed().as_secs_f64();
    }
    let cpu = crate::util::cpu_seconds;
    // The reference: import, BVH, render — timed as one command.
    let t = Instant::now();
    let c = cpu();
    let scene = crate::import::load(input.asset, Default::default())
        .with_context(|| format!("importing {}", input.asset.display()))?;
    let accel = Accel::build(&scene);
    let load_seconds = t.elapsed().as_secs_f64();
    let load_cpu = cpu() - c;
    let view = study_view(&scene, res, spp);
    let (truth, _) = reference_render(&accel, &view, reference_spp, 7)?;
    let c = cpu();
    let (ref_img, reference_render_seconds) = reference_render(&accel, &view, spp, 1)?;
    let ref_render_cpu = cpu() - c;
    let reference_seconds = load_seconds + reference_render_seconds;
    let reference_cpu_seconds = load_cpu + ref_render_cpu;
    // The LoD: open (lazily) and render, in a fresh scene so that level preparation counts.
    let t = Instant::now();
    let c = cpu();
    let lod = LodScene::open(input.agg)?;
    let lights = view.lights()?;
    let (lod_img, stats) = crate::runtime::render(
        &lod,
        &view.camera(),
        &lights,
        spp,
        1,
        &TraceSettings::default(),
        &crate::util::no_progress,
    );
    let lod_seconds = t.elapsed().as_secs_f64();
    let lod_cpu_seconds = cpu() - c;
    if let Some(e) = lod.first_error() {
        anyhow::bail!("{}: {e}", input.agg.display());
    }
    let lod_levels: Vec<u32> = lod.resolutions_used();
    let lod_rmse = compare(&lod_img, &truth).expect("same size").rmse;
    let reference_rmse = compare(&ref_img, &truth).expect("same size").rmse;
    // Equal time: the reference's spp whose whole command fits the LoD's whole CPU time,
    // scaled from its render CPU time per spp, then corrected once.
    let per_spp = ref_render_cpu.max(1e-6) / spp as f64;
    let budget = (lod_cpu_seconds - load_cpu).max(0.0);
    let mut eq_spp = ((budget / per_spp).floor() as u32).max(1);
    let c = cpu();
    let (mut eq_img, _) = reference_render(&accel, &view, eq_spp, 3)?;
    let mut eq_render = cpu() - c;
    if eq_render > budget * 1.25 && eq_spp > 1 {
        eq_spp = ((eq_spp as f64 * budget / eq_render).floor() as u32).max(1);
        let c = cpu();
        (eq_img, _) = reference_render(&accel, &view, eq_spp, 3)?;
        eq_render = cpu() - c;
    }
    let eq_secs = load_cpu + eq_render;
    let eq_rmse = compare(&eq_img, &truth).expect("same size").rmse;
    let k = (256 / res).max(1);
    let side = res * k;
    let sc = if side >= 200 { 2 } else { 1 };
    let captions = [
        vec![format!("reference {reference_spp} spp"), String::new()],
        vec![
            format!("lod {spp} spp"),
            format!("{lod_cpu_seconds:.2} cpu s rmse {lod_rmse:.4}"),
        ],
        vec![
            format!("reference {spp} spp"),
            format!("{reference_cpu_seconds:.2} cpu s rmse {reference_rmse:.4}"),
        ],
        vec![
            format!("reference {eq_spp} spp"),
            format!("{eq_secs:.2} cpu s rmse {eq_rmse:.4}"),
        ],
    ];
    let tiles: Vec<Vec<u8>> = [&truth, &lod_img, &ref_img, &eq_img]
        .iter()
        .zip(&captions)
        .map(|(i, c)| {
            let lines: Vec<&str> = c.iter().map(String::as_str).collect();
            crate::render::label::with_caption(
                &enlarge(&i.to_srgb8(0.0), res, res, k),
                side,
                side,
                &lines,
                sc,
            )
            .0
        })
        .collect();
    let tile_h = side + 2 * crate::render::label::line_height(sc) + 4 * sc;
    let picture = dir.join(format!("{name}-{res}-speed.png"));
    tile_png(&picture, &[tiles], side, tile_h)?;
    let (lod_peak_rss, reference_peak_rss) =
        peak_rss_of_commands(&view, input.asset, input.agg, dir, name);
    Ok(SpeedResult {
        scene: name.to_string(),
        triangles: scene.instanced_triangle_count(),
        res,
        bake_res: lod.grid(0).res,
        spp,
        bake_seconds,
        agg_bytes: lod.aggregate().header().file_size,
        lod_seconds,
        reference_seconds,
        lod_render_seconds: stats.seconds,
        reference_render_seconds,
        lod_cpu_seconds,
        reference_cpu_seconds,
        lod_levels,
        lod_rmse,
        reference_rmse,
        equal_time_reference_spp: eq_spp,
        equal_time_reference_seconds: eq_secs,
        equal_time_reference_rmse: eq_rmse,
        lod_non_finite: stats.non_finite,
        lod_peak_rss,
        reference_peak_rss,
        picture,
    })
}

/// The speed table in Markdown.
pub fn speed_table(rows: &[SpeedResult]) -> String {
    let mut s = String::from("| scene | triangles | image | bake | spp | LoD cpu s | reference cpu s | LoD / reference (cpu) | (wall) | render only (wall) | LoD levels | LoD RMSE | reference RMSE | equal-time reference spp (cpu s) | its RMSE | peak RSS LoD / reference (MiB) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    let rss = |r: &SpeedResult| match (r.lod_peak_rss, r.reference_peak_rss) {
        (Some(a), Some(b)) => format!(
            "{:.0} / {:.0} ({:.2}×)",
            a as f64 / (1 << 20) as f64,
            b as f64 / (1 << 20) as f64,
            a as f64 / b.max(1) as f64
        ),
        _ => "-".into(),
    };
    for r in rows {
        s += &format!(
            "| {} | {} | {}² | {}³ | {} | {:.2} | {:.2} | {:.2}× | {:.2}× | {:.2}× | {:?} | {:.4} | {:.4} | {} ({:.2}) | {:.4} | {} |\n",
            r.scene,
            r.triangles,
            r.res,
            r.bake_res,
            r.spp,
            r.lod_cpu_seconds,
            r.reference_cpu_seconds,
            r.lod_cpu_seconds / r.reference_cpu_seconds.max(1e-9),
            r.lod_seconds / r.reference_seconds.max(1e-9),
            r.lod_render_seconds / r.reference_render_seconds.max(1e-9),
            r.lod_levels,
            r.lod_rmse,
            r.reference_rmse,
            r.equal_time_reference_spp,
            r.equal_time_reference_seconds,
            r.equal_time_reference_rmse,
            rss(r)
        );
    }
    s
}
