//! `aggtool convert`: an asset file imported and baked into an `.agg` (or, sharded, a part
//! file), with the report the command line prints. The file-level entry point over
//! [`bake_to_file`](super::bake_to_file) and [`bake_shard_to_file`](super::bake_shard_to_file).

use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;

use super::{BakeReport, BakeSettings};
use crate::format::part::Shard;
use crate::import::{self, ImportOptions};
use crate::report::{mib, usage};
use crate::util::Progress;

/// What `convert` does besides the bake's own settings.
#[derive(Clone, Debug, Default)]
pub struct ConvertSettings {
    /// The bake.
    pub bake: BakeSettings,
    /// The output (default: the asset's path with `.agg`, or `.I-of-N.aggpart` for a shard).
    pub output: Option<PathBuf>,
    /// Bake only this shard into a part file.
    pub shard: Option<Shard>,
    /// Also write the bake's report as JSON to this file.
    pub report: Option<PathBuf>,
    /// Import warnings are errors.
    pub strict: bool,
    /// The report's text lists every effect decision per level.
    pub verbose: bool,
}

impl ConvertSettings {
    /// The output path for `asset`: [`ConvertSettings::output`] or its default.
    pub fn output_for(&self, asset: &Path) -> PathBuf {
        self.output.clone().unwrap_or_else(|| match self.shard {
            Some(s) => asset.with_extension(format!("{}-of-{}.aggpart", s.index, s.count)),
            None => asset.with_extension("agg"),
        })
    }
}

/// What a conversion did: the import and the bake.
#[derive(Clone, Debug, Serialize)]
pub struct ConvertReport {
    /// The asset.
    pub input: String,
    /// What it imported as (meshes, instances, triangles, materials, textures).
    pub scene: String,
    /// Import warnings.
    pub warnings: Vec<String>,
    /// Seconds of the import.
    pub import_seconds: f64,
    /// The bake's report (output, bytes, levels, seconds, effects).
    pub bake: BakeReport,
    /// The JSON report file written, if asked for.
    pub report_file: Option<String>,
    /// Whether the text lists every effect decision.
    #[serde(skip)]
    pub verbose: bool,
}

/// Imports `asset` and bakes it as `settings` say; the destinations are checked before the
/// import and the bake (minutes), so a folder given as the output fails at once.
pub fn convert(
    asset: &Path,
    settings: &ConvertSettings,
    progress: Progress,
) -> Result<ConvertReport> {
    settings.bake.validate().map_err(usage)?;
    let out = settings.output_for(asset);
    for p in std::iter::once(out.as_path()).chain(settings.report.as_deref()) {
        crate::util::check_destination(p)
            .map_err(|e| crate::report::output(format!("cannot write {}: {e}", p.display())))?;
    }
    let t0 = Instant::now();
    let scene = import::load(
        asset,
        ImportOptions {
            strict: settings.strict,
        },
    )?;
    let import_seconds = t0.elapsed().as_secs_f64();
    let source = asset
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let bake = match settings.shard {
        None => super::bake_to_file(&scene, &source, &settings.bake, &out, progress),
        Some(sh) => super::bake_shard_to_file(&scene, &source, &settings.bake, sh, &out, progress),
    }
    .with_context(|| format!("baking {}", asset.display()))?;
    let mut report_file = None;
    if let Some(p) = &settings.report {
        let json = serde_json::to_string_pretty(&bake)?;
        crate::util::write_bytes_atomic(p, json.as_bytes()).map_err(crate::report::output)?;
        report_file = Some(p.display().to_string());
    }
    Ok(ConvertReport {
        input: asset.display().to_string(),
        scene: scene.summary(),
        warnings: scene.warnings.clone(),
        import_seconds,
        bake,
        report_file,
        verbose: settings.verbose,
    })
}

impl fmt::Display for ConvertReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for w in &self.warnings {
            writeln!(f, "warning: {w}")?;
        }
        let r = &self.bake;
        writeln!(
            f,
            "input: {}: {} (imported in {:.2} s)",
            self.input, self.scene, self.import_seconds
        )?;
        writeln!(f, "output: {} ({})", r.output, mib(r.bytes))?;
        for l in &r.levels {
            writeln!(
                f,
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
            )?;
        }
        let c = &r.components;
        writeln!(
            f,
            "stats: bytes: keys {}, voxel records {}, lobes {}, moments {} (+ dielectric {}), AIV trees {}, faces {}, ABV trees {}",
            mib(c.keys),
            mib(c.voxels),
            mib(c.lobes),
            mib(c.moments),
            mib(c.dielectric_moments),
            mib(c.aiv_nodes),
            mib(c.faces),
            mib(c.abv_nodes)
        )?;
        writeln!(
            f,
            "stats: seconds: import {:.2}, voxelize {:.2}, voxels {:.2}, faces {:.2}, write {:.2}, bake total {:.2}; {} rays ({:.2} Mrays/s); peak memory {}",
            self.import_seconds,
            r.seconds.voxelize,
            r.seconds.voxels,
            r.seconds.faces,
            r.seconds.write,
            r.total_seconds,
            r.rays,
            r.rays_per_second / 1e6,
            r.peak_memory.map_or("unknown".into(), mib)
        )?;
        let names = |kept: bool| {
            let v: Vec<&str> = r
                .effects
                .iter()
                .filter(|e| e.kept == kept)
                .map(|e| e.name)
                .collect();
            if v.is_empty() {
                "none".to_string()
            } else {
                v.join("; ")
            }
        };
        if let Some(rate) = &r.rate {
            writeln!(f, "stats: rate: {}", rate.line())?;
        }
        writeln!(f, "stats: effects kept: {}", names(true))?;
        write!(f, "stats: effects dropped: {}", names(false))?;
        if self.verbose {
            write!(
                f,
                "\n{}",
                crate::format::effects::format_effects(&r.effects).trim_end()
            )?;
        }
        if let Some(p) = &self.report_file {
            write!(f, "\noutput: {p}")?;
        }
        Ok(())
    }
}

/// What `aggtool rate` did: an existing file's visibility details re-spent on a target.
#[derive(Clone, Debug, Serialize)]
pub struct RateFileReport {
    /// The file read.
    pub input: String,
    /// Its size.
    pub input_bytes: u64,
    /// The file written.
    pub output: String,
    /// Its size.
    pub bytes: u64,
    /// What the rate control chose and met.
    pub rate: super::rate::RateReport,
}

/// Re-spends the visibility details of the `.agg` at `input` on the rate target of `target`
/// (its `size_mib`, `level_mib` or `error`; [`super::rate_file`]) into `output`, without
/// baking again.
pub fn rate(input: &Path, target: &BakeSettings, output: &Path) -> Result<RateFileReport> {
    target.validate().map_err(usage)?;
    let Some(t) = target.rate_target() else {
        return Err(usage("give the target: --size-mib, --level-mib or --error"));
    };
    crate::util::check_destination(output)
        .map_err(|e| crate::report::output(format!("cannot write {}: {e}", output.display())))?;
    let agg = crate::format::Aggregate::open(input)
        .with_context(|| format!("cannot read {}", input.display()))?;
    let (bytes, rate) = super::rate_file(&agg, t, output)?;
    Ok(RateFileReport {
        input: input.display().to_string(),
        input_bytes: agg.bytes().len() as u64,
        output: output.display().to_string(),
        bytes,
        rate,
    })
}

impl fmt::Display for RateFileReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "input: {} ({})", self.input, mib(self.input_bytes))?;
        writeln!(f, "output: {} ({})", self.output, mib(self.bytes))?;
        write!(f, "stats: rate: {}", self.rate.line())
    }
}
