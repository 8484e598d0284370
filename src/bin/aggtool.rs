//! `aggtool`: the command-line front end, thin as gltfpack's: each subcommand maps its flags
//! onto the library's settings (whose `Default`s give the flags' defaults), makes one library
//! call, and prints the report it returns ([`aggtool::report`]): as text, or under `--json` as
//! one JSON object. Errors are classified into exit statuses ([`aggtool::report::ErrorKind`]).

#[path = "aggtool/args.rs"]
mod args;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Result;
use clap::{Parser, Subcommand};

use aggtool::assembly::{self, render_file::render_file};
use aggtool::import::ImportOptions;
use aggtool::render::ImageFiles;
use aggtool::report::{ErrorKind, ErrorReport, Failure, Report, Written};
use aggtool::tables::fit::{self, BuildSettings};
use aggtool::util::Progress;
use args::{AssembleArgs, ConvertArgs, EvalArgs, GenArgs, RenderArgs, SweepArgs, ViewArgs};

const EXIT_STATUS: &str = "\
Exit status: 0 success; 2 usage error (bad flags or settings, as clap's); 3 input error (an
input missing, unreadable or invalid); 4 output error (an output could not be written); 130
interrupted (SIGINT or SIGTERM). Under --json the report, or the error as {\"error\", \"kind\",
\"causes\", \"exit_code\"}, is one JSON object on stdout.

Example:
  aggtool gen foliage -o . && aggtool convert foliage.glb && aggtool inspect foliage.agg
  aggtool render foliage.agg --auto-view -o lod.exr";

#[derive(Parser)]
#[command(
    name = "aggtool",
    version,
    about = "Appearance-preserving level of detail: aggregate scenes into voxel LoDs and render them.",
    after_help = EXIT_STATUS
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Print the report as one JSON object on stdout; errors too ({"error", "kind", ...}).
    #[arg(long, global = true)]
    json: bool,
    /// No progress bars and no informational lines (errors still print).
    #[arg(short, long, global = true)]
    quiet: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Bake an asset into an aggregate: writes ASSET's stem + .agg next to it by default.
    #[command(
        after_help = "Example:\n  aggtool convert tree.glb --preset draft -o tree.agg --report tree.json"
    )]
    Convert(ConvertArgs),
    /// Print the bake presets (`convert --preset NAME`) with every setting of each; --json
    /// prints the table the Python module's `aggtool.presets()` returns and the Blender
    /// extension's preset menu reads ({"default", "fields", "presets": [{"name", "summary",
    /// "settings"}]}).
    #[command(after_help = "Example:\n  aggtool presets --json")]
    Presets,
    /// Print what an .agg file holds: header, settings, levels (by resolution), effects kept
    /// and dropped; or, for an assembly manifest (.json): assets, instances, bytes, triangles.
    #[command(after_help = "Example:\n  aggtool inspect tree.agg --json")]
    Inspect {
        /// The aggregate (.agg) or manifest (.json).
        file: PathBuf,
    },
    /// Render an .agg aggregate, or an assembly manifest (.json), with the LoD runtime (cone
    /// tracing, Eq. 30) to EXR and PNG.
    #[command(
        after_help = "Example:\n  aggtool render tree.agg --auto-view --width 512 --height 512 --level 64 -o lod.exr"
    )]
    Render(RenderArgs),
    /// Bake every asset of an assembly manifest whose aggregate is missing or stale (a stamp
    /// NAME.agg.stamp.json beside each records its source's and settings' checksums), assets
    /// in parallel; says what it baked and what it reused. The bake settings are `convert`'s.
    #[command(after_help = "Example:\n  aggtool assemble town/city.json --preset draft")]
    Assemble(AssembleArgs),
    /// Render an asset, or an assembly manifest, with the reference path tracer (direct
    /// illumination) to EXR and PNG.
    #[command(
        after_help = "Example:\n  aggtool reference tree.glb --auto-view --save-view view.json -o ref.exr"
    )]
    Reference {
        /// The asset (.gltf, .glb or .obj), or an assembly manifest (.json): each mesh loaded
        /// once and instanced by the two-level BVH.
        asset: PathBuf,
        #[command(flatten)]
        view: ViewArgs,
        /// Treat import warnings as errors.
        #[arg(long)]
        strict: bool,
    },
    /// Compare two linear images (EXR, PFM, HDR; PNG and other 8-bit formats are refused):
    /// RMSE and relative MSE.
    #[command(after_help = "Example:\n  aggtool compare lod.exr ref.exr --diff diff.png")]
    Compare {
        /// The image compared.
        a: PathBuf,
        /// The reference.
        b: PathBuf,
        /// Write a false-colour difference image (PNG).
        #[arg(long)]
        diff: Option<PathBuf>,
    },
    /// Write a generated hard-case scene as GLB; or, with `forest`, an assembly: --species
    /// trees of --triangles each and a manifest (forest.json) placing --instances of them; or,
    /// with `city`, a manifest (city.json) laying out --instances pieces of existing kits
    /// (--kit, repeatable; default: the Kenney city kit and the Quaternius village of
    /// $AGGTOOL_ASSETS, else of ../shared/assets from the current folder) as a town, referenced
    /// by relative path, not copied.
    #[command(
        after_help = "Example:\n  aggtool gen foliage -o . --triangles 20000\n  aggtool gen city -o town --instances 64 --kit assets/kenney_city_kit"
    )]
    Gen(GenArgs),
    /// Join the part files of a sharded bake (`convert --shard I/N`) into the .agg a
    /// one-machine bake writes, byte for byte; refuses missing, duplicate or mismatched parts
    /// and then writes nothing.
    #[command(
        after_help = "Example:\n  aggtool merge --parts-of tree --shards 4 -o tree.agg --remove-parts"
    )]
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
    /// Re-spend an existing aggregate's visibility details on a size or error target without
    /// baking again (the same allocation as `convert --size-mib`): the candidates are the
    /// details the file holds, so a file baked with a target, or with `--keep 1 --energy 1`,
    /// goes to any smaller budget.
    #[command(
        after_help = "Example:\n  aggtool convert tree.glb --keep 1 --energy 1 -o tree-all.agg\n  aggtool rate tree-all.agg --size-mib 4 -o tree-4.agg"
    )]
    Rate {
        /// The aggregate (.agg).
        agg: PathBuf,
        /// The aggregate to write.
        #[arg(short, long)]
        output: PathBuf,
        /// The whole file's size in MiB (met within 3% under it).
        #[arg(long, value_name = "MIB", conflicts_with_all = ["level_mib", "error"], required_unless_present_any = ["level_mib", "error"])]
        size_mib: Option<f64>,
        /// The finest level's size in MiB.
        #[arg(long, value_name = "MIB", conflicts_with = "error")]
        level_mib: Option<f64>,
        /// The largest level error estimate (RMS visibility error weighted by radiance).
        #[arg(long, value_name = "E")]
        error: Option<f64>,
    },
    /// Write an asset as plain data for tools without a glTF/OBJ reader (the USD integration):
    /// scene.json (meshes, instances, materials), geometry.bin (positions, normals, UVs,
    /// indices) and the textures as PNG.
    #[command(after_help = "Example:\n  aggtool export tree.glb -o tree-data")]
    Export {
        /// The asset (.gltf, .glb or .obj).
        asset: PathBuf,
        /// Output folder (created if needed).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Print what an asset imports as: counts, bounds, materials, warnings.
    #[command(after_help = "Example:\n  aggtool info tree.glb --json")]
    Info {
        /// The asset (.gltf, .glb or .obj).
        asset: PathBuf,
    },
    /// Write an asset as world-space OBJ files, one per material, with materials.json
    /// (base colours) beside them: the input of the Mitsuba cross-check.
    #[command(after_help = "Example:\n  aggtool flatten tree.glb -o tree-obj")]
    Flatten {
        /// The asset (.gltf, .glb or .obj).
        asset: PathBuf,
        /// Output folder (created if needed).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Generate a built-in scene, bake it, render the LoD and the reference at equal time
    /// against a converged reference, and say where everything is.
    #[command(after_help = "Example:\n  aggtool demo -o aggtool-demo")]
    Demo {
        /// Output folder.
        #[arg(short, long, default_value = "aggtool-demo")]
        output: PathBuf,
    },
    /// Quality study (paper Table 3): our LoD against the reference and the alternatives
    /// (cube primitives, exponential volume, meshopt-simplified mesh at equal memory) on assets
    /// and generated hard cases; or, with --speed, equal-spp and equal-time figures; or, with
    /// --budget, the error budget.
    #[command(
        after_help = "Example:\n  aggtool eval gen:foliage --res 32 --spp 16 --reference-spp 256 -o eval"
    )]
    Eval(EvalArgs),
    /// What accuracy costs: bake ASSET under every preset and under the base (--preset and
    /// the bake flags) with one setting changed at a time (--vary), render each with the LoD
    /// runtime against one converged reference, and write table.md, table.json and Pareto
    /// plots of RMSE against bake seconds, MiB and render seconds. An interrupted sweep
    /// resumes: rows finished with the same settings are reused. The paper's Table 4:
    /// `--vary ndf_lobes=1,2,4 --vary keep=10%,1%`.
    #[command(
        after_help = "Example:\n  aggtool sweep tree.glb --res 64 --vary ndf_lobes=1,2,4 --vary keep=10%,1%"
    )]
    Sweep(SweepArgs),
    /// The precomputed tables M1–M5 of the factorized ABSDF.
    #[command(after_help = "Example:\n  aggtool tables check --points 16")]
    Tables {
        #[command(subcommand)]
        action: TablesAction,
    },
    /// Plot the factored ABSDF against its ground truth for a validation voxel (8×8 outgoing
    /// lat-long slices, like paper Fig. 4): ground truth | factored | difference.
    #[command(after_help = "Example:\n  aggtool absdf-plot foliage -o plots")]
    AbsdfPlot {
        /// One of: flat, curved, foliage, anisotropic, orientation-color, mixed-roughness,
        /// metal-dielectric, leaf-and-twig, or all.
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
    /// Print this command line's reference as Markdown (the book's CLI reference page).
    #[command(hide = true)]
    HelpMarkdown,
}

#[derive(Subcommand)]
enum TablesAction {
    /// Fit every table against Monte Carlo ground truth and write the table file.
    #[command(
        after_help = "Example:\n  aggtool tables build -o tables/aggtool-tables.bin --mc-samples 128"
    )]
    Build {
        /// Output file (the crate embeds tables/aggtool-tables.bin).
        #[arg(short, long, default_value = "tables/aggtool-tables.bin")]
        output: PathBuf,
        /// Monte Carlo samples per strategy per ground-truth direction (M1, M3).
        #[arg(long, default_value_t = BuildSettings::default().samples)]
        mc_samples: u32,
        /// M3 resolution per axis.
        #[arg(long, default_value_t = BuildSettings::default().m3_res)]
        m3_res: u32,
        /// M1 resolution per axis.
        #[arg(long, default_value_t = BuildSettings::default().m1_res)]
        m1_res: u32,
    },
    /// Print each table's fit error against fresh Monte Carlo ground truth.
    #[command(after_help = "Example:\n  aggtool tables check --points 16 --mc-samples 128 --json")]
    Check {
        /// Table file to check (default: the embedded one).
        #[arg(long)]
        file: Option<PathBuf>,
        /// Random parameter points per table.
        #[arg(long, default_value_t = fit::CheckSettings::default().points)]
        points: usize,
        /// Monte Carlo samples per strategy per direction.
        #[arg(long, default_value_t = fit::CheckSettings::default().samples)]
        mc_samples: u32,
    },
}

/// `absdf-plot`: each case's slices beside their ground truth and difference.
fn absdf_plot(
    case: &str,
    output: &Path,
    samples: u32,
    slice: u32,
    exposure: f32,
) -> Result<Written> {
    use aggtool::absdf::cases::{compare_case, CASES};
    use aggtool::eval::plot::plot_slices;
    use aggtool::render::compare::difference_image;
    let t = aggtool::tables::Tables::embedded();
    let names: Vec<&str> = if case == "all" {
        CASES.to_vec()
    } else {
        vec![case]
    };
    std::fs::create_dir_all(output)?;
    let mut out = Written::default();
    for name in names {
        let (Some((gt, ours)), Some((r, _))) = (
            plot_slices(name, t, samples, slice.max(4)),
            compare_case(name, t, samples, 8),
        ) else {
            return Err(aggtool::report::usage(format!(
                "unknown case '{name}'; choose one of: {}",
                CASES.join(", ")
            )));
        };
        let (diff, scale) = difference_image(&ours, &gt, None);
        let path = output.join(format!("absdf-{name}.png"));
        let tiles: [&[u8]; 3] = [
            &gt.to_srgb8(exposure),
            &ours.to_srgb8(exposure),
            &diff.to_srgb8(0.0),
        ];
        aggtool::film::side_by_side(&path, &tiles, gt.width, gt.height)?;
        out.push(&path, format!("{name}: lobes {} rmse {:.5} (ground truth rms {:.5}, relative {:.3}); difference white = {scale:.4}", r.lobes, r.rmse, r.gt_rms, r.rmse / r.gt_rms));
    }
    Ok(out)
}

/// An imported asset.
fn load(path: &Path) -> Result<aggtool::scene::Scene> {
    Ok(aggtool::import::load(path, ImportOptions::default())?)
}

/// One output and what it holds, as a report.
fn written(path: &Path, what: String) -> Box<dyn Report> {
    let mut w = Written::default();
    w.push(path, what);
    Box::new(w)
}

/// Where progress and informational lines go: bars and stdout, or nowhere under --quiet
/// (informational lines go to stderr under --json, whose stdout is the report alone).
struct Out {
    bars: Option<aggtool::util::TerminalProgress>,
    json: bool,
}

impl Out {
    fn progress(&self, stage: &str, done: u64, total: u64) {
        if let Some(b) = &self.bars {
            b.report(stage, done, total);
        }
    }

    fn note(&self, line: &str) {
        if let Some(b) = &self.bars {
            b.finish();
            if self.json {
                eprintln!("{line}")
            } else {
                println!("{line}")
            }
        }
    }
}

/// Runs one command: its settings from its flags, one library call, its report.
fn run(command: Command, out: &Out) -> Result<Box<dyn Report>> {
    use aggtool::{eval, inspect, render};
    let progress = |s: &str, d: u64, n: u64| out.progress(s, d, n);
    let notes = |l: &str| out.note(l);
    Ok(match command {
        Command::Convert(a) => {
            let json = aggtool::util::JsonProgress::stderr();
            let json_progress = |s: &str, d: u64, n: u64| json.report(s, d, n);
            let p: Progress = if a.progress_json {
                &json_progress
            } else {
                &progress
            };
            Box::new(aggtool::bake::convert::convert(&a.asset, &a.settings(), p)?)
        }
        Command::Presets => Box::new(aggtool::bake::PresetTable::new()),
        Command::Inspect { file } => Box::new(inspect::inspect_file(&file)?),
        Command::Render(a) => Box::new(render_file(&a.agg, &a.request(), &progress)?),
        Command::Assemble(a) if a.list => Box::new(assembly::bake::list(&a.manifest)?),
        Command::Assemble(a) => Box::new(assembly::bake::assemble_file(&a.manifest, &a.request())?),
        Command::Reference {
            asset,
            view,
            strict,
        } => {
            let (scene, input) = assembly::mesh::load_any(&asset, ImportOptions { strict })?;
            let v = view.request().resolve(|| Ok(scene.bounding_sphere()))?;
            let files = ImageFiles::for_output(&view.output);
            let e = view.exposure;
            let report =
                render::reference::render_to_files(&scene, input, &v, &files, e, &progress)?;
            // As `render` does (`RenderRequest::exiting`): the process ends with this render.
            std::mem::forget(scene);
            Box::new(report)
        }
        Command::Compare { a, b, diff } => {
            Box::new(render::compare::compare_files(&a, &b, diff.as_deref())?)
        }
        Command::Gen(a) => Box::new(assembly::generate::generate(&a.request())?),
        Command::Merge {
            parts,
            output,
            parts_of,
            shards,
            remove_parts,
        } => {
            use aggtool::format::part::{merge_files, PartFiles};
            let files = match (parts_of, shards) {
                (Some(prefix), Some(n)) => PartFiles::Prefix(prefix, n),
                _ => PartFiles::Listed(parts),
            };
            Box::new(merge_files(&files, &output, remove_parts)?)
        }
        Command::Rate {
            agg,
            output,
            size_mib,
            level_mib,
            error,
        } => {
            let target = aggtool::bake::BakeSettings {
                size_mib: size_mib.unwrap_or(0.0),
                level_mib: level_mib.unwrap_or(0.0),
                error: error.unwrap_or(0.0),
                ..Default::default()
            };
            Box::new(aggtool::bake::convert::rate(&agg, &target, &output)?)
        }
        Command::Export { asset, output } => {
            let stats = aggtool::scene::export::export(&load(&asset)?, &output)?;
            written(&output, stats.describe())
        }
        Command::Info { asset } => Box::new(inspect::asset_info(&asset)?),
        Command::Flatten { asset, output } => {
            let stats = aggtool::scene::flatten::flatten(&load(&asset)?, &output)?;
            for w in &stats.warnings {
                notes(&format!("warning: {w}"));
            }
            written(&output, format!("{} files", stats.files))
        }
        Command::Demo { output } => {
            let settings = eval::demo::DemoSettings::default();
            Box::new(eval::demo::demo(&output, &settings, &progress)?)
        }
        Command::Eval(a) => Box::new(eval::run::run(&a.settings()?, &progress, &notes)?),
        Command::Sweep(a) => {
            let dir = a
                .output
                .clone()
                .unwrap_or_else(|| eval::sweep::default_dir(&a.asset));
            let s = a.settings()?;
            Box::new(eval::sweep::sweep_file(
                &a.asset, &s, &dir, a.strict, &progress, &notes,
            )?)
        }
        Command::Tables { action } => match action {
            TablesAction::Build {
                output,
                mc_samples,
                m3_res,
                m1_res,
            } => {
                let settings = fit::BuildSettings {
                    samples: mc_samples,
                    m3_res,
                    m1_res,
                };
                Box::new(fit::build_file(settings, &output, &progress)?)
            }
            TablesAction::Check {
                file,
                points,
                mc_samples,
            } => {
                let settings = fit::CheckSettings {
                    points,
                    samples: mc_samples,
                };
                Box::new(fit::check_file(file.as_deref(), settings)?)
            }
        },
        Command::AbsdfPlot {
            case,
            output,
            samples,
            slice,
            exposure,
        } => Box::new(absdf_plot(&case, &output, samples, slice, exposure)?),
        Command::HelpMarkdown => Box::new(Markdown {
            markdown: reference_markdown(),
        }),
    })
}

/// The book's command-line reference: clap-markdown's page of this parser, each `Example:`
/// command line fenced as shell.
fn reference_markdown() -> String {
    let options = clap_markdown::MarkdownOptions::new()
        .title("Command-line reference".into())
        .show_footer(false);
    let mut out = String::new();
    let mut fenced = false;
    for line in clap_markdown::help_markdown_custom::<Cli>(&options).lines() {
        let example = line
            .strip_prefix("  ")
            .filter(|l| l.starts_with("aggtool "));
        if example.is_some() != fenced {
            out.push_str(if fenced { "```\n" } else { "```sh\n" });
            fenced = !fenced;
        }
        out.push_str(example.unwrap_or(line).trim_end());
        out.push('\n');
    }
    out
}

/// Text printed as it is (the CLI reference); as JSON, `{"markdown": TEXT}`.
#[derive(serde::Serialize)]
struct Markdown {
    markdown: String,
}

impl std::fmt::Display for Markdown {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.markdown.trim_end())
    }
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
    if let Err(e) = aggtool::util::clean_up_on_interrupt() {
        eprintln!("warning: cannot handle SIGTERM and SIGINT: {e}");
    }
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        // Usage errors under --json are JSON too, with clap's status (2); help and version
        // print as clap prints them.
        Err(e) if e.use_stderr() && std::env::args_os().any(|a| a == "--json") => {
            let message = e.to_string();
            let first = message.lines().next().unwrap_or_default();
            let report = ErrorReport {
                error: first.strip_prefix("error: ").unwrap_or(first).to_string(),
                kind: ErrorKind::Usage,
                causes: Vec::new(),
                exit_code: ErrorKind::Usage.exit_code(),
            };
            println!("{:#}", report.to_json());
            return ExitCode::from(report.exit_code);
        }
        Err(e) => e.exit(),
    };
    let (json, quiet) = (cli.json, cli.quiet);
    let out = Out {
        bars: (!quiet).then(aggtool::util::TerminalProgress::new),
        json,
    };
    let result = run(cli.command, &out);
    drop(out);
    match result {
        Ok(report) if json => {
            println!("{:#}", report.to_json());
            ExitCode::SUCCESS
        }
        Ok(report) => {
            let text = report.to_string();
            if !quiet && !text.is_empty() {
                println!("{}", text.trim_end());
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            let report = ErrorReport::new(&e, classify(&e));
            if json {
                println!("{:#}", report.to_json());
            } else {
                eprintln!("{report}");
            }
            ExitCode::from(report.exit_code)
        }
    }
}

/// The kind of a failure: the first cause in its chain whose kind is known (a `Failure`, or
/// a write error of the image, bake, merge or export stages, or an interrupted I/O call);
/// anything else is an input error.
fn classify(e: &anyhow::Error) -> ErrorKind {
    for cause in e.chain() {
        if let Some(k) = kind_of(cause) {
            return k;
        }
    }
    ErrorKind::Input
}

fn kind_of(cause: &(dyn std::error::Error + 'static)) -> Option<ErrorKind> {
    use aggtool::assembly::bake::AssembleError;
    use aggtool::bake::BakeError;
    use aggtool::film::ImageError;
    use aggtool::format::part::MergeError;
    use aggtool::scene::export::ExportError;
    if let Some(f) = cause.downcast_ref::<Failure>() {
        return Some(f.kind);
    }
    if let Some(io) = cause.downcast_ref::<std::io::Error>() {
        if io.kind() == std::io::ErrorKind::Interrupted {
            return Some(ErrorKind::Interrupted);
        }
    }
    match () {
        _ if matches!(cause.downcast_ref(), Some(ImageError::Write { .. })) => {
            Some(ErrorKind::Output)
        }
        _ if matches!(cause.downcast_ref(), Some(BakeError::Io { .. })) => Some(ErrorKind::Output),
        _ if matches!(cause.downcast_ref(), Some(BakeError::Settings(_))) => Some(ErrorKind::Usage),
        _ if matches!(cause.downcast_ref(), Some(AssembleError::Settings(_))) => {
            Some(ErrorKind::Usage)
        }
        _ if matches!(cause.downcast_ref(), Some(MergeError::Io { .. })) => Some(ErrorKind::Output),
        _ if matches!(cause.downcast_ref(), Some(ExportError::Write { .. })) => {
            Some(ErrorKind::Output)
        }
        _ => None,
    }
}
