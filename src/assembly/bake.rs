//! `aggtool assemble`: bake every asset whose aggregate is missing or stale.
//!
//! Staleness is decided by a stamp beside each aggregate, `NAME.agg.stamp.json`: the source's
//! length and CRC-32, and the CRC-32 of the bake settings as JSON. (The `.agg` format is being
//! changed elsewhere, so the stamp lives beside the file rather than in it; CRC-32 is a change
//! detector, not a cryptographic hash: an accidental collision has odds of 2⁻³² per edit.)
//! Only the source file itself is stamped: a `.gltf`'s external buffers and textures are not.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use super::manifest::{Asset, Manifest};
use crate::bake::{bake_to_file, BakeSettings};
use crate::import::{self, ImportOptions};

/// The stamp of one bake.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Stamp {
    /// Stamp layout version (1).
    pub version: u32,
    /// The source's length in bytes.
    pub source_bytes: u64,
    /// CRC-32 of the source's bytes.
    pub source_crc32: u32,
    /// CRC-32 of the bake settings serialised as JSON.
    pub settings_crc32: u32,
}

/// What happened to one asset.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Outcome {
    /// The asset id.
    pub asset: String,
    /// The aggregate.
    pub aggregate: PathBuf,
    /// Baked now (false: the aggregate was up to date and reused).
    pub baked: bool,
    /// Why it was baked: "missing", "no stamp", "source changed", "settings changed".
    pub reason: Option<String>,
    /// Seconds spent (import and bake).
    pub seconds: f64,
    /// Size of the aggregate.
    pub bytes: u64,
}

/// Why `assemble` failed.
#[derive(Debug, thiserror::Error)]
pub enum AssembleError {
    /// Bad settings.
    #[error("{0}")]
    Settings(String),
    /// A source is missing.
    #[error(transparent)]
    Manifest(#[from] super::ManifestError),
    /// An asset could not be read, baked or stamped.
    #[error("asset '{asset}': {message}")]
    Asset {
        /// The asset id.
        asset: String,
        /// What went wrong.
        message: String,
    },
}

/// The path of an aggregate's stamp.
pub fn stamp_path(aggregate: &Path) -> PathBuf {
    let mut s = aggregate.as_os_str().to_owned();
    s.push(".stamp.json");
    PathBuf::from(s)
}

/// The stamp the asset's aggregate should carry for `settings`.
pub fn stamp(asset: &Asset, settings: &BakeSettings) -> Result<Stamp, String> {
    let bytes = std::fs::read(&asset.source)
        .map_err(|e| format!("cannot read {}: {e}", asset.source.display()))?;
    let settings_json = serde_json::to_vec(settings).map_err(|e| e.to_string())?;
    Ok(Stamp {
        version: 1,
        source_bytes: bytes.len() as u64,
        source_crc32: crc32fast::hash(&bytes),
        settings_crc32: crc32fast::hash(&settings_json),
    })
}

/// Why the asset's aggregate must be baked, or `None` when it is up to date.
fn stale(asset: &Asset, want: &Stamp) -> Option<String> {
    if !asset.aggregate.is_file() {
        return Some("missing".into());
    }
    let have: Option<Stamp> = std::fs::read(stamp_path(&asset.aggregate))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok());
    match have {
        None => Some("no stamp".into()),
        Some(h) if h.source_bytes != want.source_bytes || h.source_crc32 != want.source_crc32 => {
            Some("source changed".into())
        }
        Some(h) if h.settings_crc32 != want.settings_crc32 || h.version != want.version => {
            Some("settings changed".into())
        }
        Some(_) => None,
    }
}

/// The assets of `m` whose aggregate [`assemble`] would bake under `settings`, as (id, why), in
/// asset order; nothing is baked (each source is read for its checksum). For refusing before
/// a bake rather than after it (`assemble --require-reuse`).
pub fn stale_assets(
    m: &Manifest,
    settings: &BakeSettings,
) -> Result<Vec<(String, String)>, AssembleError> {
    settings.validate().map_err(AssembleError::Settings)?;
    m.require_sources()?;
    m.assets
        .par_iter()
        .filter_map(|a| match stamp(a, settings) {
            Ok(want) => stale(a, &want).map(|why| Ok((a.id.clone(), why))),
            Err(message) => Some(Err(AssembleError::Asset {
                asset: a.id.clone(),
                message,
            })),
        })
        .collect()
}

/// Bakes every asset of `m` whose aggregate is missing or stale, assets in parallel;
/// `report(outcome)` hears of each as it finishes. The outcomes come back in asset order.
pub fn assemble(
    m: &Manifest,
    settings: &BakeSettings,
    options: ImportOptions,
    report: &(dyn Fn(&Outcome) + Sync),
) -> Result<Vec<Outcome>, AssembleError> {
    settings.validate().map_err(AssembleError::Settings)?;
    m.require_sources()?;
    m.assets
        .par_iter()
        .map(|a| {
            let fail = |message: String| AssembleError::Asset {
                asset: a.id.clone(),
                message,
            };
            let t0 = Instant::now();
            let want = stamp(a, settings).map_err(fail)?;
            let reason = stale(a, &want);
            if reason.is_some() {
                let scene = import::load(&a.source, options).map_err(|e| fail(e.to_string()))?;
                let source = a
                    .source
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default();
                if let Some(dir) = a.aggregate.parent().filter(|d| !d.as_os_str().is_empty()) {
                    std::fs::create_dir_all(dir)
                        .map_err(|e| fail(format!("cannot create {}: {e}", dir.display())))?;
                }
                bake_to_file(
                    &scene,
                    &source,
                    settings,
                    &a.aggregate,
                    &crate::util::no_progress,
                )
                .map_err(|e| fail(e.to_string()))?;
                let text = serde_json::to_vec_pretty(&want).map_err(|e| fail(e.to_string()))?;
                let sp = stamp_path(&a.aggregate);
                crate::util::write_atomic(&sp, |tmp| {
                    std::fs::write(tmp, &text).map_err(|e| e.to_string())
                })
                .map_err(|e| fail(format!("{}: {e}", sp.display())))?;
            }
            let out = Outcome {
                asset: a.id.clone(),
                aggregate: a.aggregate.clone(),
                baked: reason.is_some(),
                reason,
                seconds: t0.elapsed().as_secs_f64(),
                bytes: std::fs::metadata(&a.aggregate).map_or(0, |md| md.len()),
            };
            report(&out);
            Ok(out)
        })
        .collect()
}

/// Which assets of a manifest `aggtool assemble` considers, and how.
#[derive(Clone, Debug, Default)]
pub struct AssembleRequest {
    /// The bake settings of every asset.
    pub settings: BakeSettings,
    /// Only these asset ids (none: every asset).
    pub assets: Vec<String>,
    /// Only these asset numbers, 1-based, in manifest order.
    pub asset_numbers: Vec<usize>,
    /// Fail, before baking anything, if any aggregate would have to be baked.
    pub require_reuse: bool,
    /// Import warnings are errors.
    pub strict: bool,
}

/// What `aggtool assemble` reports.
#[derive(Clone, Debug, serde::Serialize)]
pub struct AssembleReport {
    /// Per asset considered, in manifest order.
    pub outcomes: Vec<Outcome>,
    /// Seconds in all.
    pub seconds: f64,
}

/// The ids of the manifest's assets, in order (`aggtool assemble --list`).
#[derive(Clone, Debug, serde::Serialize)]
pub struct AssetList {
    /// The ids.
    pub assets: Vec<String>,
}

impl std::fmt::Display for AssetList {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.assets.join("\n"))
    }
}

/// Lists the asset ids of the manifest at `path`.
pub fn list(path: &Path) -> anyhow::Result<AssetList> {
    let m = Manifest::load(path)?;
    Ok(AssetList {
        assets: m.assets.iter().map(|a| a.id.clone()).collect(),
    })
}

/// Bakes the stale assets of the manifest at `path` that `request` selects ([`assemble`]).
pub fn assemble_file(path: &Path, request: &AssembleRequest) -> anyhow::Result<AssembleReport> {
    use crate::report::usage;
    let mut m = Manifest::load(path)?;
    let mut ids = request.assets.clone();
    for &k in &request.asset_numbers {
        let a = k
            .checked_sub(1)
            .and_then(|i| m.assets.get(i))
            .ok_or_else(|| {
                usage(format!(
                    "{}: no asset number {k} (it has {}, numbered from 1)",
                    path.display(),
                    m.assets.len()
                ))
            })?;
        ids.push(a.id.clone());
    }
    if !ids.is_empty() {
        if let Some(id) = ids.iter().find(|id| !m.assets.iter().any(|a| &a.id == *id)) {
            return Err(usage(format!("{}: no asset '{id}'", path.display())));
        }
        m.assets.retain(|a| ids.contains(&a.id));
    }
    if request.require_reuse {
        // Refused before anything is baked, not after the bakes.
        let stale = stale_assets(&m, &request.settings)?;
        if !stale.is_empty() {
            let list: Vec<String> = stale
                .iter()
                .map(|(id, why)| format!("asset '{id}' ({why})"))
                .collect();
            anyhow::bail!(
                "{}: {} aggregate(s) would have had to be baked, so nothing was baked \
                 (--require-reuse: every asset's bake task should have written them): {}",
                path.display(),
                stale.len(),
                list.join(", ")
            );
        }
    }
    let t0 = Instant::now();
    let options = ImportOptions {
        strict: request.strict,
    };
    let outcomes = assemble(&m, &request.settings, options, &|_| {})?;
    Ok(AssembleReport {
        outcomes,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

impl std::fmt::Display for AssembleReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use crate::report::mib;
        for o in &self.outcomes {
            match &o.reason {
                Some(r) => writeln!(
                    f,
                    "baked: asset '{}' ({r}) -> {} ({}, {:.1} s)",
                    o.asset,
                    o.aggregate.display(),
                    mib(o.bytes),
                    o.seconds
                )?,
                None => writeln!(
                    f,
                    "reused: asset '{}': {} is up to date",
                    o.asset,
                    o.aggregate.display()
                )?,
            }
        }
        let baked = self.outcomes.iter().filter(|o| o.baked).count();
        write!(
            f,
            "stats: {} assets: {baked} baked, {} reused, {:.1} s",
            self.outcomes.len(),
            self.outcomes.len() - baked,
            self.seconds
        )
    }
}
