//! The flags of `aggtool`'s commands and how each maps onto the library's settings; every
//! default comes from the library's `Default` impls or presets.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use aggtool::assembly::{bake::AssembleRequest, generate::GenRequest, render_file::RenderRequest};
use aggtool::bake::{convert::ConvertSettings, Preset};
use aggtool::eval::{run::EvalSettings, run::Study, run::StudyScene, sweep::SweepSettings};
use aggtool::render::ViewRequest;

/// `convert`'s flags.
#[derive(Args)]
pub struct ConvertArgs {
    /// The asset (.gltf, .glb or .obj).
    pub asset: PathBuf,
    /// Output file (default: the asset's path with the extension .agg).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub bake: BakeArgs,
    /// Write the stats as JSON to this file.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Print per-level details and every effect decision.
    #[arg(short, long)]
    pub verbose: bool,
    /// Treat import warnings as errors.
    #[arg(long)]
    pub strict: bool,
    /// Report progress on stderr as JSON lines ({"stage", "done", "total"}: at each stage's
    /// start, whole percent and end) instead of bars, for programs that run the bake.
    #[arg(long)]
    pub progress_json: bool,
    /// Bake only shard I of N (e.g. 2/8) into a part file (default: ASSET's path with
    /// .I-of-N.aggpart); `aggtool merge` joins the N parts into the bytes of the one-machine
    /// bake with the same settings. See the book's "Farm bakes".
    #[arg(long, value_parser = aggtool::format::part::Shard::parse)]
    pub shard: Option<aggtool::format::part::Shard>,
}

/// `render`'s flags.
#[derive(Args)]
pub struct RenderArgs {
    /// The aggregate (.agg), or an assembly manifest (.json; see the book's "Assemblies").
    pub agg: PathBuf,
    #[command(flatten)]
    pub view: ViewArgs,
    /// Force the level of this resolution (e.g. 64, as `inspect` lists levels) instead of
    /// choosing by the pixel footprint.
    #[arg(long, value_name = "RES")]
    pub level: Option<u32>,
    /// Light samples (and ABSDF samples) per primitive hit, combined by MIS (at least 1).
    #[arg(long, default_value_t = aggtool::runtime::TraceSettings::default().nee,
          value_parser = clap::value_parser!(u32).range(1..))]
    pub nee: u32,
    /// Use the voxel cube as the primitive (the Fig. 6 ablation).
    #[arg(long, conflicts_with = "volume")]
    pub cube: bool,
    /// Render the voxels as an exponential-transmittance volume instead (the traditional
    /// volumetric model, a baseline).
    #[arg(long)]
    pub volume: bool,
    /// Leave each cone's weights as baked instead of dividing its surfaces and background
    /// by their sum (the runtime's default; see the book's error budget).
    #[arg(long)]
    pub no_normalize: bool,
    /// Choose each cone's level by its footprint alone, ⌊log2(footprint / voxel)⌋, instead
    /// of blending the two nearest levels stochastically (continuous level of detail, the
    /// default, which keeps a moving camera from seeing levels switch).
    #[arg(long)]
    pub discrete_lod: bool,
    /// Samples of a pixel that shade from one walk of its cone (the walks stratified over
    /// the pixel and the level's blend): fewer walks, faster, a little noisier. 1 walks
    /// every sample's own cone; by default 2 where a pixel still gets 32 walks (64 spp and
    /// more), else 1; where the pixel's cone is 2 or 4 times narrower than the finest voxels
    /// (its walks meet the same voxels) 4 or 8 from 64 spp up, and below that as many as
    /// leave it 16 or 8 walks.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub samples_per_walk: Option<u32>,
    /// Level-of-detail bias in levels (as a texture's LOD bias): 1 walks the next coarser
    /// level, about twice as fast where cones cross many voxels and blurrier; negative is
    /// sharper and slower. 0 is the paper's choice by footprint.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true, value_parser = lod_bias)]
    pub lod_bias: f32,
    /// Assemblies: draw every instance from its aggregate. By default an instance seen
    /// finer than its aggregate's finest level is drawn from its mesh (imported when first
    /// needed), as a renderer does.
    #[arg(long)]
    pub no_mesh: bool,
    /// Assemblies: draw every asset of at most N triangles (counted from its source file)
    /// from its mesh at every distance: an aggregate pays where it replaces many triangles,
    /// and a small mesh is cheaper to trace, smaller and exact. 0 keeps every asset's
    /// aggregate wherever it is seen at least as coarse as its finest level.
    #[arg(long, value_name = "N", default_value_t = aggtool::assembly::render_file::DEFAULT_MESH_BELOW)]
    pub mesh_below: u64,
    /// Assemblies: also write a PNG colouring each pixel by what its first hit was drawn
    /// with (mesh, or the aggregate's level, named by its resolution), with a legend.
    #[arg(long, value_name = "PNG")]
    pub level_map: Option<PathBuf>,
    /// Memory budget of the block cache in MiB: the prepared blocks of every aggregate
    /// drawn (records, inflated bytes, ABSDFs) stay within it, the least recently used
    /// evicted. A smaller budget gives the same image, only slower. Default: a quarter of
    /// the machine's memory.
    #[arg(long, value_name = "MIB")]
    pub cache_mib: Option<u64>,
}

/// `assemble`'s flags.
#[derive(Args)]
pub struct AssembleArgs {
    /// The manifest (.json).
    pub manifest: PathBuf,
    #[command(flatten)]
    pub bake: BakeArgs,
    /// Consider only this asset (repeatable): a farm task bakes one asset of the manifest
    /// (see the book's "Farm bakes").
    #[arg(long = "asset")]
    pub assets: Vec<String>,
    /// Consider only the K-th asset of the manifest, 1-based, in the order `--list` prints
    /// (repeatable; for farm tasks over a range of numbers).
    #[arg(long = "asset-number")]
    pub asset_numbers: Vec<usize>,
    /// Print the manifest's asset ids, one a line, in order, and bake nothing.
    #[arg(long)]
    pub list: bool,
    /// Fail, before baking anything, if any aggregate would have to be baked (a farm's last
    /// step, after every asset's task, checks that they all did their part).
    #[arg(long)]
    pub require_reuse: bool,
    /// Treat import warnings as errors.
    #[arg(long)]
    pub strict: bool,
}

/// `gen`'s flags.
#[derive(Args)]
pub struct GenArgs {
    /// One of: plane45, lattice, foliage, displaced-sphere, rings, buildings, all, forest
    /// or city.
    pub name: String,
    /// Output folder.
    #[arg(short, long, default_value_os_t = GenRequest::default().output)]
    pub output: PathBuf,
    /// Approximate triangles of each generated asset (a hard case; a forest's tree).
    #[arg(long, default_value_t = GenRequest::default().settings.triangles)]
    pub triangles: usize,
    /// Make every material Lambertian (metallic 0, KHR_materials_specular factor 0).
    #[arg(long)]
    pub lambertian: bool,
    /// Store vertex data with KHR_mesh_quantization.
    #[arg(long)]
    pub quantize: bool,
    /// Random seed.
    #[arg(long, default_value_t = GenRequest::default().settings.seed)]
    pub seed: u64,
    /// forest: distinct trees.
    #[arg(long, default_value_t = GenRequest::default().species)]
    pub species: usize,
    /// forest: trees placed; city: pieces placed.
    #[arg(long, default_value_t = GenRequest::default().instances)]
    pub instances: usize,
    /// city: a folder of assets to lay out (repeatable).
    #[arg(long = "kit")]
    pub kits: Vec<PathBuf>,
}

/// `eval`'s flags.
#[derive(Args)]
pub struct EvalArgs {
    /// Assets to study (.gltf, .glb, .obj, or gen:NAME for one generated hard case); none
    /// means every generated hard case.
    pub assets: Vec<PathBuf>,
    /// Also study every generated hard case (the default when no asset is given).
    #[arg(long)]
    pub hard_cases: bool,
    /// Approximate triangles of each generated hard case.
    #[arg(long, default_value_t = EvalSettings::default().triangles)]
    pub triangles: usize,
    /// LoD resolutions (each gives an image of res² pixels).
    #[arg(long, value_delimiter = ',', default_values_t = EvalSettings::default().resolutions)]
    pub res: Vec<u32>,
    /// Quality study and budget: the image's side in pixels (default: each --res, one voxel a
    /// pixel); e.g. `--res 128 --image 256` renders the 128³ level at 256², as users render.
    #[arg(long, value_name = "PIXELS", conflicts_with = "speed")]
    pub image: Option<u32>,
    /// Quality study: samples of a pixel that shade from one walk in the LoD methods (as
    /// `render --samples-per-walk`; default: the runtime's choice).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub samples_per_walk: Option<u32>,
    /// Samples per pixel of every method.
    #[arg(long, default_value_t = EvalSettings::default().spp)]
    pub spp: u32,
    /// Samples per pixel of the reference.
    #[arg(long, default_value_t = EvalSettings::default().reference_spp)]
    pub reference_spp: u32,
    /// Speed study instead: equal-spp time and equal-time RMSE against the reference,
    /// images of this many pixels square, LoD by footprint.
    #[arg(long, value_name = "PIXELS")]
    pub speed: Option<u32>,
    /// With --speed: the bakes' finest resolutions (default: the image's).
    #[arg(long, value_delimiter = ',')]
    pub bake_res: Vec<u32>,
    /// Where bakes are kept and reused (NAME-RES.agg, RES the finest resolution; default:
    /// bake into the output folder, every time for the quality study).
    #[arg(long)]
    pub agg_dir: Option<PathBuf>,
    /// Error budget instead (issue 17): at each --res, the LoD rendered with one
    /// approximation at a time replaced by its ground truth from the mesh (coverage, AIV
    /// towards viewer and lights, ABV, ABSDF, visibility split, all); bakes are kept in
    /// --agg-dir as NAME-RES.agg and reused.
    #[arg(long, conflicts_with = "speed")]
    pub budget: bool,
    /// With --budget: oracle surface samples per voxel (at most 64).
    #[arg(long, default_value_t = aggtool::eval::budget::BudgetSettings::default().samples)]
    pub budget_samples: u32,
    /// With --budget: instead of its rows, the ABV's (baked, exact, all, all but the ABV),
    /// and for each N the ABV replaced by the share of rays in the ray's own direction from
    /// the 1/N × 1/N part of the entry face that escape the mesh (alone, and with every
    /// other term exact): what a face's spatial average costs.
    #[arg(long, requires = "budget", value_delimiter = ',', value_parser = clap::value_parser!(u8).range(1..=16))]
    pub abv_parts: Vec<u8>,
    /// With --abv-parts: rows of the ABV over the face with its rays' directions uniform over
    /// the ray's cell of an N × N concentric map (the baked map's cells) instead of its own.
    #[arg(long, requires = "abv_parts", value_delimiter = ',')]
    pub abv_cells: Vec<u16>,
    /// Quality study and budget: render the LoD methods (the budget's rows) without the
    /// per-cone normalisation (as `render --no-normalize`), to measure what it does.
    #[arg(long, conflicts_with = "speed")]
    pub no_normalize: bool,
    /// Output folder (table.md, table.json, pictures).
    #[arg(short, long, default_value_os_t = EvalSettings::default().output)]
    pub output: PathBuf,
}

/// `sweep`'s flags.
#[derive(Args)]
pub struct SweepArgs {
    /// The asset (.gltf, .glb or .obj).
    pub asset: PathBuf,
    /// A bake setting and its values, NAME=V1,V2,... (repeatable); each value is applied
    /// alone over the base. NAME is a bake setting as `inspect --json` and `convert
    /// --report` name it (ndf_lobes, keep, energy, samples, aiv_rays, ...; dashes work
    /// too); values are numbers, true/false or percentages (keep=1%).
    #[arg(long)]
    pub vary: Vec<String>,
    /// LoD resolution studied: the image is res² pixels (level chosen by footprint) and,
    /// unless --max-res is given, the bakes' finest level.
    #[arg(long, default_value_t = SweepSettings::default().res)]
    pub res: u32,
    /// Cones per pixel of the LoD renders.
    #[arg(long, default_value_t = SweepSettings::default().spp)]
    pub spp: u32,
    /// Samples per pixel of the reference (rendered once, kept in the output folder).
    #[arg(long, default_value_t = SweepSettings::default().reference_spp)]
    pub reference_spp: u32,
    /// Output folder (default: sweep-STEM beside the current folder, STEM the asset's).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub bake: BakeArgs,
    /// Treat import warnings as errors.
    #[arg(long)]
    pub strict: bool,
}
/// The bake's settings on the command line: a preset, and flags that override its values.
/// Defaults live in `aggtool::bake::BakeSettings` and its presets alone (see `--preset`).
#[derive(clap::Args, Debug, Clone)]
pub struct BakeArgs {
    /// Starting point for every setting below: draft (64³, an eighth of the samples and rays,
    /// coarser truncation), default, high (twice the samples and the AIV rays, two ABV rays
    /// per cell, centred ABV windows), max (the paper's ablation control: 4 lobes, no
    /// truncation, quantization or compression). Flags given beside it override it.
    #[arg(long, default_value = "default", value_parser = clap::builder::PossibleValuesParser::new(aggtool::bake::Preset::ALL.map(aggtool::bake::Preset::name)))]
    pub preset: String,
    /// Finest level resolution (a power of two); levels halve down to --min-res [preset
    /// default: 256; draft 64].
    #[arg(long)]
    pub max_res: Option<u32>,
    /// Coarsest level resolution [default: 4].
    #[arg(long)]
    pub min_res: Option<u32>,
    /// Surface samples per voxel at the finest level; a level of resolution r gets
    /// samples·(max_res/r)², at most --max-samples [default: 32; draft 4, high 64].
    #[arg(long)]
    pub samples: Option<u32>,
    /// Cap on the surface samples per voxel of coarser levels [default: 1024].
    #[arg(long)]
    pub max_samples: Option<u32>,
    /// Interior-visibility map resolution (Clarberg equal-area, per voxel) [default: 32;
    /// draft 16].
    #[arg(long)]
    pub aiv_res: Option<u32>,
    /// Interior-visibility rays per surface sample [default: 32; draft 4, high 64].
    #[arg(long)]
    pub aiv_rays: Option<u32>,
    /// Fewest rays an interior-visibility cell's estimate rests on (a cell pools the rays of
    /// the smallest enclosing block of cells holding that many): 0 chooses it per voxel by
    /// cross-validation, 1 is the per-cell average of earlier versions [default: 0; max 1].
    #[arg(long)]
    pub aiv_min_rays: Option<u32>,
    /// Boundary-visibility map resolution (concentric, per boundary face) [default: 64;
    /// draft 32].
    #[arg(long)]
    pub abv_res: Option<u32>,
    /// Boundary-visibility rays per direction cell [default: 1; high 2].
    #[arg(long)]
    pub abv_rays: Option<u32>,
    /// Levels finer than this share each face's boundary-visibility rays among blocks of
    /// (res / N)² direction cells, so that each finer level costs about as many ABV rays as
    /// this one; set it to --max-res for a ray per cell on every level (the paper's budget)
    /// [default: 64; draft 32].
    #[arg(long)]
    pub abv_full_res: Option<u32>,
    /// Make the finest N levels visibility levels: they keep the geometry, the material and
    /// the boundary visibility but no interior visibility of their own (no AIV rays, trees
    /// or directional moments); their voxels read the AIV of the next level that keeps one.
    /// About a third fewer bytes and less bake time a level; it costs little on foliage and
    /// thin structures and more on solids [default: 0, every level keeps its own]. Files
    /// that use it are format 1.7.
    #[arg(long, value_name = "N")]
    pub visibility_levels: Option<u32>,
    /// Let boundary-visibility cells average a window of cells centred on them, besides the
    /// enclosing blocks, where each face's held-out rays prefer it: less bias on smooth
    /// visibility, about twice the ABV's bytes [default: false; high true].
    #[arg(long, value_name = "BOOL")]
    pub abv_windows: Option<bool>,
    /// Most SGGX lobes per voxel, 1 to 4 [default: 4; draft 2].
    #[arg(long)]
    pub ndf_lobes: Option<u32>,
    /// Directional-moment grid resolution (Eq. 23) [default: 3].
    #[arg(long)]
    pub moment_res: Option<u32>,
    /// Fraction of wavelet coefficients kept per map; with --block-allocation (the default)
    /// the error that truncation gives is each block's, spent where it weighs most
    /// [default: 0.15; draft 0.1, max 1].
    #[arg(long)]
    pub keep: Option<f32>,
    /// Detail energy kept by the wavelet truncation (more coefficients kept until reached)
    /// [default: 0.98; draft 0.95, max 1].
    #[arg(long)]
    pub energy: Option<f32>,
    /// Spend each block's bytes where radiance needs them: keep the visibility details and
    /// directional moments of largest weighted energy, as the rate control does, at the
    /// estimated error that --keep and --energy give each map on its own (fewer bytes for the
    /// same error: 0.79× on the maple at 64³); false truncates each map on its own
    /// [default: true; max false].
    #[arg(long, value_name = "BOOL")]
    pub block_allocation: Option<bool>,
    /// Store every effect in full even where the asset does not need it.
    #[arg(long)]
    pub keep_all_effects: bool,
    /// Keep the Monte Carlo noise in the visibility wavelets (the paper's truncation alone;
    /// the max preset does).
    #[arg(long)]
    pub no_denoise: bool,
    /// Keep the float layout of format 1.0–1.3 (f32 Haar nodes, lobes and moments) instead
    /// of format 1.4's quantized one (about 2.3× smaller; visibility values within 0.035; the
    /// max preset does).
    #[arg(long)]
    pub lossless: bool,
    /// Zstandard level of the blocks (format 1.5; 1 to 22, 0 for none). Lossless: readers
    /// inflate a block the first time they read it. 19 gives the maple at 64³ 2.2× fewer
    /// bytes than level 0 for a few seconds of bake [default: 19; draft 3, max 0].
    #[arg(long)]
    pub compression_level: Option<i32>,
    /// Rate control: the whole file's size in MiB. The bake keeps every visibility detail
    /// that survives the noise shrinkage as a candidate and spends the budget on those that
    /// matter most to radiance (surface area × (albedo² + 1) for a voxel's interior
    /// visibility, which scales both the light it reflects and its share of a cone, the
    /// face's area for boundary visibility; one Lagrange multiplier for the file), landing
    /// within 3% under it; --keep and --energy then do nothing. Holds the bake's levels in
    /// memory until the end [default: none].
    #[arg(long, value_name = "MIB", conflicts_with_all = ["level_mib", "error"])]
    pub size_mib: Option<f64>,
    /// Rate control: the finest level's size in MiB (coarser levels get the same
    /// multiplier) [default: none].
    #[arg(long, value_name = "MIB", conflicts_with = "error")]
    pub level_mib: Option<f64>,
    /// Rate control: the largest level error estimate, the RMS visibility error weighted by
    /// what it does to radiance (0.01 to 0.05 is a useful range) [default: none].
    #[arg(long, value_name = "E")]
    pub error: Option<f64>,
}

impl BakeArgs {
    /// The preset's settings with every flag given applied over them.
    pub fn settings(&self) -> aggtool::bake::BakeSettings {
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
        set(&mut s.visibility_levels, self.visibility_levels);
        s.abv_windows = self.abv_windows.unwrap_or(s.abv_windows);
        s.block_allocation = self.block_allocation.unwrap_or(s.block_allocation);
        set(&mut s.ndf_lobes, self.ndf_lobes);
        set(&mut s.moment_res, self.moment_res);
        s.keep = self.keep.unwrap_or(s.keep);
        s.energy = self.energy.unwrap_or(s.energy);
        s.compression = self.compression_level.unwrap_or(s.compression);
        s.keep_all_effects |= self.keep_all_effects;
        s.denoise &= !self.no_denoise;
        s.lossless |= self.lossless;
        s.size_mib = self.size_mib.unwrap_or(s.size_mib);
        s.level_mib = self.level_mib.unwrap_or(s.level_mib);
        s.error = self.error.unwrap_or(s.error);
        s
    }
}

/// The view and the images of a render command (`reference`, `render`).
#[derive(Args)]
pub struct ViewArgs {
    /// View file (JSON); see the book's "View files".
    #[arg(long, conflicts_with = "auto_view")]
    pub view: Option<PathBuf>,
    /// Frame the scene's bounding sphere instead of reading a view file (`render` frames the
    /// bounds the aggregate records, so it frames an asset as `reference` frames its mesh).
    #[arg(long)]
    pub auto_view: bool,
    /// Image width for --auto-view (1 to 16384).
    #[arg(long, default_value_t = ViewRequest::default().width,
          value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: u32,
    /// Image height for --auto-view (1 to 16384).
    #[arg(long, default_value_t = ViewRequest::default().height,
          value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: u32,
    /// Samples (cones) per pixel (overrides the view file; 64 with --auto-view).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Random seed (overrides the view file).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Write the view used (useful with --auto-view) to this file.
    #[arg(long)]
    pub save_view: Option<PathBuf>,
    /// Output EXR, with a tonemapped PNG beside it (or the PNG, with the EXR beside it).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Exposure of the PNG in stops.
    #[arg(long, default_value_t = RenderRequest::default().exposure)]
    pub exposure: f32,
}

impl ViewArgs {
    /// The library's view request.
    pub fn request(&self) -> ViewRequest {
        ViewRequest {
            view: self.view.clone(),
            auto_view: self.auto_view,
            width: self.width,
            height: self.height,
            spp: self.spp,
            seed: self.seed,
            save_view: self.save_view.clone(),
        }
    }
}

/// `--lod-bias`: a finite number of levels in [-8, 8].
fn lod_bias(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(b) if b.is_finite() && (-8.0..=8.0).contains(&b) => Ok(b),
        Ok(_) => Err("a number of levels between -8 and 8".to_string()),
        Err(e) => Err(e.to_string()),
    }
}

impl RenderArgs {
    /// The library's render request.
    pub fn request(&self) -> RenderRequest {
        use aggtool::runtime::{PrimitiveKind, TraceSettings};
        let primitive = match (self.cube, self.volume) {
            (true, _) => PrimitiveKind::Cube,
            (_, true) => PrimitiveKind::Volume,
            _ => PrimitiveKind::TruncatedEllipsoid,
        };
        RenderRequest {
            view: self.view.request(),
            output: self.view.output.clone(),
            exposure: self.view.exposure,
            trace: TraceSettings {
                nee: self.nee,
                primitive,
                normalize: !self.no_normalize,
                continuous_lod: !self.discrete_lod,
                samples_per_walk: self.samples_per_walk.unwrap_or(0),
                lod_bias: self.lod_bias,
                ..TraceSettings::default()
            },
            level: self.level,
            meshes: !self.no_mesh,
            mesh_below: self.mesh_below,
            level_map: self.level_map.clone(),
            cache_mib: self.cache_mib,
            // The command ends with this render.
            exiting: true,
        }
    }
}

impl EvalArgs {
    /// The library's study settings.
    pub fn settings(&self) -> Result<EvalSettings> {
        let mut scenes = self
            .assets
            .iter()
            .map(|a| StudyScene::parse(a))
            .collect::<Result<Vec<_>>>()?;
        if self.hard_cases && !scenes.is_empty() {
            scenes.extend(StudyScene::hard_cases());
        }
        let study = match (self.speed, self.budget) {
            (Some(image), _) => Study::Speed {
                image,
                bake_res: self.bake_res.clone(),
            },
            (None, true) => Study::Budget {
                samples: self.budget_samples,
                abv_parts: self.abv_parts.clone(),
                abv_cells: self.abv_cells.clone(),
            },
            (None, false) => Study::Quality,
        };
        Ok(EvalSettings {
            scenes,
            triangles: self.triangles,
            study,
            resolutions: self.res.clone(),
            spp: self.spp,
            reference_spp: self.reference_spp,
            normalize: !self.no_normalize,
            agg_dir: self.agg_dir.clone(),
            image: self.image,
            samples_per_walk: self.samples_per_walk.unwrap_or(0),
            output: self.output.clone(),
        })
    }
}

impl SweepArgs {
    /// Each preset with the same flags, the base among them, the bakes' finest level --res
    /// unless --max-res is given.
    pub fn settings(&self) -> Result<SweepSettings> {
        use aggtool::eval::sweep::Vary;
        let res = self.res;
        if self.bake.max_res.is_none() && (!res.is_power_of_two() || res < 4) {
            return Err(aggtool::report::usage(format!("--res {res}: the bakes' finest level is --res, so it must be a power of two of at least 4 (or give --max-res)")));
        }
        let settings_of = |preset: &str| {
            let mut s = BakeArgs {
                preset: preset.to_string(),
                ..self.bake.clone()
            }
            .settings();
            s.max_res = self.bake.max_res.unwrap_or(res);
            s
        };
        let vary = self
            .vary
            .iter()
            .map(|v| Vary::parse(v))
            .collect::<Result<Vec<_>, _>>();
        Ok(SweepSettings {
            base_name: self.bake.preset.clone(),
            base: settings_of(&self.bake.preset),
            presets: Preset::ALL
                .iter()
                .map(|p| (p.name().to_string(), settings_of(p.name())))
                .collect(),
            vary: vary.map_err(aggtool::report::usage)?,
            res,
            spp: self.spp,
            reference_spp: self.reference_spp,
        })
    }
}

impl ConvertArgs {
    /// The library's conversion settings.
    pub fn settings(&self) -> ConvertSettings {
        ConvertSettings {
            bake: self.bake.settings(),
            output: self.output.clone(),
            shard: self.shard,
            report: self.report.clone(),
            strict: self.strict,
            verbose: self.verbose,
        }
    }
}

impl AssembleArgs {
    /// The library's assemble request.
    pub fn request(&self) -> AssembleRequest {
        AssembleRequest {
            settings: self.bake.settings(),
            assets: self.assets.clone(),
            asset_numbers: self.asset_numbers.clone(),
            require_reuse: self.require_reuse,
            strict: self.strict,
        }
    }
}

impl GenArgs {
    /// The library's generation request.
    pub fn request(&self) -> GenRequest {
        GenRequest {
            name: self.name.clone(),
            output: self.output.clone(),
            settings: aggtool::gen::GenSettings {
                triangles: self.triangles,
                lambertian: self.lambertian,
                seed: self.seed,
            },
            quantize: self.quantize,
            species: self.species,
            instances: self.instances,
            kits: self.kits.clone(),
        }
    }
}
