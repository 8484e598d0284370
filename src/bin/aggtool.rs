//! `aggtool`: the command-line front end. Each subcommand maps its flags onto settings and
//! calls one library function; errors print their whole chain and exit with status 1.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};

use aggtool::gen::{self, GenSettings};
use aggtool::import::{self, ImportOptions};
use aggtool::render::compare::{compare, difference_image};
use aggtool::render::reference::{self, ReferenceSettings};
use aggtool::render::{Camera, Image, Lights, View};
use aggtool::scene::Scene;
use aggtool::trace::Accel;

#[derive(Parser)]
#[command(
    name = "aggtool",
    version,
    about = "Appearance-preserving level of detail: aggregate scenes into voxel LoDs and render them."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate a built-in scene, render it, and say where everything is (the main job).
    Demo {
        /// Output folder.
        #[arg(short, long, default_value = "aggtool-demo")]
        output: PathBuf,
    },
    /// Render an asset with the reference path tracer (direct illumination) to EXR and PNG.
    Reference {
        /// The asset (.gltf, .glb or .obj).
        asset: PathBuf,
        /// View file (JSON); see the README.
        #[arg(long, conflicts_with = "auto_view")]
        view: Option<PathBuf>,
        /// Frame the asset's bounding sphere instead of reading a view file.
        #[arg(long)]
        auto_view: bool,
        /// Image width for --auto-view.
        #[arg(long, default_value_t = 256)]
        width: u32,
        /// Image height for --auto-view.
        #[arg(long, default_value_t = 256)]
        height: u32,
        /// Samples per pixel (overrides the view file).
        #[arg(long)]
        spp: Option<u32>,
        /// Random seed (overrides the view file).
        #[arg(long)]
        seed: Option<u64>,
        /// Output EXR; a tonemapped PNG is written beside it.
        #[arg(short, long)]
        output: PathBuf,
        /// Exposure of the PNG in stops.
        #[arg(long, default_value_t = 0.0)]
        exposure: f32,
        /// Treat import warnings as errors.
        #[arg(long)]
        strict: bool,
        /// Write the view used (useful with --auto-view) to this file.
        #[arg(long)]
        save_view: Option<PathBuf>,
    },
    /// Compare two EXR images: RMSE and relative MSE on linear values.
    Compare {
        a: PathBuf,
        /// The reference.
        b: PathBuf,
        /// Write a false-colour difference image (PNG).
        #[arg(long)]
        diff: Option<PathBuf>,
        /// Print {"rmse", "relmse", "width", "height"} as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Write a generated hard-case scene as GLB.
    Gen {
        /// One of: plane45, lattice, foliage, displaced-sphere, rings, buildings, or all.
        name: String,
        /// Output folder.
        #[arg(short, long, default_value = ".")]
        output: PathBuf,
        /// Approximate number of triangles.
        #[arg(long, default_value_t = 20_000)]
        triangles: usize,
        /// Make every material Lambertian (metallic 0, KHR_materials_specular factor 0).
        #[arg(long)]
        lambertian: bool,
        /// Store vertex data with KHR_mesh_quantization.
        #[arg(long)]
        quantize: bool,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Print what an asset imports as: counts, bounds, materials, warnings.
    Info {
        asset: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// Plot the factored ABSDF against its ground truth for a validation voxel (8×8 outgoing
    /// lat-long slices, like paper Fig. 4): ground truth | factored | difference.
    AbsdfPlot {
        /// One of: flat, curved, foliage, anisotropic, orientation-color, mixed-roughness,
        /// metal-dielectric, or all.
        case: String,
        /// Output folder.
        #[arg(short, long, default_value = ".")]
        output: PathBuf,
        /// Surface samples of the voxel.
        #[arg(long, default_value_t = 4096)]
        samples: u32,
        /// Width of one slice in pixels.
        #[arg(long, default_value_t = 32)]
        slice: u32,
        /// Exposure of the PNG in stops.
        #[arg(long, default_value_t = 0.0)]
        exposure: f32,
    },
    /// The precomputed tables M1–M5 of the factorized ABSDF.
    Tables {
        #[command(subcommand)]
        action: TablesAction,
    },
    /// Write an asset as world-space OBJ files, one per material, with materials.json
    /// (base colours) beside them: the input of the Mitsuba cross-check.
    Flatten {
        asset: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
    },
}

#[derive(Subcommand)]
enum TablesAction {
    /// Fit every table against Monte Carlo ground truth and write the table file.
    Build {
        /// Output file (the crate embeds tables/aggtool-tables.bin).
        #[arg(short, long, default_value = "tables/aggtool-tables.bin")]
        output: PathBuf,
        /// Monte Carlo samples per strategy per ground-truth direction (M1, M3).
        #[arg(long, default_value_t = 128)]
        samples: u32,
        /// M3 resolution per axis.
        #[arg(long, default_value_t = 50)]
        m3_res: u32,
        /// M1 resolution per axis.
        #[arg(long, default_value_t = 20)]
        m1_res: u32,
    },
    /// Print each table's fit error against fresh Monte Carlo ground truth.
    Check {
        /// Table file to check (default: the embedded one).
        #[arg(long)]
        file: Option<PathBuf>,
        /// Random parameter points per table.
        #[arg(long, default_value_t = 64)]
        points: usize,
        /// Monte Carlo samples per strategy per direction.
        #[arg(long, default_value_t = 512)]
        samples: u32,
        #[arg(long)]
        json: bool,
    },
}

fn tables_cmd(action: TablesAction) -> Result<()> {
    use aggtool::tables::{fit, Tables};
    match action {
        TablesAction::Build {
            output,
            samples,
            m3_res,
            m1_res,
        } => {
            let t0 = std::time::Instant::now();
            let t = fit::build(
                fit::BuildSettings {
                    samples,
                    m3_res,
                    m1_res,
                },
                true,
            );
            let bytes = t.to_bytes();
            aggtool::render::image::write_atomic(&output, |tmp| {
                std::fs::write(tmp, &bytes).map_err(|e| e.to_string())
            })
            .map_err(anyhow::Error::msg)?;
            println!(
                "output: {} ({} bytes) in {:.1} s",
                output.display(),
                bytes.len(),
                t0.elapsed().as_secs_f64()
            );
            Ok(())
        }
        TablesAction::Check {
            file,
            points,
            samples,
            json,
        } => {
            let owned;
            let t = match file {
                Some(f) => {
                    owned = Tables::from_bytes(
                        &std::fs::read(&f)
                            .with_context(|| format!("cannot read {}", f.display()))?,
                    )?;
                    &owned
                }
                None => Tables::embedded(),
            };
            let r = fit::check(t, points, samples);
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!(
                    "{:<6} {:>7} {:>9} {:>9}  metric",
                    "table", "points", "RMSE", "worst"
                );
                for c in r {
                    println!(
                        "{:<6} {:>7} {:>9.4} {:>9.4}  {}",
                        c.table, c.points, c.rmse, c.worst, c.metric
                    );
                }
            }
            Ok(())
        }
    }
}

fn absdf_plot(case: &str, output: &Path, samples: u32, slice: u32, exposure: f32) -> Result<()> {
    use aggtool::absdf::cases::{compare_case, plot_slices, CASES};
    let t = aggtool::tables::Tables::embedded();
    let names: Vec<&str> = if case == "all" {
        CASES.to_vec()
    } else {
        vec![case]
    };
    std::fs::create_dir_all(output)?;
    for name in names {
        let Some((gt, ours)) = plot_slices(name, t, samples, slice.max(4)) else {
            bail!("unknown case '{name}'; choose one of: {}", CASES.join(", "));
        };
        let (diff, scale) = difference_image(&ours, &gt, None);
        // Side by side: ground truth | factored | difference.
        let (w, h) = (gt.width, gt.height);
        let mut rgb = vec![0u8; (3 * w * h * 3) as usize];
        for (k, img) in [
            gt.to_srgb8(exposure),
            ours.to_srgb8(exposure),
            diff.to_srgb8(0.0),
        ]
        .iter()
        .enumerate()
        {
            for y in 0..h {
                let src = &img[(y * w * 3) as usize..((y + 1) * w * 3) as usize];
                let dst = ((y * 3 * w + k as u32 * w) * 3) as usize;
                rgb[dst..dst + src.len()].copy_from_slice(src);
            }
        }
        let path = output.join(format!("absdf-{name}.png"));
        aggtool::render::image::write_rgb8_png(&path, 3 * w, h, &rgb)?;
        let (r, _) = compare_case(name, t, samples, 8).expect("known case");
        println!("{name}: lobes {} rmse {:.5} (ground truth rms {:.5}, relative {:.3}); difference white = {scale:.4}; output: {}", r.lobes, r.rmse, r.gt_rms, r.rmse / r.gt_rms, path.display());
    }
    Ok(())
}

fn load_scene(path: &Path, strict: bool) -> Result<Scene> {
    let scene = import::load(path, ImportOptions { strict })?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    Ok(scene)
}

fn png_beside(exr: &Path) -> PathBuf {
    exr.with_extension("png")
}

fn run_reference(
    scene: &Scene,
    view: &View,
    output: &Path,
    exposure: f32,
    progress: bool,
) -> Result<reference::RenderStats> {
    let lights = Lights::from_view(view)?;
    let t0 = std::time::Instant::now();
    let accel = Accel::build(scene);
    let build = t0.elapsed().as_secs_f64();
    let camera = Camera::new(&view.camera);
    let (img, stats) = reference::render(
        &accel,
        &camera,
        &lights,
        ReferenceSettings {
            spp: view.spp,
            seed: view.seed,
            progress,
        },
    );
    img.write_exr(output)?;
    img.write_png(&png_beside(output), exposure)?;
    println!(
        "stats: bvh {:.2} s ({} BLAS, {} TLAS entries), render {:.2} s, {} rays, {:.2} Mrays/s, {} invalid samples",
        build,
        accel.stats.blas_count,
        accel.stats.tlas_entries,
        stats.seconds,
        stats.rays,
        stats.rays_per_second / 1e6,
        stats.invalid_samples
    );
    println!(
        "output: {} and {}",
        output.display(),
        png_beside(output).display()
    );
    Ok(stats)
}

fn flatten(scene: &Scene, dir: &Path) -> Result<()> {
    use std::fmt::Write as _;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut per_mat: Vec<String> = vec![String::new(); scene.materials.len()];
    let mut counts = vec![0u32; scene.materials.len()];
    for inst in &scene.instances {
        let m = &scene.meshes[inst.mesh as usize];
        let nm = glam::Mat3::from(inst.transform.matrix3)
            .inverse()
            .transpose();
        let out = &mut per_mat[m.material as usize];
        let base = counts[m.material as usize];
        for p in &m.positions {
            let w = inst.transform.transform_point3(*p);
            let _ = writeln!(out, "v {} {} {}", w.x, w.y, w.z);
        }
        let has_n = !m.normals.is_empty();
        for n in &m.normals {
            let w = (nm * *n).normalize_or_zero();
            let _ = writeln!(out, "vn {} {} {}", w.x, w.y, w.z);
        }
        for t in &m.triangles {
            let [a, b, c] = t.map(|i| i + base + 1);
            if has_n {
                let _ = writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}");
            } else {
                let _ = writeln!(out, "f {a} {b} {c}");
            }
        }
        counts[m.material as usize] += m.positions.len() as u32;
    }
    let mut list = Vec::new();
    for (i, text) in per_mat.iter().enumerate() {
        if text.is_empty() {
            continue;
        }
        let file = format!("material_{i:03}.obj");
        std::fs::write(dir.join(&file), text)?;
        let mat = &scene.materials[i];
        if mat.base_color_texture.is_some() || mat.has_cutout() {
            eprintln!("warning: material '{}' has textures or cut-outs; materials.json gives only its factors", mat.name);
        }
        list.push(serde_json::json!({
            "file": file,
            "name": mat.name,
            "base_color": [mat.base_color.x, mat.base_color.y, mat.base_color.z],
            "metallic": mat.metallic,
            "specular_factor": mat.specular_factor,
            "roughness": mat.perceptual_roughness,
        }));
    }
    std::fs::write(
        dir.join("materials.json"),
        serde_json::to_string_pretty(&list)?,
    )?;
    println!("output: {} ({} files)", dir.display(), list.len());
    Ok(())
}

fn demo(output: &Path) -> Result<()> {
    std::fs::create_dir_all(output)?;
    let settings = GenSettings {
        triangles: 50_000,
        ..GenSettings::default()
    };
    let (asset, tris) =
        gen::write("buildings", &settings, output, false).map_err(anyhow::Error::msg)?;
    println!("input: generated {} ({} triangles)", asset.display(), tris);
    let scene = load_scene(&asset, false)?;
    let (c, r) = scene.bounding_sphere();
    let mut view = View::framing(c, r, 256, 256, 64);
    view.sun = Some(aggtool::render::view::SunDesc {
        direction: [0.4, 1.0, 0.3],
        irradiance: aggtool::render::view::Rgb::Scalar(3.0),
    });
    view.environment = Some(aggtool::render::view::EnvironmentDesc::Constant {
        constant: aggtool::render::view::Rgb::Rgb([0.3, 0.4, 0.6]),
    });
    let out = output.join("reference.exr");
    run_reference(&scene, &view, &out, 0.0, true)?;
    std::fs::write(
        output.join("view.json"),
        serde_json::to_string_pretty(&view)?,
    )?;
    println!("The level-of-detail bake and renderer come next; this demo renders the reference.");
    println!("Look at {}", png_beside(&out).display());
    Ok(())
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo { output } => demo(&output),
        Command::Reference {
            asset,
            view,
            auto_view,
            width,
            height,
            spp,
            seed,
            output,
            exposure,
            strict,
            save_view,
        } => {
            let scene = load_scene(&asset, strict)?;
            println!("input: {}: {}", asset.display(), scene.summary());
            let mut view = match (view, auto_view) {
                (Some(v), _) => View::load(&v)?,
                (None, true) => {
                    let (c, r) = scene.bounding_sphere();
                    View::framing(c, r, width, height, spp.unwrap_or(64))
                }
                (None, false) => bail!("give a view file with --view, or --auto-view"),
            };
            if let Some(s) = spp {
                view.spp = s;
            }
            if let Some(s) = seed {
                view.seed = s;
            }
            view.validate().map_err(anyhow::Error::msg)?;
            if let Some(p) = save_view {
                std::fs::write(&p, serde_json::to_string_pretty(&view)?)
                    .with_context(|| format!("cannot write {}", p.display()))?;
            }
            run_reference(&scene, &view, &output, exposure, true)?;
            Ok(())
        }
        Command::Compare { a, b, diff, json } => {
            let ia = Image::read_exr(&a)?;
            let ib = Image::read_exr(&b)?;
            let c = compare(&ia, &ib).map_err(anyhow::Error::msg)?;
            if let Some(d) = diff {
                let (img, scale) = difference_image(&ia, &ib, None);
                img.write_png(&d, 0.0)?;
                if !json {
                    println!("diff: {} (white = {scale:.4})", d.display());
                }
            }
            if json {
                println!("{}", serde_json::to_string(&c)?);
            } else {
                println!(
                    "rmse {:.6}  relmse {:.6}  ({}x{})",
                    c.rmse, c.relmse, c.width, c.height
                );
            }
            Ok(())
        }
        Command::Gen {
            name,
            output,
            triangles,
            lambertian,
            quantize,
            seed,
        } => {
            let settings = GenSettings {
                triangles,
                lambertian,
                seed,
            };
            let names: Vec<&str> = if name == "all" {
                gen::NAMES.to_vec()
            } else {
                vec![name.as_str()]
            };
            for n in names {
                let (path, tris) =
                    gen::write(n, &settings, &output, quantize).map_err(anyhow::Error::msg)?;
                println!("output: {} ({tris} triangles)", path.display());
            }
            Ok(())
        }
        Command::Info { asset, json } => {
            let scene = load_scene(&asset, false)?;
            let (lo, hi) = scene.bounds();
            if json {
                let mats: Vec<_> = scene
                    .materials
                    .iter()
                    .map(|m| serde_json::json!({"name": m.name, "base_color": m.base_color.to_array(), "metallic": m.metallic, "roughness": m.perceptual_roughness, "specular_factor": m.specular_factor, "textured": m.base_color_texture.is_some(), "cutout": m.has_cutout()}))
                    .collect();
                println!(
                    "{}",
                    serde_json::to_string_pretty(&serde_json::json!({
                        "meshes": scene.meshes.len(),
                        "instances": scene.instances.len(),
                        "triangles": scene.unique_triangle_count(),
                        "instanced_triangles": scene.instanced_triangle_count(),
                        "bounds": [lo.to_array(), hi.to_array()],
                        "materials": mats,
                        "textures": scene.textures.len(),
                        "warnings": scene.warnings,
                    }))?
                );
            } else {
                println!("{}: {}", asset.display(), scene.summary());
                println!("bounds: {lo} .. {hi}");
                for m in &scene.materials {
                    println!(
                        "material '{}': base {:?} metallic {:.2} roughness {:.2} specular {:.2}{}{}",
                        m.name,
                        m.base_color.to_array(),
                        m.metallic,
                        m.perceptual_roughness,
                        m.specular_factor,
                        if m.base_color_texture.is_some() { " textured" } else { "" },
                        if m.has_cutout() { " cut-out" } else { "" }
                    );
                }
            }
            Ok(())
        }
        Command::Tables { action } => tables_cmd(action),
        Command::AbsdfPlot {
            case,
            output,
            samples,
            slice,
            exposure,
        } => absdf_plot(&case, &output, samples, slice, exposure),
        Command::Flatten { asset, output } => {
            let scene = load_scene(&asset, false)?;
            flatten(&scene, &output)
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            for cause in e.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            ExitCode::FAILURE
        }
    }
}
