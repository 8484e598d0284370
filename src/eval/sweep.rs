//! `aggtool sweep`: what accuracy costs. One asset baked under many settings: every named
//! preset, and a base preset with one setting at a time changed (`--vary NAME=V1,V2,...`);
//! per setting the bake CPU seconds, the bytes per component, the LoD render CPU seconds and the RMSE
//! against one converged reference of the same view, in `table.md`, `table.json` and three
//! Pareto plots (RMSE against bake seconds, MiB and render seconds; [`super::plot`]).
//!
//! Every row renders the same view ([`super::study_view`]: the asset framed, a sun and a blue
//! sky, `res`² pixels, level chosen by the pixel footprint), saved as `view.json`; the
//! reference (`reference-Nspp.exr`) is rendered once and reused while `view.json` is unchanged.
//!
//! **Resuming.** Each finished row is written atomically as `rows/LABEL.json` with a hash of
//! everything that decides its figures (asset, bake settings, view, spp and reference spp);
//! a later sweep into the same folder reuses a row whose file carries the same hash, so an
//! interrupted sweep continues where it stopped and a sweep with one more value bakes only
//! that one. Rows of equal settings within one sweep (a `--vary` value equal to the base) are
//! baked once.
//!
//! The paper's Table 4 ablation (lobes 1/2/4, truncation 10%/1%):
//!
//! ```sh
//! aggtool sweep chandelier-lamp.obj --res 32 --vary ndf_lobes=1,2,4 --vary keep=10%,1% -o sweep-chandelier
//! ```

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::bake::{bake_to_file, BakeSettings};
use crate::film::Image;
use crate::format::encode::ComponentBytes;
use crate::render::compare::compare;
use crate::render::reference::{self, ReferenceSettings};
use crate::render::View;
use crate::runtime::{LodScene, TraceSettings};
use crate::scene::Scene;
use crate::trace::Accel;
use crate::util::write_bytes_atomic;
use crate::util::Progress;

/// One `--vary NAME=V1,V2,...`: a [`BakeSettings`] field (as
/// [`BakeSettings::with_field`] names it) and its values, each applied alone over the base.
#[derive(Clone, Debug, PartialEq)]
pub struct Vary {
    /// The field's name (dashes as underscores).
    pub name: String,
    /// The values, each a row.
    pub values: Vec<String>,
}

impl Vary {
    /// Parses `NAME=V1,V2,...`.
    pub fn parse(s: &str) -> Result<Vary, String> {
        let (name, values) = s
            .split_once('=')
            .ok_or_else(|| format!("--vary {s}: expected NAME=V1,V2,..."))?;
        let values: Vec<String> = values
            .split(',')
            .map(|v| v.trim().to_string())
            .filter(|v| !v.is_empty())
            .collect();
        if name.trim().is_empty() || values.is_empty() {
            return Err(format!("--vary {s}: expected NAME=V1,V2,..."));
        }
        Ok(Vary {
            name: name.trim().replace('-', "_"),
            values,
        })
    }
}

/// What a sweep bakes and how it measures.
#[derive(Clone, Debug)]
pub struct SweepSettings {
    /// The base preset's name (a row of its own, and what `--vary` rows start from).
    pub base_name: String,
    /// The base settings.
    pub base: BakeSettings,
    /// The named presets, each a row (the base among them, marked).
    pub presets: Vec<(String, BakeSettings)>,
    /// Settings varied one at a time over the base.
    pub vary: Vec<Vary>,
    /// Image side in pixels (the LoD level is chosen by the pixel footprint).
    pub res: u32,
    /// Cones per pixel of the LoD renders.
    pub spp: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
}

/// What a row is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RowKind {
    /// A named preset.
    Preset,
    /// The base with one setting changed.
    Vary,
}

/// A row to bake: its label (`preset=NAME` or `NAME=VALUE`) and settings.
#[derive(Clone, Debug)]
pub struct PlannedRow {
    /// `preset=NAME` or `NAME=VALUE`.
    pub label: String,
    /// A preset or a varied setting.
    pub kind: RowKind,
    /// Whether this is the base preset's row.
    pub base: bool,
    /// The settings to bake.
    pub settings: BakeSettings,
}

/// One row's figures.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Row {
    /// `preset=NAME` or `NAME=VALUE`.
    pub label: String,
    /// A preset or a varied setting.
    pub kind: RowKind,
    /// The base preset's row.
    pub base: bool,
    /// The settings baked.
    pub settings: BakeSettings,
    /// Hash of everything that decides the figures (see the module documentation), hex.
    pub hash: String,
    /// Wall seconds of the bake (import excluded: the asset is imported once).
    pub bake_seconds: f64,
    /// CPU seconds (user + system, all threads) of the bake: the figure the table and the
    /// plots use, since wall seconds on a shared machine measure its other jobs too. Rows saved
    /// before it was recorded read 0 and fall back to the wall seconds.
    #[serde(default)]
    pub bake_cpu_seconds: f64,
    /// Rays the bake traced.
    pub bake_rays: u64,
    /// File bytes.
    pub bytes: u64,
    /// Bytes per component.
    pub components: ComponentBytes,
    /// Wall seconds of the LoD render loop (the file opened lazily just before).
    pub render_seconds: f64,
    /// CPU seconds of the LoD render, the levels' lazy preparation included (0 in rows saved
    /// before it was recorded: the wall seconds stand in).
    #[serde(default)]
    pub render_cpu_seconds: f64,
    /// Levels the render touched (resolutions).
    pub levels_used: Vec<u32>,
    /// RMSE against the reference.
    pub rmse: f64,
    /// Relative MSE against the reference.
    pub relmse: f64,
    /// Non-finite values counted in the render (zero when healthy).
    pub non_finite: u64,
    /// The LoD image (PNG), relative to the sweep folder.
    pub image: String,
    /// The aggregate, relative to the sweep folder.
    pub aggregate: String,
    /// The asset's mesh simplified by meshoptimizer to the row's file bytes and rendered by
    /// the reference at the row's spp: where the aggregate pays and where a mesh of its
    /// bytes does better. Absent in rows saved before it was recorded (computed again).
    #[serde(default)]
    pub mesh: Option<MeshPoint>,
}

/// A meshopt-simplified mesh at a row's bytes ([`Row::mesh`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MeshPoint {
    /// Geometry bytes of the simplified mesh.
    pub bytes: u64,
    /// Its triangles.
    pub triangles: usize,
    /// RMSE against the reference.
    pub rmse: f64,
    /// Relative MSE against the reference.
    pub relmse: f64,
}

impl Row {
    /// File bytes in MiB.
    pub fn mib(&self) -> f64 {
        self.bytes as f64 / (1024.0 * 1024.0)
    }

    /// The bake's cost in the table and plots: CPU seconds, or wall seconds for a row saved
    /// before CPU seconds were recorded.
    pub fn bake_cost(&self) -> f64 {
        if self.bake_cpu_seconds > 0.0 {
            self.bake_cpu_seconds
        } else {
            self.bake_seconds
        }
    }

    /// The render's cost, as [`Row::bake_cost`].
    pub fn render_cost(&self) -> f64 {
        if self.render_cpu_seconds > 0.0 {
            self.render_cpu_seconds
        } else {
            self.render_seconds
        }
    }
}

/// What happened to a row, for the caller's report.
#[derive(Clone, Debug)]
pub enum RowEvent<'a> {
    /// Baked and rendered now.
    Done(&'a Row),
    /// Taken from `rows/LABEL.json` (an earlier sweep) or from an earlier row of equal
    /// settings (`same_as`).
    Reused {
        /// The row reused.
        row: &'a Row,
        /// The label of the earlier row of equal settings, if it came from one.
        same_as: Option<&'a str>,
    },
    /// The reference was rendered (seconds) or reused (`None`).
    Reference(Option<f64>),
}

/// The whole sweep: what `table.json` holds.
#[derive(Clone, Debug, Serialize)]
pub struct SweepReport {
    /// The asset swept.
    pub asset: String,
    /// Its triangles.
    pub triangles: usize,
    /// Image side in pixels.
    pub res: u32,
    /// Cones per pixel of the LoD renders.
    pub spp: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// The base preset's name.
    pub base: String,
    /// One row per preset and varied value.
    pub rows: Vec<Row>,
    /// Files written, relative to the sweep folder: the Markdown table.
    pub table_md: String,
    /// The Pareto plots (PNG).
    pub plots: Vec<String>,
}

/// The rows a sweep bakes: every preset, then every `--vary` value over the base; an unknown
/// name or a bad value is an error naming the valid settings, before anything is baked.
pub fn plan(settings: &SweepSettings) -> Result<Vec<PlannedRow>> {
    let mut rows: Vec<PlannedRow> = settings
        .presets
        .iter()
        .map(|(name, s)| PlannedRow {
            label: format!("preset={name}"),
            kind: RowKind::Preset,
            base: *name == settings.base_name,
            settings: s.clone(),
        })
        .collect();
    if !settings
        .presets
        .iter()
        .any(|(n, _)| *n == settings.base_name)
    {
        rows.insert(
            0,
            PlannedRow {
                label: format!("preset={}", settings.base_name),
                kind: RowKind::Preset,
                base: true,
                settings: settings.base.clone(),
            },
        );
    }
    for v in &settings.vary {
        for value in &v.values {
            let s = settings
                .base
                .with_field(&v.name, value)
                .map_err(|e| anyhow::anyhow!("--vary {}: {e}", v.name))?;
            rows.push(PlannedRow {
                label: format!("{}={value}", v.name),
                kind: RowKind::Vary,
                base: false,
                settings: s,
            });
        }
    }
    let mut seen = std::collections::HashSet::new();
    rows.retain(|r| seen.insert(r.label.clone()));
    Ok(rows)
}

/// A label as a file name: characters other than letters, digits and `._=%+-` become `_`.
fn file_stem(label: &str) -> String {
    label
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "._=%+-".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Hash (CRC-32 of a JSON record, hex) of what decides a row's figures.
fn row_hash(
    asset: &str,
    asset_bytes: u64,
    settings: &BakeSettings,
    view: &View,
    s: &SweepSettings,
) -> String {
    let record = serde_json::json!({
        "asset": asset,
        "asset_bytes": asset_bytes,
        "settings": settings,
        "view": view,
        "spp": s.spp,
        "reference_spp": s.reference_spp,
    });
    format!("{:08x}", crc32fast::hash(record.to_string().as_bytes()))
}

/// Runs the sweep on the asset at `asset_path` (already imported as `scene`) into `dir`:
/// `view.json`, `reference-Nspp.exr`, `aggs/LABEL.agg`, `images/LABEL.png`, `rows/LABEL.json`,
/// `table.md`, `table.json` and the plots `pareto-bake-seconds.png`, `pareto-mib.png`,
/// `pareto-render-seconds.png`. `on_row` hears of each row as it finishes.
pub fn sweep(
    asset_path: &Path,
    scene: &Scene,
    settings: &SweepSettings,
    dir: &Path,
    progress: Progress,
    on_row: &dyn Fn(RowEvent),
) -> Result<SweepReport> {
    if settings.res < 1 || settings.spp < 1 || settings.reference_spp < 1 {
        bail!("--res, --spp and --reference-spp must be positive");
    }
    let planned = plan(settings)?;
    for d in ["rows", "aggs", "images"] {
        std::fs::create_dir_all(dir.join(d))
            .with_context(|| format!("cannot create {}", dir.join(d).display()))?;
    }
    let asset_name = asset_path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let asset_bytes = std::fs::metadata(asset_path).map(|m| m.len()).unwrap_or(0);
    // The view, and the reference, rendered once per view.
    let view = super::study_view(scene, settings.res, settings.spp);
    let view_json = serde_json::to_string_pretty(&view)?;
    let view_path = dir.join("view.json");
    let ref_path = dir.join(format!("reference-{}spp.exr", settings.reference_spp));
    let same_view = std::fs::read_to_string(&view_path).is_ok_and(|v| v == view_json);
    let truth = match (same_view, Image::read_exr(&ref_path)) {
        (true, Ok(img)) if img.width == settings.res && img.height == settings.res => {
            on_row(RowEvent::Reference(None));
            img
        }
        _ => {
            let accel = Accel::build(scene);
            let (img, stats) = reference::render(
                &accel,
                &view.camera(),
                &view.lights()?,
                ReferenceSettings {
                    spp: settings.reference_spp,
                    seed: 7,
                },
                progress,
            );
            img.write_exr(&ref_path)?;
            img.write_png(&ref_path.with_extension("png"), 0.0)?;
            write_bytes_atomic(&view_path, view_json.as_bytes()).map_err(anyhow::Error::msg)?;
            on_row(RowEvent::Reference(Some(stats.seconds)));
            img
        }
    };
    let lights = view.lights()?;
    let camera = view.camera();
    let mut rows: Vec<Row> = Vec::new();
    let mut by_hash: HashMap<String, usize> = HashMap::new();
    for p in &planned {
        let hash = row_hash(&asset_name, asset_bytes, &p.settings, &view, settings);
        let stem = file_stem(&p.label);
        let row_path = dir.join("rows").join(format!("{stem}.json"));
        let relabel = |mut r: Row| {
            r.label = p.label.clone();
            r.kind = p.kind;
            r.base = p.base;
            r
        };
        // An earlier sweep's row of the same settings.
        let saved: Option<Row> = std::fs::read(&row_path)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .filter(|r: &Row| r.hash == hash);
        if let Some(r) = saved {
            rows.push(relabel(r));
            by_hash.entry(hash).or_insert(rows.len() - 1);
            on_row(RowEvent::Reused {
                row: rows.last().expect("pushed"),
                same_as: None,
            });
            continue;
        }
        // A row of this sweep with the same settings.
        if let Some(&k) = by_hash.get(&hash) {
            let r = relabel(rows[k].clone());
            let json = serde_json::to_string_pretty(&r)?;
            write_bytes_atomic(&row_path, json.as_bytes()).map_err(anyhow::Error::msg)?;
            let other = rows[k].label.clone();
            rows.push(r);
            on_row(RowEvent::Reused {
                row: rows.last().expect("pushed"),
                same_as: Some(&other),
            });
            continue;
        }
        // Bake.
        let agg_rel = format!("aggs/{stem}.agg");
        let agg_path = dir.join(&agg_rel);
        let t = Instant::now();
        let c0 = crate::util::cpu_seconds();
        let report = bake_to_file(scene, &asset_name, &p.settings, &agg_path, progress)
            .with_context(|| format!("{}: baking {}", p.label, asset_path.display()))?;
        let bake_seconds = t.elapsed().as_secs_f64();
        let bake_cpu_seconds = crate::util::cpu_seconds() - c0;
        let c0 = crate::util::cpu_seconds();
        // Render, level by footprint.
        let lod = LodScene::open(&agg_path)
            .with_context(|| format!("cannot read {}", agg_path.display()))?;
        let (img, stats) = crate::runtime::render(
            &lod,
            &camera,
            &lights,
            settings.spp,
            1,
            &TraceSettings::default(),
            progress,
        );
        if let Some(e) = lod.first_error() {
            bail!("{}: {e}", agg_path.display());
        }
        let render_cpu_seconds = crate::util::cpu_seconds() - c0;
        let levels_used = lod.resolutions_used();
        let c = compare(&img, &truth).map_err(anyhow::Error::msg)?;
        let image_rel = format!("images/{stem}.png");
        img.write_png(&dir.join(&image_rel), 0.0)?;
        let row = Row {
            label: p.label.clone(),
            kind: p.kind,
            base: p.base,
            settings: p.settings.clone(),
            hash: hash.clone(),
            bake_seconds,
            bake_cpu_seconds,
            bake_rays: report.rays,
            bytes: report.bytes,
            components: report.components,
            render_seconds: stats.seconds,
            render_cpu_seconds,
            levels_used,
            rmse: c.rmse,
            relmse: c.relmse,
            non_finite: stats.non_finite,
            image: image_rel,
            aggregate: agg_rel,
            mesh: None,
        };
        let json = serde_json::to_string_pretty(&row)?;
        write_bytes_atomic(&row_path, json.as_bytes()).map_err(anyhow::Error::msg)?;
        rows.push(row);
        by_hash.insert(hash, rows.len() - 1);
        on_row(RowEvent::Done(rows.last().expect("pushed")));
    }
    // The mesh at each row's bytes (simplified once per distinct byte count).
    let mut meshes: HashMap<u64, MeshPoint> = HashMap::new();
    for (i, r) in rows.iter_mut().enumerate() {
        if r.mesh.is_none() {
            let m = match meshes.get(&r.bytes) {
                Some(m) => m.clone(),
                None => {
                    let simp = super::simplify::simplify_to_budget(scene, r.bytes as usize);
                    let accel = Accel::build(&simp.scene);
                    let (img, _) = reference::render(
                        &accel,
                        &camera,
                        &lights,
                        ReferenceSettings {
                            spp: settings.spp,
                            seed: 1,
                        },
                        progress,
                    );
                    let c = compare(&img, &truth).map_err(anyhow::Error::msg)?;
                    MeshPoint {
                        bytes: simp.bytes_after as u64,
                        triangles: simp.triangles_after,
                        rmse: c.rmse,
                        relmse: c.relmse,
                    }
                }
            };
            meshes.insert(r.bytes, m.clone());
            r.mesh = Some(m);
            let stem = file_stem(&planned[i].label);
            let json = serde_json::to_string_pretty(&*r)?;
            write_bytes_atomic(
                &dir.join("rows").join(format!("{stem}.json")),
                json.as_bytes(),
            )
            .map_err(anyhow::Error::msg)?;
        }
    }
    // Tables and plots.
    let md = markdown_table(&asset_name, settings, &rows);
    write_bytes_atomic(&dir.join("table.md"), md.as_bytes()).map_err(anyhow::Error::msg)?;
    let mut plots = Vec::new();
    type Cost = fn(&Row) -> f64;
    let axes: [(&str, &str, Cost); 3] = [
        (
            "pareto-bake-seconds.png",
            "bake CPU seconds",
            Row::bake_cost,
        ),
        ("pareto-mib.png", "file MiB", |r| r.mib()),
        (
            "pareto-render-seconds.png",
            "render CPU seconds",
            Row::render_cost,
        ),
    ];
    for (file, x_label, cost) in axes {
        let mut points: Vec<super::plot::Point> = rows
            .iter()
            .map(|r| super::plot::Point {
                x: cost(r),
                y: r.rmse,
                label: r
                    .label
                    .strip_prefix("preset=")
                    .unwrap_or(&r.label)
                    .to_string(),
                marked: r.kind == RowKind::Preset,
                other: false,
            })
            .collect();
        if file == "pareto-mib.png" {
            // The meshes of equal bytes on the same axes.
            let mut seen = std::collections::HashSet::new();
            for m in rows.iter().filter_map(|r| r.mesh.as_ref()) {
                if seen.insert(m.bytes) {
                    points.push(super::plot::Point {
                        x: m.bytes as f64 / (1024.0 * 1024.0),
                        y: m.rmse,
                        label: format!("mesh {} tris", m.triangles),
                        marked: false,
                        other: true,
                    });
                }
            }
        }
        let title = format!(
            "{asset_name}: rmse against {x_label} ({}² px, {} spp, reference {} spp)",
            settings.res, settings.spp, settings.reference_spp
        );
        super::plot::pareto_plot(&dir.join(file), &title, x_label, "rmse", &points)?;
        plots.push(file.to_string());
    }
    let report = SweepReport {
        asset: asset_path.display().to_string(),
        triangles: scene.instanced_triangle_count(),
        res: settings.res,
        spp: settings.spp,
        reference_spp: settings.reference_spp,
        base: settings.base_name.clone(),
        rows,
        table_md: "table.md".into(),
        plots,
    };
    let json = serde_json::to_string_pretty(&report)?;
    write_bytes_atomic(&dir.join("table.json"), json.as_bytes()).map_err(anyhow::Error::msg)?;
    Ok(report)
}

/// The sweep's Markdown table: one row per setting, the Pareto-optimal rows (no other row has
/// lower or equal RMSE at lower or equal cost, one strictly) marked per cost.
pub fn markdown_table(asset: &str, settings: &SweepSettings, rows: &[Row]) -> String {
    let front = |cost: fn(&Row) -> f64| -> Vec<bool> {
        super::plot::pareto_front(&rows.iter().map(|r| (cost(r), r.rmse)).collect::<Vec<_>>())
    };
    let (fb, fm, fr) = (
        front(Row::bake_cost),
        front(|r| r.mib()),
        front(Row::render_cost),
    );
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    let mut s = format!(
        "Sweep of {asset}: {}² pixels, {} spp, against a {}-spp reference; `*` marks the rows on the Pareto front of RMSE against that cost.\n\n",
        settings.res, settings.spp, settings.reference_spp
    );
    s += "| setting | RMSE | relMSE | bake CPU s | MiB | render CPU s | records | lobes | moments | AIV | faces | ABV | levels used | mesh of equal bytes: RMSE (triangles) |\n";
    s += "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    for (i, r) in rows.iter().enumerate() {
        let star = |f: &[bool]| if f[i] { "*" } else { "" };
        let c = &r.components;
        s += &format!(
            "| {}{} | {:.5} | {:.5} | {:.2}{} | {:.3}{} | {:.3}{} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:?} | {} |\n",
            r.label,
            if r.base { " (base)" } else { "" },
            r.rmse,
            r.relmse,
            r.bake_cost(),
            star(&fb),
            r.mib(),
            star(&fm),
            r.render_cost(),
            star(&fr),
            mib(c.voxels + c.keys + c.exposure),
            mib(c.lobes),
            mib(c.moments + c.dielectric_moments),
            mib(c.aiv_nodes),
            mib(c.faces),
            mib(c.abv_nodes),
            r.levels_used,
            r.mesh.as_ref().map_or("".into(), |m| format!(
                "{:.5}{} ({})",
                m.rmse,
                if m.rmse < r.rmse { " (mesh wins)" } else { "" },
                m.triangles
            ))
        );
    }
    s += "\nThe last column: the asset's mesh simplified by meshoptimizer to the row's file bytes (geometry only) and rendered by the reference at the same spp.\n";
    s += "\nSeconds are CPU seconds (user + system, all threads; the render's include the levels' lazy preparation). Components in MiB (payloads): records include keys and exposure; moments include the dielectric ones.\n";
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vary_parses_and_plan_refuses_unknown_names() {
        let v = Vary::parse("ndf-lobes=1, 2,4").unwrap();
        assert_eq!((v.name.as_str(), v.values.len()), ("ndf_lobes", 3));
        assert!(Vary::parse("ndf_lobes").is_err());
        assert!(Vary::parse("ndf_lobes=").is_err());
        let base = BakeSettings::default();
        let mut s = SweepSettings {
            base_name: "default".into(),
            base: base.clone(),
            presets: vec![("default".into(), base.clone())],
            vary: vec![v, Vary::parse("keep=10%,1%").unwrap()],
            res: 8,
            spp: 1,
            reference_spp: 1,
        };
        let rows = plan(&s).unwrap();
        let labels: Vec<&str> = rows.iter().map(|r| r.label.as_str()).collect();
        assert_eq!(
            labels,
            [
                "preset=default",
                "ndf_lobes=1",
                "ndf_lobes=2",
                "ndf_lobes=4",
                "keep=10%",
                "keep=1%"
            ]
        );
        assert!(rows[0].base && rows[5].settings.keep == 0.01);
        s.vary.push(Vary::parse("lobes=2").unwrap());
        let e = plan(&s).unwrap_err().to_string();
        assert!(e.contains("lobes") && e.contains("ndf_lobes"), "{e}");
        assert_eq!(file_stem("a/b=1 2"), "a_b=1_2");
    }
}

impl std::fmt::Display for RowEvent<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RowEvent::Reference(Some(secs)) => write!(f, "reference: rendered in {secs:.1} s"),
            RowEvent::Reference(None) => write!(f, "reused: reference"),
            RowEvent::Done(r) => write!(
                f,
                "baked: {}: bake {:.2} s ({:.1} CPU s), {}, render {:.2} s ({:.2} CPU s), RMSE {:.5}",
                r.label,
                r.bake_seconds,
                r.bake_cpu_seconds,
                crate::report::mib(r.bytes),
                r.render_seconds,
                r.render_cpu_seconds,
                r.rmse
            ),
            RowEvent::Reused { row, same_as } => match same_as {
                Some(o) => write!(f, "reused: {} (same settings as {o})", row.label),
                None => write!(f, "reused: {} (finished earlier)", row.label),
            },
        }
    }
}

/// What `aggtool sweep` reports: the sweep's [`SweepReport`], its folder and its table.
#[derive(Clone, Debug, Serialize)]
pub struct SweepRun {
    /// The sweep folder.
    pub output: String,
    /// The table (`table.md`).
    pub table: String,
    /// The figures (`table.json`).
    pub report: SweepReport,
}

impl std::fmt::Display for SweepRun {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "{}", self.table.trim_end())?;
        write!(
            f,
            "output: {} (table.md, table.json, {})",
            self.output,
            self.report.plots.join(", ")
        )
    }
}

/// The sweep folder by default: `sweep-STEM`, STEM the asset's.
pub fn default_dir(asset: &Path) -> std::path::PathBuf {
    let stem = asset.file_stem().unwrap_or_default().to_string_lossy();
    std::path::PathBuf::from(format!("sweep-{stem}"))
}

/// Imports `asset` and runs [`sweep`] into `dir`; bad `--vary` names and values are refused
/// before anything is imported; `notes` hears a line per row.
pub fn sweep_file(
    asset: &Path,
    settings: &SweepSettings,
    dir: &Path,
    strict: bool,
    progress: Progress,
    notes: crate::report::Notes,
) -> Result<SweepRun> {
    let planned = plan(settings).map_err(|e| crate::report::usage(format!("{e:#}")))?;
    let scene = crate::import::load(asset, crate::import::ImportOptions { strict })?;
    for w in &scene.warnings {
        notes(&format!("warning: {w}"));
    }
    notes(&format!(
        "input: {}: {}; {} settings, {}² pixels, {} spp, reference {} spp",
        asset.display(),
        scene.summary(),
        planned.len(),
        settings.res,
        settings.spp,
        settings.reference_spp
    ));
    let report = sweep(asset, &scene, settings, dir, progress, &|e| {
        notes(&e.to_string())
    })?;
    let table = std::fs::read_to_string(dir.join(&report.table_md))?;
    Ok(SweepRun {
        output: dir.display().to_string(),
        table,
        report,
    })
}

impl Default for SweepSettings {
    /// The default preset as base, every preset a row, nothing varied, 64² pixels at 64
    /// cones per pixel against a 1024-spp reference.
    fn default() -> Self {
        use crate::bake::Preset;
        SweepSettings {
            base_name: Preset::Default.name().to_string(),
            base: BakeSettings::default(),
            presets: Preset::ALL
                .iter()
                .map(|p| (p.name().to_string(), BakeSettings::preset(*p)))
                .collect(),
            vary: Vec::new(),
            res: 64,
            spp: 64,
            reference_spp: 1024,
        }
    }
}
