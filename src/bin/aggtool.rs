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
use aggtool::render::{Image, View};
use aggtool::scene::Scene;
use aggtool::trace::Accel;
use aggtool::util::TerminalProgress;

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
    /// Generate a built-in scene, bake it, render the LoD and the reference at equal time
    /// against a converged reference, and say where everything is (the main job).
    Demo {
        /// Output folder.
        #[arg(short, long, default_value = "aggtool-demo")]
        output: PathBuf,
    },
    /// Quality study (paper Table 3): our LoD against the reference and the alternatives
    /// (cube primitives, exponential volume, meshopt-simplified mesh at equal memory) on assets
    /// and generated hard cases; or, with --speed, equal-spp and equal-time figures.
    Eval {
        /// Assets to study (.gltf, .glb, .obj, or gen:NAME for one generated hard case); none
        /// means every generated hard case.
        assets: Vec<PathBuf>,
        /// Also study every generated hard case (the default when no asset is given).
        #[arg(long)]
        hard_cases: bool,
        /// Triangles of each generated hard case.
        #[arg(long, default_value_t = 100_000)]
        triangles: usize,
        /// LoD resolutions (each gives an image of res² pixels).
        #[arg(long, value_delimiter = ',', default_value = "32,64")]
        res: Vec<u32>,
        /// Samples per pixel of every method.
        #[arg(long, default_value_t = 64)]
        spp: u32,
        /// Samples per pixel of the reference.
        #[arg(long, default_value_t = 1024)]
        reference_spp: u32,
        /// Speed study instead: equal-spp time and equal-time RMSE against the reference,
        /// images of this many pixels square, LoD by footprint.
        #[arg(long)]
        speed: Option<u32>,
        /// With --speed: the bakes' finest resolutions (default: the image's).
        #[arg(long, value_delimiter = ',')]
        bake_res: Vec<u32>,
        /// Where bakes are kept and reused (NAME-RES.agg, RES the finest resolution; default:
        /// bake into the output folder, every time for the quality study).
        #[arg(long)]
        agg_dir: Option<PathBuf>,
        /// Error budget instead (issue 17): at each --res, the LoD rendered with one
        /// approximation at a time replaced by its ground truth from the mesh (coverage, AIV
        /// towards viewer and lights, ABV, ABSDF, visibility split, all); bakes are kept in
        /// --agg-dir as NAME-RES.agg and reused.
        #[arg(long, conflicts_with = "speed")]
        budget: bool,
        /// With --budget: oracle surface samples per voxel (at most 64).
        #[arg(long, default_value_t = 32)]
        budget_samples: u32,
        /// Quality study and budget: render the LoD methods (the budget's rows) without the
        /// per-cone normalisation (as `render --no-normalize`), to measure what it does.
        #[arg(long, conflicts_with = "speed")]
        no_normalize: bool,
        /// Output folder (table.md, table.json, pictures).
        #[arg(short, long, default_value = "aggtool-eval")]
        output: PathBuf,
    },
    /// What accuracy costs: bake ASSET under every preset and under the base (--preset and
    /// the bake flags) with one setting changed at a time (--vary), render each with the LoD
    /// runtime against one converged reference, and write table.md, table.json and Pareto
    /// plots of RMSE against bake seconds, MiB and render seconds. An interrupted sweep
    /// resumes: rows finished with the same settings are reused. The paper's Table 4:
    /// `--vary ndf_lobes=1,2,4 --vary keep=10%,1%`.
    Sweep {
        /// The asset (.gltf, .glb or .obj).
        asset: PathBuf,
        /// A bake setting and its values, NAME=V1,V2,... (repeatable); each value is applied
        /// alone over the base. NAME is a bake setting as `inspect --json` and `convert
        /// --report` name it (ndf_lobes, keep, energy, samples, aiv_rays, ...; dashes work
        /// too); values are numbers, true/false or percentages (keep=1%).
        #[arg(long)]
        vary: Vec<String>,
        /// Image side in pixels (level chosen by footprint); also the bakes' finest level
        /// unless --max-res is given.
        #[arg(long, default_value_t = 64)]
        res: u32,
        /// Cones per pixel of the LoD renders.
        #[arg(long, default_value_t = 64)]
        spp: u32,
        /// Samples per pixel of the reference (rendered once, kept in the output folder).
        #[arg(long, default_value_t = 1024)]
        reference_spp: u32,
        /// Output folder (default: sweep-STEM beside the current folder, STEM the asset's).
        #[arg(short, long)]
        output: Option<PathBuf>,
        #[command(flatten)]
        bake: BakeArgs,
        /// Treat import warnings as errors.
        #[arg(long)]
        strict: bool,
    },
    /// Render an asset, or an assembly manifest, with the reference path tracer (direct
    /// illumination) to EXR and PNG.
    Reference {
        /// The asset (.gltf, .glb or .obj), or an assembly manifest (.json): each mesh loaded
        /// once and instanced by the two-level BVH.
        asset: PathBuf,
        #[command(flatten)]
        view: ViewArgs,
        /// Output EXR; a tonemapped PNG is written beside it.
        #[arg(short, long)]
        output: PathBuf,
        /// Exposure of the PNG in stops.
        #[arg(long, default_value_t = 0.0)]
        exposure: f32,
        /// Treat import warnings as errors.
        #[arg(long)]
        strict: bool,
    },
    /// Compare two linear images (EXR, PFM, HDR; PNG and other 8-bit formats are refused):
    /// RMSE and relative MSE.
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
    /// Write a generated hard-case scene as GLB; or, with `forest`, an assembly: --species
    /// trees of --triangles each and a manifest (forest.json) placing --instances of them; or,
    /// with `city`, a manifest (city.json) laying out --instances pieces of existing kits
    /// (--kit, repeatable; default: the Kenney city kit and the Quaternius village of
    /// $AGGTOOL_ASSETS, else of ../shared/assets from the current folder) as a town, referenced
    /// by relative path, not copied.
    Gen {
        /// One of: plane45, lattice, foliage, displaced-sphere, rings, buildings, all, forest
        /// or city.
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
        /// forest: distinct trees.
        #[arg(long, default_value_t = 4)]
        species: usize,
        /// forest: trees placed; city: pieces placed.
        #[arg(long, default_value_t = 100)]
        instances: usize,
        /// city: a folder of assets to lay out (repeatable).
        #[arg(long = "kit")]
        kits: Vec<PathBuf>,
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
    /// Bake an asset into an aggregate: writes ASSET's stem + .agg next to it by default.
    Convert {
        /// The asset (.gltf, .glb or .obj).
        asset: PathBuf,
        /// Output file (default: the asset's path with the extension .agg).
        #[arg(short, long)]
        output: Option<PathBuf>,
        #[command(flatten)]
        bake: BakeArgs,
        /// Write the stats as JSON to this file.
        #[arg(long)]
        report: Option<PathBuf>,
        /// Print per-level details and every effect decision.
        #[arg(short, long)]
        verbose: bool,
        /// Treat import warnings as errors.
        #[arg(long)]
        strict: bool,
        /// Report progress on stderr as JSON lines ({"stage", "done", "total"}: at each stage's
        /// start, whole percent and end) instead of bars, for programs that run the bake.
        #[arg(long)]
        progress_json: bool,
        /// Bake only shard I of N (e.g. 2/8) into a part file (default: ASSET's path with
        /// .I-of-N.aggpart); `aggtool merge` joins the N parts into the bytes of the one-machine
        /// bake with the same settings. See the README's "Farm bakes".
        #[arg(long, value_parser = parse_shard)]
        shard: Option<aggtool::format::part::Shard>,
    },
    /// Print the bake presets (`convert --preset NAME`) with every setting of each; --json
    /// prints the table the Python module's `aggtool.presets()` returns and the Blender
    /// extension's preset menu reads.
    Presets {
        /// One JSON object on stdout: {"default", "fields", "presets": [{"name", "summary",
        /// "settings"}]}.
        #[arg(long)]
        json: bool,
    },
    /// Join the part files of a sharded bake (`convert --shard I/N`) into the .agg a
    /// one-machine bake writes, byte for byte; refuses missing, duplicate or mismatched parts
    /// and then writes nothing.
    Merge {
        /// The part files, every shard once, in any order.
        #[arg(required_unless_present = "parts_of")]
        parts: Vec<PathBuf>,
        /// The aggregate to write.
        #[arg(short, long)]
        output: PathBuf,
        /// Instead of listing the parts: merge PREFIX.I-of-N.aggpart for I in 0..N (as the
        /// farm template names them), with --shards N.
        #[arg(
            long,
            value_name = "PREFIX",
            requires = "shards",
            conflicts_with = "parts"
        )]
        parts_of: Option<PathBuf>,
        /// N, with --parts-of.
        #[arg(long, requires = "parts_of")]
        shards: Option<u32>,
        /// Delete the part files once the aggregate is written.
        #[arg(long)]
        remove_parts: bool,
    },
    /// Render an .agg aggregate, or an assembly manifest (.json), with the LoD runtime (cone
    /// tracing, Eq. 30) to EXR and PNG.
    Render {
        /// The aggregate (.agg), or an assembly manifest (.json; see the README's "Assemblies").
        agg: PathBuf,
        #[command(flatten)]
        view: ViewArgs,
        /// Output EXR; a tonemapped PNG is written beside it.
        #[arg(short, long)]
        output: PathBuf,
        /// Force this level (0 = finest) instead of choosing by the pixel footprint.
        #[arg(long)]
        level: Option<usize>,
        /// Light samples (and ABSDF samples) per primitive hit, combined by MIS (at least 1).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
        nee: u32,
        /// Use the voxel cube as the primitive (the Fig. 6 ablation).
        #[arg(long, conflicts_with = "volume")]
        cube: bool,
        /// Render the voxels as an exponential-transmittance volume instead (the traditional
        /// volumetric model, a baseline).
        #[arg(long)]
        volume: bool,
        /// Leave each cone's weights as baked instead of dividing its surfaces and background
        /// by their sum (the runtime's default; see the README's error budget).
        #[arg(long)]
        no_normalize: bool,
        /// Exposure of the PNG in stops.
        #[arg(long, default_value_t = 0.0)]
        exposure: f32,
        /// Assemblies: draw every instance from its aggregate. By default an instance seen
        /// finer than its aggregate's finest level is drawn from its mesh (imported when first
        /// needed), as a renderer does.
        #[arg(long)]
        no_mesh: bool,
        /// Assemblies: also write a PNG colouring each pixel by what its first hit was drawn
        /// with (mesh, or the aggregate's level), with a legend.
        #[arg(long, value_name = "PNG")]
        level_map: Option<PathBuf>,
        /// Memory budget of the block cache in MiB: the prepared blocks of every aggregate
        /// drawn (records, inflated bytes, ABSDFs) stay within it, the least recently used
        /// evicted. A smaller budget gives the same image, only slower. Default: a quarter of
        /// the machine's memory.
        #[arg(long, value_name = "MIB")]
        cache_mib: Option<u64>,
    },
    /// Bake every asset of an assembly manifest whose aggregate is missing or stale (a stamp
    /// NAME.agg.stamp.json beside each records its source's and settings' checksums), assets
    /// in parallel; says what it baked and what it reused. The bake settings are `convert`'s.
    Assemble {
        /// The manifest (.json).
        manifest: PathBuf,
        #[command(flatten)]
        bake: BakeArgs,
        /// Consider only this asset (repeatable): a farm task bakes one asset of the manifest
        /// (see the README's "Farm bakes").
        #[arg(long = "asset")]
        assets: Vec<String>,
        /// Consider only the K-th asset of the manifest, 1-based, in the order `--list` prints
        /// (repeatable; for farm tasks over a range of numbers).
        #[arg(long = "asset-number")]
        asset_numbers: Vec<usize>,
        /// Print the manifest's asset ids, one a line, in order, and bake nothing.
        #[arg(long)]
        list: bool,
        /// Fail if any aggregate had to be baked (a farm's last step, after every asset's
        /// task, checks that they all did their part).
        #[arg(long)]
        require_reuse: bool,
        /// Treat import warnings as errors.
        #[arg(long)]
        strict: bool,
        /// Print the outcomes as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Print what an .agg file holds: header, settings, levels, effects kept and dropped; or,
    /// for an assembly manifest (.json): assets, instances, aggregate bytes, triangles.
    Inspect {
        file: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// Write an asset as world-space OBJ files, one per material, with materials.json
    /// (base colours) beside them: the input of the Mitsuba cross-check.
    Flatten {
        asset: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Write an asset as plain data for tools without a glTF/OBJ reader (the USD integration):
    /// scene.json (meshes, instances, materials), geometry.bin (positions, normals, UVs,
    /// indices) and the textures as PNG.
    Export {
        asset: PathBuf,
        /// Output folder (created if needed).
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
            let bars = TerminalProgress::new();
            let t = fit::build(
                fit::BuildSettings {
                    samples,
                    m3_res,
                    m1_res,
                },
                &|s, d, n| bars.report(s, d, n),
            );
            let bytes = t.to_bytes();
            aggtool::util::atomic::write_bytes_atomic(&output, &bytes)
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
        let path = output.join(format!("absdf-{name}.png"));
        aggtool::film::image::side_by_side(
            &path,
            &[
                &gt.to_srgb8(exposure),
                &ours.to_srgb8(exposure),
                &diff.to_srgb8(0.0),
            ],
            gt.width,
            gt.height,
        )?;
        let (r, _) = compare_case(name, t, samples, 8).expect("known case");
        println!("{name}: lobes {} rmse {:.5} (ground truth rms {:.5}, relative {:.3}); difference white = {scale:.4}; output: {}", r.lobes, r.rmse, r.gt_rms, r.rmse / r.gt_rms, path.display());
    }
    Ok(())
}

/// The bake's settings on the command line: a preset, and flags that override its values.
/// Defaults live in `aggtool::bake::BakeSettings` and its presets alone (see `--preset`).
#[derive(clap::Args, Debug, Clone)]
struct BakeArgs {
    /// Starting point for every setting below: draft (64³, an eighth of the samples and rays,
    /// coarser truncation), default, high (twice the samples and the AIV rays, two ABV rays
    /// per cell, centred ABV windows), max (the paper's ablation control: 4 lobes, no
    /// truncation, quantization or compression). Flags given beside it override it.
    #[arg(long, default_value = "default", value_parser = clap::builder::PossibleValuesParser::new(aggtool::bake::Preset::ALL.map(aggtool::bake::Preset::name)))]
    preset: String,
    /// Finest level resolution (a power of two); levels halve down to --min-res [preset
    /// default: 256; draft 64].
    #[arg(long)]
    max_res: Option<u32>,
    /// Coarsest level resolution [default: 4].
    #[arg(long)]
    min_res: Option<u32>,
    /// Surface samples per voxel at the finest level; a level of resolution r gets
    /// samples·(max_res/r)², at most --max-samples [default: 32; draft 4, high 64].
    #[arg(long)]
    samples: Option<u32>,
    /// Cap on the surface samples per voxel of coarser levels [default: 1024].
    #[arg(long)]
    max_samples: Option<u32>,
    /// Interior-visibility map resolution (Clarberg equal-area, per voxel) [default: 32;
    /// draft 16].
    #[arg(long)]
    aiv_res: Option<u32>,
    /// Interior-visibility rays per surface sample [default: 32; draft 4, high 64].
    #[arg(long)]
    aiv_rays: Option<u32>,
    /// Fewest rays an interior-visibility cell's estimate rests on (a cell pools the rays of
    /// the smallest enclosing block of cells holding that many): 0 chooses it per voxel by
    /// cross-validation, 1 is the per-cell average of earlier versions [default: 0; max 1].
    #[arg(long)]
    aiv_min_rays: Option<u32>,
    /// Boundary-visibility map resolution (concentric, per boundary face) [default: 64;
    /// draft 32].
    #[arg(long)]
    abv_res: Option<u32>,
    /// Boundary-visibility rays per direction cell [default: 1; high 2].
    #[arg(long)]
    abv_rays: Option<u32>,
    /// Levels finer than this share each face's boundary-visibility rays among blocks of
    /// (res / N)² direction cells, so that each finer level costs about as many ABV rays as
    /// this one; set it to --max-res for a ray per cell on every level (the paper's budget)
    /// [default: 64; draft 32].
    #[arg(long)]
    abv_full_res: Option<u32>,
    /// Let boundary-visibility cells average a window of cells centred on them, besides the
    /// enclosing blocks, where each face's held-out rays prefer it: less bias on smooth
    /// visibility, about twice the ABV's bytes [default: false; high true].
    #[arg(long, value_name = "BOOL")]
    abv_windows: Option<bool>,
    /// Most SGGX lobes per voxel, 1 to 4 [default: 4; draft 2].
    #[arg(long)]
    ndf_lobes: Option<u32>,
    /// Directional-moment grid resolution (Eq. 23) [default: 3].
    #[arg(long)]
    moment_res: Option<u32>,
    /// Fraction of wavelet coefficients kept [default: 0.15; draft 0.1, max 1].
    #[arg(long)]
    keep: Option<f32>,
    /// Detail energy kept by the wavelet truncation (more coefficients kept until reached)
    /// [default: 0.98; draft 0.95, max 1].
    #[arg(long)]
    energy: Option<f32>,
    /// Store every effect in full even where the asset does not need it.
    #[arg(long)]
    keep_all_effects: bool,
    /// Keep the Monte Carlo noise in the visibility wavelets (the paper's truncation alone;
    /// the max preset does).
    #[arg(long)]
    no_denoise: bool,
    /// Keep the float layout of format 1.0–1.3 (f32 Haar nodes, lobes and moments) instead
    /// of format 1.4's quantized one (about 2.3× smaller; visibility values within 0.035; the
    /// max preset does).
    #[arg(long)]
    lossless: bool,
    /// Zstandard level of the blocks (format 1.5; 1 to 22, 0 for none). Lossless: readers
    /// inflate a block the first time they read it. 19 gives the maple at 64³ 2.2× fewer
    /// bytes than level 0 for a few seconds of bake [default: 19; draft 3, max 0].
    #[arg(long)]
    compression_level: Option<i32>,
    /// No clustered PCA of the visibility. Accepted and ignored: CPCA was measured
    /// (examples/cpca_probe.rs) and does not pay on the quantized, truncated trees, so no
    /// file stores it.
    #[arg(long)]
    no_cpca: bool,
}

impl BakeArgs {
    /// The preset's settings with every flag given applied over them.
    fn settings(&self) -> aggtool::bake::BakeSettings {
        use aggtool::bake::{BakeSettings, Preset};
        let mut s =
            BakeSettings::preset(Preset::from_name(&self.preset).unwrap_or(Preset::Default));
        let set = |dst: &mut u32, v: Option<u32>| {
            if let Some(v) = v {
                *dst = v;
            }
        };
        set(&mut s.max_res, self.max_res);
        set(&mut s.min_res, self.min_res);
        set(&mut s.samples, self.samples);
        set(&mut s.max_samples, self.max_samples);
        set(&mut s.aiv_res, self.aiv_res);
        set(&mut s.aiv_rays, self.aiv_rays);
        set(&mut s.aiv_min_rays, self.aiv_min_rays);
        set(&mut s.abv_res, self.abv_res);
        set(&mut s.abv_rays, self.abv_rays);
        set(&mut s.abv_full_res, self.abv_full_res);
        s.abv_windows = self.abv_windows.unwrap_or(s.abv_windows);
        set(&mut s.ndf_lobes, self.ndf_lobes);
        set(&mut s.moment_res, self.moment_res);
        s.keep = self.keep.unwrap_or(s.keep);
        s.energy = self.energy.unwrap_or(s.energy);
        s.compression = self.compression_level.unwrap_or(s.compression);
        s.keep_all_effects |= self.keep_all_effects;
        s.denoise &= !self.no_denoise;
        s.lossless |= self.lossless;
        s
    }
}

/// `aggtool sweep`: the settings from the flags (each preset with the same flags, the base
/// among them), one library call (`aggtool::eval::sweep`), the report.
#[allow(clippy::too_many_arguments)]
fn sweep(
    asset: &Path,
    vary: &[String],
    res: u32,
    spp: u32,
    reference_spp: u32,
    output: Option<PathBuf>,
    bake: &BakeArgs,
    strict: bool,
) -> Result<()> {
    use aggtool::bake::Preset;
    use aggtool::eval::sweep::{sweep, RowEvent, SweepSettings, Vary};
    if bake.max_res.is_none() && (!res.is_power_of_two() || res < 4) {
        bail!("--res {res}: the bakes' finest level is --res, so it must be a power of two of at least 4 (or give --max-res)");
    }
    let settings_of = |preset: &str| {
        let mut s = BakeArgs {
            preset: preset.to_string(),
            ..bake.clone()
        }
        .settings();
        if bake.max_res.is_none() {
            s.max_res = res;
        }
        s
    };
    let vary = vary
        .iter()
        .map(|v| Vary::parse(v))
        .collect::<Result<Vec<_>, _>>()
        .map_err(anyhow::Error::msg)?;
    let settings = SweepSettings {
        base_name: bake.preset.clone(),
        base: settings_of(&bake.preset),
        presets: Preset::ALL
            .iter()
            .map(|p| (p.name().to_string(), settings_of(p.name())))
            .collect(),
        vary,
        res,
        spp,
        reference_spp,
    };
    // Refuse bad --vary names and values before importing anything.
    let planned = aggtool::eval::sweep::plan(&settings)?;
    let dir = output.unwrap_or_else(|| {
        let stem = asset.file_stem().unwrap_or_default().to_string_lossy();
        PathBuf::from(format!("sweep-{stem}"))
    });
    let scene = load_scene(asset, strict)?;
    println!(
        "input: {}: {}; {} settings, {res}² pixels, {spp} spp, reference {reference_spp} spp",
        asset.display(),
        scene.summary(),
        planned.len()
    );
    let bars = TerminalProgress::new();
    let on_row = |e: RowEvent| {
        bars.finish();
        match e {
            RowEvent::Reference(Some(secs)) => {
                println!("reference: rendered at {reference_spp} spp in {secs:.1} s")
            }
            RowEvent::Reference(None) => println!("reused: reference ({reference_spp} spp)"),
            RowEvent::Done(r) => println!(
                "baked: {}: bake {:.2} s ({:.1} CPU s), {}, render {:.2} s ({:.2} CPU s), RMSE {:.5}",
                r.label,
                r.bake_seconds,
                r.bake_cpu_seconds,
                mib(r.bytes),
                r.render_seconds,
                r.render_cpu_seconds,
                r.rmse
            ),
            RowEvent::Reused { row, same_as } => match same_as {
                Some(o) => println!("reused: {} (same settings as {o})", row.label),
                None => println!("reused: {} (finished earlier)", row.label),
            },
        }
    };
    let r = sweep(
        asset,
        &scene,
        &settings,
        &dir,
        &|s, d, n| bars.report(s, d, n),
        &on_row,
    )?;
    bars.finish();
    print!("{}", std::fs::read_to_string(dir.join(&r.table_md))?);
    println!(
        "output: {} (table.md, table.json, {})",
        dir.display(),
        r.plots.join(", ")
    );
    Ok(())
}

fn load_scene(path: &Path, strict: bool) -> Result<Scene> {
    let scene = import::load(path, ImportOptions { strict })?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    Ok(scene)
}

/// An assembly's meshes as one scene, each source imported once (see
/// `aggtool::assembly::mesh`).
fn load_assembly_scene(path: &Path, strict: bool) -> Result<Scene> {
    use aggtool::assembly::{mesh, Manifest};
    let m = Manifest::load(path)?;
    let sources = mesh::load_sources(&m, ImportOptions { strict })?;
    let scene = mesh::scene(&m, &sources);
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "input: {}: {} assets, {} instances",
        path.display(),
        m.assets.len(),
        m.instance_count()
    );
    Ok(scene)
}

/// The view of a render command (`reference`, `render`): a view file, or the asset framed.
#[derive(clap::Args)]
struct ViewArgs {
    /// View file (JSON); see the book's "View files".
    #[arg(long, conflicts_with = "auto_view")]
    view: Option<PathBuf>,
    /// Frame the asset's bounding sphere instead of reading a view file (`render` frames the
    /// bounds the aggregate records, so it frames an asset as `reference` frames its mesh).
    #[arg(long)]
    auto_view: bool,
    /// Image width for --auto-view (1 to 16384).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=16384))]
    width: u32,
    /// Image height for --auto-view (1 to 16384).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=16384))]
    height: u32,
    /// Samples (cones) per pixel (overrides the view file).
    #[arg(long)]
    spp: Option<u32>,
    /// Random seed (overrides the view file).
    #[arg(long)]
    seed: Option<u64>,
    /// Write the view used (useful with --auto-view) to this file.
    #[arg(long)]
    save_view: Option<PathBuf>,
}

impl ViewArgs {
    /// The view: loaded, or framing the sphere `sphere` gives (centre, radius); with --spp and
    /// --seed applied, validated, and saved where --save-view asks.
    fn resolve(&self, sphere: impl FnOnce() -> Result<(glam::Vec3, f32)>) -> Result<View> {
        let mut view = match (&self.view, self.auto_view) {
            (Some(v), _) => View::load(v)?,
            (None, true) => {
                let (c, r) = sphere()?;
                View::framing(c, r, self.width, self.height, self.spp.unwrap_or(64))
            }
            (None, false) => bail!("give a view file with --view, or --auto-view"),
        };
        if let Some(s) = self.spp {
            view.spp = s;
        }
        if let Some(s) = self.seed {
            view.seed = s;
        }
        view.validate().map_err(anyhow::Error::msg)?;
        if let Some(p) = &self.save_view {
            std::fs::write(p, serde_json::to_string_pretty(&view)?)
                .with_context(|| format!("cannot write {}", p.display()))?;
        }
        Ok(view)
    }
}

fn png_beside(exr: &Path) -> PathBuf {
    exr.with_extension("png")
}

/// The EXR a render writes for `-o OUTPUT`: OUTPUT itself, or beside it with `.exr` when
/// OUTPUT names the PNG (which is then the tonemapped picture, not overwritten by EXR data).
fn exr_path(output: &Path) -> PathBuf {
    let png = output
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if png {
        output.with_extension("exr")
    } else {
        output.to_path_buf()
    }
}

fn run_reference(
    scene: &Scene,
    view: &View,
    output: &Path,
    exposure: f32,
) -> Result<aggtool::film::ImageStats> {
    let lights = view.lights()?;
    let t0 = std::time::Instant::now();
    let accel = Accel::build(scene);
    let build = t0.elapsed().as_secs_f64();
    let bars = TerminalProgress::new();
    let (img, stats) = reference::render(
        &accel,
        &view.camera(),
        &lights,
        ReferenceSettings {
            spp: view.spp,
            seed: view.seed,
        },
        &|s, d, n| bars.report(s, d, n),
    );
    bars.finish();
    img.write_exr(&exr_path(output))?;
    img.write_png(&png_beside(output), exposure)?;
    println!(
        "stats: bvh {:.2} s ({} BLAS, {} TLAS entries)",
        build, accel.stats.blas_count, accel.stats.tlas_entries,
    );
    println!("{}", stats.line("reference"));
    if let Some(l) = aggtool::util::process::peak_rss_line() {
        println!("{l}");
    }
    println!(
        "output: {} and {}",
        exr_path(output).display(),
        png_beside(output).display()
    );
    Ok(stats)
}

/// Renders an aggregate with the LoD runtime; returns (open seconds, render seconds).
fn run_lod(
    agg_path: &Path,
    view: &View,
    output: &Path,
    exposure: f32,
    settings: &aggtool::runtime::TraceSettings,
) -> Result<(f64, f64)> {
    let lights = view.lights()?;
    let t0 = std::time::Instant::now();
    let scene = aggtool::runtime::LodScene::open(agg_path)
        .with_context(|| format!("cannot read {}", agg_path.display()))?;
    let prepare = t0.elapsed().as_secs_f64();
    if let Some(l) = settings.level {
        if l >= scene.level_count() {
            bail!(
                "--level {l}: the aggregate has levels 0 to {}",
                scene.level_count() - 1
            );
        }
    }
    println!(
        "input: {}: {} levels, {} bytes (opened in {:.1} ms)",
        agg_path.display(),
        scene.level_count(),
        scene.aggregate().header().file_size,
        prepare * 1e3
    );
    let bars = TerminalProgress::new();
    let (img, stats) = aggtool::runtime::render(
        &scene,
        &view.camera(),
        &lights,
        view.spp,
        view.seed,
        settings,
        &|s, d, n| bars.report(s, d, n),
    );
    bars.finish();
    if let Some(e) = scene.first_error() {
        bail!("{}: {e}", agg_path.display());
    }
    img.write_exr(&exr_path(output))?;
    img.write_png(&png_beside(output), exposure)?;
    let seconds = stats.seconds;
    println!("{}", stats.line("LoD"));
    println!(
        "stats: {} cones/pixel, {} light samples per shaded voxel, levels used {:?}",
        view.spp,
        settings.nee,
        scene.resolutions_used()
    );
    println!("{}", cache_line(scene.skeleton_bytes()));
    if let Some(l) = aggtool::util::process::peak_rss_line() {
        println!("{l}");
    }
    println!(
        "output: {} and {}",
        exr_path(output).display(),
        png_beside(output).display()
    );
    Ok((prepare, seconds))
}

/// Renders an assembly (a manifest) with the LoD runtime, hybrid (meshes where they are seen
/// finer than the finest level) unless `meshes` is false; returns the render seconds.
fn run_assembly_lod(
    manifest: &Path,
    view: &View,
    output: &Path,
    exposure: f32,
    settings: &aggtool::runtime::TraceSettings,
    meshes: bool,
    level_map: Option<&Path>,
) -> Result<f64> {
    use aggtool::assembly::Representation;
    let lights = view.lights()?;
    let t0 = std::time::Instant::now();
    let mut asm = aggtool::assembly::Assembly::open(manifest)?;
    if meshes {
        asm.set_representation(Representation::Hybrid);
    }
    let m = asm.manifest();
    println!(
        "input: {}: {} assets, {} instances (opened with the instance BVH in {:.1} ms)",
        manifest.display(),
        m.assets.len(),
        m.instance_count(),
        t0.elapsed().as_secs_f64() * 1e3
    );
    let bars = TerminalProgress::new();
    let (img, stats) = aggtool::assembly::render(
        &asm,
        &view.camera(),
        &lights,
        view.spp,
        view.seed,
        settings,
        &|s, d, n| bars.report(s, d, n),
    );
    bars.finish();
    for (a, asset) in m.assets.iter().enumerate() {
        if let Some(e) = asm.scene(a).first_error() {
            bail!("asset '{}': {}: {e}", asset.id, asset.aggregate.display());
        }
    }
    if let Some((a, e)) = asm.mesh_error() {
        bail!(
            "asset '{}': its mesh is needed (an instance is seen finer than its aggregate's \
             finest level) but {e}; --no-mesh draws every instance from its aggregate",
            m.assets[a].id
        );
    }
    img.write_exr(&exr_path(output))?;
    img.write_png(&png_beside(output), exposure)?;
    println!("{}", stats.line("LoD"));
    for (a, asset) in m.assets.iter().enumerate() {
        let s = asm.scene(a);
        let mesh = match asm.mesh_triangles(a) {
            Some(t) => format!(", mesh loaded ({t} triangles)"),
            None => String::new(),
        };
        println!(
            "stats: asset '{}': levels used {:?}{mesh}",
            asset.id,
            s.resolutions_used()
        );
    }
    let skeletons = (0..m.assets.len())
        .map(|a| asm.scene(a).skeleton_bytes())
        .sum();
    println!("{}", cache_line(skeletons));
    if let Some(l) = aggtool::util::process::peak_rss_line() {
        println!("{l}");
    }
    if let Some(path) = level_map {
        let camera = view.camera();
        let map = aggtool::assembly::level_map(&asm, &camera, settings);
        let levels = (0..m.assets.len())
            .map(|a| asm.scene(a).level_count())
            .max()
            .unwrap_or(1);
        let (rgb, h, legend) =
            aggtool::assembly::lod::level_map_picture(&map, camera.width, camera.height, levels);
        aggtool::film::image::write_rgb8_png(path, camera.width, h, &rgb)?;
        println!(
            "level map: {} (what the cone through each pixel's centre meets first: mesh, or the \
             aggregate's level L0 = finest; share of pixels): {}",
            path.display(),
            legend.join(", ").to_lowercase()
        );
    }
    println!(
        "output: {} and {}",
        exr_path(output).display(),
        png_beside(output).display()
    );
    Ok(stats.seconds)
}

/// `inspect MANIFEST`: assets, instances, bytes of the aggregates, triangles.
fn inspect_assembly(path: &Path, json: bool) -> Result<()> {
    let m = aggtool::assembly::Manifest::load(path)?;
    let s = aggtool::assembly::mesh::summary(&m, true)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&s)?);
        return Ok(());
    }
    let opt = |v: Option<u64>| v.map_or("?".to_string(), |v| v.to_string());
    println!(
        "{}: {} assets, {} instances ({} in memory)",
        path.display(),
        s.assets,
        s.instances,
        mib(s.instance_bytes as u64)
    );
    for a in &s.per_asset {
        println!(
            "asset '{}': {} instances, source {}{}, aggregate {} ({}), {} triangles ({} placed)",
            a.id,
            a.instances,
            a.source,
            if a.source_present { "" } else { " (missing)" },
            a.aggregate,
            a.aggregate_bytes.map_or("missing".into(), mib),
            opt(a.unique_triangles),
            opt(a.placed_triangles),
        );
    }
    println!(
        "aggregates: {} present; triangles: {} unique, {} instanced",
        mib(s.aggregate_bytes),
        opt(s.unique_triangles),
        opt(s.instanced_triangles)
    );
    Ok(())
}

/// `aggtool eval`: the quality (or speed) study over assets and hard cases.
#[allow(clippy::too_many_arguments)]
fn eval(
    assets: &[PathBuf],
    hard_cases: bool,
    triangles: usize,
    res: Vec<u32>,
    spp: u32,
    reference_spp: u32,
    speed: Option<u32>,
    bake_res: Vec<u32>,
    agg_dir: Option<PathBuf>,
    budget_samples: Option<u32>,
    normalize: bool,
    output: &Path,
) -> Result<()> {
    use aggtool::eval;
    if let Some(r) = res.iter().find(|r| !r.is_power_of_two() || **r < 4) {
        bail!("--res {r}: each resolution must be a power of two of at least 4");
    }
    std::fs::create_dir_all(output)
        .with_context(|| format!("cannot create {}", output.display()))?;
    type Loader = Box<dyn Fn() -> Result<Scene>>;
    let generated = |n: String, triangles: usize| -> Loader {
        let settings = GenSettings {
            triangles,
            ..GenSettings::default()
        };
        Box::new(move || {
            gen::generate(&n, &settings)
                .map(|s| s.to_scene())
                .ok_or_else(|| anyhow::anyhow!("unknown scene {n}"))
        })
    };
    let mut scenes: Vec<(String, Loader)> = Vec::new();
    for a in assets {
        // `gen:NAME` is a generated hard case of --triangles triangles.
        if let Some(n) = a.to_str().and_then(|s| s.strip_prefix("gen:")) {
            let n = n.to_string();
            if !gen::NAMES.contains(&n.as_str()) {
                bail!(
                    "{}: unknown hard case; choose one of: {}",
                    a.display(),
                    gen::NAMES.join(", ")
                );
            }
            scenes.push((n.clone(), generated(n, triangles)));
            continue;
        }
        let name = a
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "asset".into());
        let a = a.clone();
        scenes.push((name, Box::new(move || load_scene(&a, false))));
    }
    if hard_cases {
        for &n in gen::NAMES {
            scenes.push((n.to_string(), generated(n.to_string(), triangles)));
        }
    }
    if let Some(samples) = budget_samples {
        let agg_dir = agg_dir.unwrap_or_else(|| output.to_path_buf());
        std::fs::create_dir_all(&agg_dir)?;
        let bars = TerminalProgress::new();
        let mut all = Vec::new();
        for (name, load) in &scenes {
            let scene = load()?;
            for &r in &res {
                let settings = eval::budget::BudgetSettings {
                    res: r,
                    spp,
                    reference_spp,
                    samples,
                    normalize,
                    ..Default::default()
                };
                let agg = agg_dir.join(format!("{name}-{r}.agg"));
                let b = eval::budget::budget_scene(
                    name,
                    &scene,
                    &agg,
                    &settings,
                    output,
                    &|s, d, n| bars.report(s, d, n),
                )?;
                bars.finish();
                println!("{}", eval::budget::budget_table(std::slice::from_ref(&b)));
                all.push(b);
            }
        }
        let md = output.join("budget.md");
        std::fs::write(&md, eval::budget::budget_table(&all))?;
        std::fs::write(
            output.join("budget.json"),
            serde_json::to_string_pretty(&all)?,
        )?;
        println!(
            "output: {}, budget.json and {}/NAME-budget-RES.png (top: reference and each row; bottom: differences on one scale)",
            md.display(),
            output.display()
        );
        return Ok(());
    }
    if let Some(px) = speed {
        // Each scene as a file (generated hard cases written as GLB), each bake looked up in
        // --agg-dir as NAME-RES.agg and baked there when missing.
        let agg_dir = agg_dir.unwrap_or_else(|| output.to_path_buf());
        std::fs::create_dir_all(&agg_dir)?;
        let mut files: Vec<(String, PathBuf)> = Vec::new();
        for a in assets {
            if let Some(n) = a.to_str().and_then(|s| s.strip_prefix("gen:")) {
                if !gen::NAMES.contains(&n) {
                    bail!(
                        "{}: unknown hard case; choose one of: {}",
                        a.display(),
                        gen::NAMES.join(", ")
                    );
                }
                let path = agg_dir.join(format!("{n}-{triangles}.glb"));
                if !path.exists() {
                    let settings = GenSettings {
                        triangles,
                        ..GenSettings::default()
                    };
                    let (p, _) =
                        gen::write(n, &settings, &agg_dir, false).map_err(anyhow::Error::msg)?;
                    std::fs::rename(&p, &path)?;
                }
                files.push((n.to_string(), path));
            } else {
                let name = a
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "asset".into());
                files.push((name, a.clone()));
            }
        }
        let bake_res = if bake_res.is_empty() {
            vec![px.max(8)]
        } else {
            bake_res
        };
        let bars = TerminalProgress::new();
        let mut rows = Vec::new();
        for (name, path) in &files {
            for &br in &bake_res {
                let agg = agg_dir.join(format!("{name}-{br}.agg"));
                let bake = aggtool::bake::BakeSettings {
                    max_res: br,
                    ..Default::default()
                };
                let r = eval::speed_scene(
                    &eval::SpeedInput {
                        name,
                        asset: path,
                        agg: &agg,
                    },
                    &bake,
                    px,
                    spp,
                    reference_spp,
                    output,
                    &|s, d, n| bars.report(s, d, n),
                )?;
                bars.finish();
                eprintln!("{}: done", r.scene);
                rows.push(r);
            }
        }
        let table = eval::speed_table(&rows);
        println!("{table}");
        std::fs::write(output.join("speed.md"), &table)?;
        let json = output.join("speed.json");
        std::fs::write(&json, serde_json::to_string_pretty(&rows)?)?;
        println!(
            "output: {}, speed.md and {}/NAME-RES-speed.png (reference | LoD | reference at equal spp | reference at equal time)",
            json.display(),
            output.display()
        );
        return Ok(());
    }
    if let Some(d) = &agg_dir {
        std::fs::create_dir_all(d)?;
    }
    let settings = eval::StudySettings {
        resolutions: res,
        spp,
        reference_spp,
        agg_dir,
        normalize,
        ..Default::default()
    };
    let mut all = Vec::new();
    for (name, load) in &scenes {
        let t = std::time::Instant::now();
        let scene = load()?;
        let r = eval::study_scene(name, &scene, &settings, output, &aggtool::util::no_progress)?;
        for x in &r {
            let line: Vec<String> = x
                .methods
                .iter()
                .map(|m| format!("{} {:.4}", m.method, m.rmse))
                .collect();
            println!("{name} {}³: {}", x.res, line.join(", "));
        }
        println!("  ({:.0} s)", t.elapsed().as_secs_f64());
        all.extend(r);
    }
    let table = eval::markdown_table(&all);
    let md = output.join("table.md");
    std::fs::write(&md, &table)?;
    std::fs::write(
        output.join("table.json"),
        serde_json::to_string_pretty(&all)?,
    )?;
    println!("{table}");
    println!(
        "output: {} and table.json; pictures {}/SCENE-RES.png: top reference, ours, cube, volume, mesh, ref@spp; bottom their differences on one scale",
        md.display(),
        output.display()
    );
    Ok(())
}

/// The main job on a built-in scene (`aggtool::eval::demo`), reported.
fn demo(output: &Path) -> Result<()> {
    use aggtool::eval::demo::{demo, DemoSettings};
    let settings = DemoSettings::default();
    let bars = TerminalProgress::new();
    let r = demo(output, &settings, &|s, d, n| bars.report(s, d, n))?;
    bars.finish();
    println!(
        "input: generated {} ({} triangles)",
        r.asset.display(),
        r.triangles
    );
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "stats: bake {:.1} s, {} levels, {:.1} MiB",
        r.bake_seconds,
        r.levels,
        r.bytes as f64 / 1048576.0
    );
    println!("{}", r.lod.line("LoD"));
    println!("{}", r.reference.line("reference"));
    println!(
        "stats: equal time: LoD {:.2} s at {} spp, RMSE {:.4}; reference {:.2} s at {} spp, RMSE {:.4} (against the reference at {} spp)",
        r.lod_seconds, settings.lod_spp, r.lod_rmse, r.reference.seconds, r.reference_spp, r.reference_rmse, settings.truth_spp
    );
    println!(
        "output: {} (reference {} spp | LoD | reference at equal time | differences), in {:.0} s",
        r.picture.display(),
        settings.truth_spp,
        r.seconds
    );
    Ok(())
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo { output } => demo(&output),
        Command::Eval {
            assets,
            hard_cases,
            triangles,
            res,
            spp,
            reference_spp,
            speed,
            bake_res,
            agg_dir,
            budget,
            budget_samples,
            no_normalize,
            output,
        } => eval(
            &assets,
            hard_cases || assets.is_empty(),
            triangles,
            res,
            spp,
            reference_spp,
            speed,
            bake_res,
            agg_dir,
            budget.then_some(budget_samples),
            !no_normalize,
            &output,
        ),
        Command::Reference {
            asset,
            view,
            output,
            exposure,
            strict,
        } => {
            let scene = if aggtool::assembly::is_manifest(&asset) {
                load_assembly_scene(&asset, strict)?
            } else {
                load_scene(&asset, strict)?
            };
            println!("input: {}: {}", asset.display(), scene.summary());
            let view = view.resolve(|| Ok(scene.bounding_sphere()))?;
            run_reference(&scene, &view, &output, exposure)?;
            Ok(())
        }
        Command::Compare { a, b, diff, json } => {
            let ia = Image::read_linear(&a)?;
            let ib = Image::read_linear(&b)?;
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
            species,
            instances,
            kits,
        } => {
            if name == "city" {
                let kits = if kits.is_empty() {
                    // Looked for at run time (a path compiled in would be the build machine's).
                    let shared = std::env::var_os("AGGTOOL_ASSETS")
                        .map_or_else(|| PathBuf::from("../shared/assets"), PathBuf::from);
                    let kits = vec![
                        shared.join("kenney_city_kit"),
                        shared.join("quaternius_medieval_village"),
                    ];
                    if let Some(k) = kits.iter().find(|k| !k.is_dir()) {
                        bail!(
                            "no --kit given, and the default kit {} is not a folder (the default \
                             kits are looked for in $AGGTOOL_ASSETS, else in ../shared/assets from \
                             the current folder): give --kit FOLDER (repeatable) or set \
                             AGGTOOL_ASSETS",
                            k.display()
                        );
                    }
                    kits
                } else {
                    kits
                };
                let r = aggtool::assembly::city::write(&output, &kits, instances, seed)
                    .map_err(anyhow::Error::msg)?;
                println!(
                    "output: {} ({} pieces of {} assets)",
                    r.manifest.display(),
                    r.instances,
                    r.assets
                );
                return Ok(());
            }
            if name == "forest" {
                let r =
                    aggtool::assembly::forest::write(&output, species, instances, triangles, seed)
                        .map_err(anyhow::Error::msg)?;
                for a in &r.assets {
                    println!("output: {}", a.display());
                }
                println!(
                    "output: {} ({} trees of {} species, {} triangles each)",
                    r.manifest.display(),
                    r.instances,
                    species,
                    r.tree_triangles
                );
                return Ok(());
            }
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
                        // Each mesh once, 32 B a vertex and 12 a triangle: what the quality
                        // and compression studies weigh an aggregate against.
                        "geometry_bytes": aggtool::eval::simplify::scene_bytes(&scene),
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
        Command::Merge {
            parts,
            output,
            parts_of,
            shards,
            remove_parts,
        } => {
            let t0 = std::time::Instant::now();
            let parts = match (parts_of, shards) {
                (Some(prefix), Some(n)) => (0..n)
                    .map(|i| {
                        let mut p = prefix.clone().into_os_string();
                        p.push(format!(".{i}-of-{n}.aggpart"));
                        PathBuf::from(p)
                    })
                    .collect(),
                _ => parts,
            };
            let size = aggtool::format::part::merge(&parts, &output)?;
            if remove_parts {
                for p in &parts {
                    std::fs::remove_file(p).with_context(|| format!("removing {}", p.display()))?;
                }
            }
            println!(
                "output: {} ({}) from {} parts in {:.2} s",
                output.display(),
                mib(size),
                parts.len(),
                t0.elapsed().as_secs_f64()
            );
            Ok(())
        }
        Command::AbsdfPlot {
            case,
            output,
            samples,
            slice,
            exposure,
        } => absdf_plot(&case, &output, samples, slice, exposure),
        Command::Convert {
            asset,
            output,
            bake,
            report,
            verbose,
            strict,
            progress_json,
            shard,
        } => {
            let settings = bake.settings();
            convert(
                &asset,
                output,
                shard,
                &settings,
                report.as_deref(),
                verbose,
                strict,
                progress_json,
            )
        }
        Command::Presets { json } => {
            let table = aggtool::bake::PresetTable::new();
            match json {
                true => println!("{}", serde_json::to_string_pretty(&table)?),
                false => print!("{table}"),
            }
            Ok(())
        }
        Command::Assemble {
            manifest,
            bake,
            mut assets,
            asset_numbers,
            list,
            require_reuse,
            strict,
            json,
        } => {
            let settings = bake.settings();
            let mut m = aggtool::assembly::Manifest::load(&manifest)?;
            if list {
                for a in &m.assets {
                    println!("{}", a.id);
                }
                return Ok(());
            }
            for &k in &asset_numbers {
                let a = k
                    .checked_sub(1)
                    .and_then(|i| m.assets.get(i))
                    .with_context(|| {
                        format!(
                            "{}: no asset number {k} (it has {}, numbered from 1)",
                            manifest.display(),
                            m.assets.len()
                        )
                    })?;
                assets.push(a.id.clone());
            }
            if !assets.is_empty() {
                for id in &assets {
                    if !m.assets.iter().any(|a| &a.id == id) {
                        anyhow::bail!("{}: no asset '{id}'", manifest.display());
                    }
                }
                m.assets.retain(|a| assets.contains(&a.id));
            }
            if require_reuse {
                // Refused before anything is baked, not after the bakes.
                let stale = aggtool::assembly::bake::stale_assets(&m, &settings)?;
                if !stale.is_empty() {
                    let list: Vec<String> = stale
                        .iter()
                        .map(|(id, why)| format!("asset '{id}' ({why})"))
                        .collect();
                    anyhow::bail!(
                        "{}: {} aggregate(s) would have had to be baked, so nothing was baked \
                         (--require-reuse: every asset's bake task should have written them): {}",
                        manifest.display(),
                        stale.len(),
                        list.join(", ")
                    );
                }
            }
            let t0 = std::time::Instant::now();
            let outcomes =
                aggtool::assembly::bake::assemble(&m, &settings, ImportOptions { strict }, &|o| {
                    if !json {
                        match &o.reason {
                            Some(r) => println!(
                                "baked: asset '{}' ({r}) -> {} ({}, {:.1} s)",
                                o.asset,
                                o.aggregate.display(),
                                mib(o.bytes),
                                o.seconds
                            ),
                            None => println!(
                                "reused: asset '{}': {} is up to date",
                                o.asset,
                                o.aggregate.display()
                            ),
                        }
                    }
                })?;
            let baked = outcomes.iter().filter(|o| o.baked).count();
            if json {
                println!("{}", serde_json::to_string_pretty(&outcomes)?);
            } else {
                println!(
                    "stats: {} assets: {baked} baked, {} reused, {:.1} s",
                    outcomes.len(),
                    outcomes.len() - baked,
                    t0.elapsed().as_secs_f64()
                );
            }
            if require_reuse && baked > 0 {
                anyhow::bail!(
                    "{}: {baked} aggregate(s) had to be baked (--require-reuse: every asset's \
                     bake task should have written them)",
                    manifest.display()
                );
            }
            Ok(())
        }
        Command::Inspect { file, json } if aggtool::assembly::is_manifest(&file) => {
            inspect_assembly(&file, json)
        }
        Command::Inspect { file, json } => inspect(&file, json),
        Command::Render {
            agg,
            view,
            output,
            level,
            nee,
            cube,
            volume,
            exposure,
            no_normalize,
            no_mesh,
            level_map,
            cache_mib,
        } => {
            if let Some(m) = cache_mib {
                aggtool::runtime::BlockCache::global().set_budget(m.saturating_mul(1 << 20));
            }
            let view = view.resolve(|| {
                let opened = aggtool::assembly::Opened::open(&agg)
                    .with_context(|| format!("cannot read {}", agg.display()))?;
                let (lo, hi) = opened
                    .bounds()
                    .ok_or_else(|| anyhow::anyhow!("{}: nothing to frame", agg.display()))?;
                Ok((0.5 * (lo + hi), (0.5 * (hi - lo).length()).max(1e-6)))
            })?;
            let settings = aggtool::runtime::TraceSettings {
                nee,
                level,
                shading: Default::default(),
                normalize: !no_normalize,
                primitive: if cube {
                    aggtool::runtime::PrimitiveKind::Cube
                } else if volume {
                    aggtool::runtime::PrimitiveKind::Volume
                } else {
                    aggtool::runtime::PrimitiveKind::TruncatedEllipsoid
                },
            };
            if aggtool::assembly::is_manifest(&agg) {
                if volume {
                    bail!("--volume is not supported for assemblies");
                }
                run_assembly_lod(
                    &agg,
                    &view,
                    &output,
                    exposure,
                    &settings,
                    !no_mesh,
                    level_map.as_deref(),
                )?;
            } else {
                if no_mesh || level_map.is_some() {
                    bail!("--no-mesh and --level-map are for assembly manifests (.json)");
                }
                run_lod(&agg, &view, &output, exposure, &settings)?;
            }
            Ok(())
        }
        Command::Sweep {
            asset,
            vary,
            res,
            spp,
            reference_spp,
            output,
            bake,
            strict,
        } => sweep(
            &asset,
            &vary,
            res,
            spp,
            reference_spp,
            output,
            &bake,
            strict,
        ),
        Command::Flatten { asset, output } => {
            let scene = load_scene(&asset, false)?;
            let stats = aggtool::scene::flatten::flatten(&scene, &output)?;
            for w in &stats.warnings {
                eprintln!("warning: {w}");
            }
            println!("output: {} ({} files)", output.display(), stats.files);
            Ok(())
        }
        Command::Export { asset, output } => {
            let scene = load_scene(&asset, false)?;
            let stats = aggtool::scene::export::export(&scene, &output)?;
            println!(
                "output: {} ({} meshes, {} instances, {} materials, {} textures, {} of geometry)",
                output.display(),
                stats.meshes,
                stats.instances,
                stats.materials,
                stats.textures,
                mib(stats.geometry_bytes as u64)
            );
            Ok(())
        }
    }
}

/// The block cache's statistics line of a render.
fn cache_line(skeleton_bytes: usize) -> String {
    let c = aggtool::runtime::BlockCache::global().stats();
    format!(
        "stats: cache: {} blocks loaded, {} evicted, peak {} of a {} budget (level skeletons {})",
        c.loaded,
        c.evicted,
        mib(c.peak),
        mib(c.budget),
        mib(skeleton_bytes as u64)
    )
}

fn mib(b: u64) -> String {
    format!("{:.2} MiB", b as f64 / (1024.0 * 1024.0))
}

fn parse_shard(s: &str) -> Result<aggtool::format::part::Shard, String> {
    aggtool::format::part::Shard::parse(s)
}

#[allow(clippy::too_many_arguments)]
fn convert(
    asset: &Path,
    output: Option<PathBuf>,
    shard: Option<aggtool::format::part::Shard>,
    settings: &aggtool::bake::BakeSettings,
    report: Option<&Path>,
    verbose: bool,
    strict: bool,
    progress_json: bool,
) -> Result<()> {
    settings.validate().map_err(anyhow::Error::msg)?;
    let out = output.unwrap_or_else(|| match shard {
        Some(s) => asset.with_extension(format!("{}-of-{}.aggpart", s.index, s.count)),
        None => asset.with_extension("agg"),
    });
    // Where the files go is checked before the import and the bake (minutes), not after them.
    for p in std::iter::once(out.as_path()).chain(report) {
        aggtool::util::atomic::check_destination(p)
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    let t0 = std::time::Instant::now();
    let scene = load_scene(asset, strict)?;
    let t_import = t0.elapsed().as_secs_f64();
    println!(
        "input: {}: {} (imported in {t_import:.2} s)",
        asset.display(),
        scene.summary()
    );
    let source = asset
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let bars = TerminalProgress::new();
    let json = progress_json.then(aggtool::util::JsonProgress::stderr);
    let progress = |s: &str, d: u64, n: u64| match &json {
        Some(j) => j.report(s, d, n),
        None => bars.report(s, d, n),
    };
    let r = match shard {
        None => aggtool::bake::bake_to_file(&scene, &source, settings, &out, &progress),
        Some(sh) => {
            aggtool::bake::bake_shard_to_file(&scene, &source, settings, sh, &out, &progress)
        }
    }
    .with_context(|| format!("baking {}", asset.display()))?;
    bars.finish();
    println!("output: {} ({})", out.display(), mib(r.bytes));
    for l in &r.levels {
        println!(
            "stats: level {:>4}³: {:>8} voxels ({:.3}% occupied), {:>8} faces, {:>5} samples/voxel, {:>4} ABV rays/face, {}; voxelize {:.2} s, voxels {:.2} s (cpu: statistics {:.1} s, AIV {:.1} s), faces {:.2} s; rays {} AIV + {} ABV; AIV bandwidth {}; ABV bandwidth {}",
            l.res,
            l.voxels,
            100.0 * l.occupancy,
            l.faces,
            l.samples_per_voxel,
            l.abv_rays_per_face,
            mib(l.bytes),
            l.seconds.voxelize,
            l.seconds.voxels,
            l.cpu_statistics,
            l.cpu_aiv,
            l.seconds.faces,
            l.aiv_rays,
            l.abv_rays,
            l.aiv_bandwidth_summary(),
            l.abv_bandwidth_summary()
        );
    }
    let c = &r.components;
    println!(
        "stats: bytes: keys {}, voxel records {}, lobes {}, moments {} (+ dielectric {}), AIV trees {}, faces {}, ABV trees {}",
        mib(c.keys),
        mib(c.voxels),
        mib(c.lobes),
        mib(c.moments),
        mib(c.dielectric_moments),
        mib(c.aiv_nodes),
        mib(c.faces),
        mib(c.abv_nodes)
    );
    println!(
        "stats: seconds: import {t_import:.2}, voxelize {:.2}, voxels {:.2}, faces {:.2}, write {:.2}, bake total {:.2}; {} rays ({:.2} Mrays/s); peak memory {}",
        r.seconds.voxelize,
        r.seconds.voxels,
        r.seconds.faces,
        r.seconds.write,
        r.total_seconds,
        r.rays,
        r.rays_per_second / 1e6,
        r.peak_memory.map_or("unknown".into(), mib)
    );
    let kept: Vec<&str> = r
        .effects
        .iter()
        .filter(|e| e.kept)
        .map(|e| e.name)
        .collect();
    let dropped: Vec<&str> = r
        .effects
        .iter()
        .filter(|e| !e.kept)
        .map(|e| e.name)
        .collect();
    println!(
        "stats: effects kept: {}",
        if kept.is_empty() {
            "none".into()
        } else {
            kept.join("; ")
        }
    );
    println!(
        "stats: effects dropped: {}",
        if dropped.is_empty() {
            "none".into()
        } else {
            dropped.join("; ")
        }
    );
    if verbose {
        print!("{}", aggtool::format::effects::format_effects(&r.effects));
    }
    if let Some(p) = report {
        let json = serde_json::to_string_pretty(&r)?;
        aggtool::util::atomic::write_bytes_atomic(p, json.as_bytes())
            .map_err(anyhow::Error::msg)?;
        println!("output: {}", p.display());
    }
    Ok(())
}

/// `inspect FILE.agg`: the library's summary, as JSON or as text.
fn inspect(file: &Path, json: bool) -> Result<()> {
    let summary = aggtool::inspect::inspect(file)?;
    if json {
        // Through a JSON value, whose maps keep their keys sorted: the same output as always.
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::to_value(&summary)?)?
        );
        return Ok(());
    }
    let sm = &summary;
    let s = &sm.settings.bake;
    println!(
        "{}: aggtool format {}, {} bytes, written by {}",
        file.display(),
        sm.format,
        sm.bytes,
        sm.generator
    );
    println!(
        "source: {}; bounds {:?} to {:?}; tables v{} (crc32 {:08x}{})",
        sm.source,
        sm.bounds[0],
        sm.bounds[1],
        sm.tables_version,
        sm.tables_crc32,
        if sm.same_tables() {
            ", same as this build"
        } else {
            ", NOT the tables of this build"
        }
    );
    println!(
        "settings: max-res {} min-res {} samples {} (max {}) aiv {}² × {} rays/sample ({}-weighted{}), abv {}² × {} rays/cell{}, ndf-lobes {}, moment-res {}, keep {} energy {}{}",
        s.max_res, s.min_res, s.samples, s.max_samples, s.aiv_res, s.aiv_rays,
        if sm.settings.aiv_weighting == aggtool::format::AivWeighting::ProjectedArea { "projected-area" } else { "area" },
        match s.aiv_min_rays {
            0 => ", cells pooled per voxel by cross-validation".to_string(),
            1 => String::new(),
            n => format!(", cells pooled to at least {n} rays"),
        },
        s.abv_res, s.abv_rays,
        match s.abv_full_res {
            0 => String::new(),
            n => format!(" up to {n}³ (per block of (res/{n})² cells above)"),
        } + if s.abv_windows { ", centred windows" } else { "" },
        s.ndf_lobes, s.moment_res, s.keep, s.energy,
        if s.keep_all_effects { ", keep-all-effects" } else { "" }
    );
    if sm.minor >= 4 {
        println!(
            "layout: {}{}",
            if s.lossless {
                "lossless (the 1.0–1.3 floats)"
            } else {
                "quantized (1.4)"
            },
            match s.compression {
                0 => String::new(),
                z => format!(", blocks compressed (zstd level {z}, 1.5)"),
            }
        );
    }
    println!(
        "{:>6} {:>10} {:>10} {:>7} {:>7} {:>12} {:>12} {:>6}",
        "level", "voxels", "faces", "vblocks", "fblocks", "bytes", "inflated", "ratio"
    );
    for l in &sm.levels {
        println!(
            "{:>5}³ {:>10} {:>10} {:>7} {:>7} {:>12} {:>12} {:>5.2}×",
            l.res,
            l.voxels,
            l.faces,
            l.voxel_blocks,
            l.face_blocks,
            l.bytes,
            l.inflated_bytes,
            l.compression_ratio
        );
    }
    println!("bytes per component (payloads, without FlatBuffers headers and padding):");
    println!(
        "{:>6} {:>10} {:>10} {:>10} {:>11} {:>10} {:>11} {:>9}  layout",
        "level", "records", "lobes", "moments", "AIV nodes", "faces", "ABV nodes", "other"
    );
    for l in &sm.levels {
        let c = &l.components;
        println!(
            "{:>5}³ {:>10} {:>10} {:>10} {:>11} {:>10} {:>11} {:>9}  {}",
            l.res,
            c.voxels,
            c.lobes,
            c.moments + c.dielectric_moments,
            c.aiv_nodes,
            c.faces,
            c.abv_nodes,
            c.keys + c.exposure,
            if l.quantized { "quantized" } else { "float" }
        );
    }
    println!("effects:");
    print!("{}", aggtool::format::effects::format_effects(&sm.effects));
    Ok(())
}

fn main() -> ExitCode {
    // A closed pipe (`aggtool inspect F.agg | head`) ends the process quietly, as it does
    // other Unix tools, instead of a panic in println!.
    #[cfg(unix)]
    // SAFETY: restores the default action of one signal before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    // SIGTERM and SIGINT remove the temporary files of unfinished writes, then exit 130.
    if let Err(e) = aggtool::util::atomic::clean_up_on_interrupt() {
        eprintln!("warning: cannot handle SIGTERM and SIGINT: {e}");
    }
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            // Many errors put their source in their own message ("cannot read F: {source}"):
            // a cause already said is not said again.
            let mut said = e.to_string();
            for cause in e.chain().skip(1) {
                let cause = cause.to_string();
                if !said.contains(&cause) {
                    eprintln!("  caused by: {cause}");
                }
                said.push('\n');
                said.push_str(&cause);
            }
            ExitCode::FAILURE
        }
    }
}
