//! `aggtool eval`: which scenes, which study (quality, speed or error budget), and the files
//! each writes, behind one call, [`run`].

use std::fmt;
use std::path::{Path, PathBuf};

use anyhow::Result;
use serde::Serialize;

use super::budget::{budget_scene, budget_table, BudgetSettings};
use super::{
    markdown_table, object_table, speed_scene, speed_table, study_scene, summary_table, SpeedInput,
    StudySettings,
};
use crate::gen::{self, GenSettings};
use crate::report::{usage, write_output, Notes, Written};
use crate::scene::Scene;
use crate::util::Progress;

/// A scene studied: an asset file, or a generated hard case (`gen:NAME` on the command line).
#[derive(Clone, Debug, PartialEq)]
pub enum StudyScene {
    /// An asset file (.gltf, .glb, .obj).
    Asset(PathBuf),
    /// A hard case of [`gen::NAMES`].
    Generated(String),
}

impl StudyScene {
    /// `gen:NAME` as a hard case (an error for an unknown name), anything else as a file.
    pub fn parse(arg: &Path) -> Result<StudyScene> {
        match arg.to_str().and_then(|s| s.strip_prefix("gen:")) {
            Some(n) if gen::NAMES.contains(&n) => Ok(StudyScene::Generated(n.to_string())),
            Some(_) => Err(usage(format!(
                "{}: unknown hard case; choose one of: {}",
                arg.display(),
                gen::NAMES.join(", ")
            ))),
            None => Ok(StudyScene::Asset(arg.to_path_buf())),
        }
    }

    /// Every generated hard case.
    pub fn hard_cases() -> Vec<StudyScene> {
        gen::NAMES
            .iter()
            .map(|n| StudyScene::Generated(n.to_string()))
            .collect()
    }

    /// Its name in tables and file names: the hard case's, or the asset's file stem.
    pub fn name(&self) -> String {
        match self {
            StudyScene::Generated(n) => n.clone(),
            StudyScene::Asset(p) => p
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "asset".into()),
        }
    }

    fn load(&self, triangles: usize) -> Result<Scene> {
        match self {
            StudyScene::Generated(n) => gen::generate(n, &gen_settings(triangles))
                .map(|s| s.to_scene())
                .ok_or_else(|| anyhow::anyhow!("unknown scene {n}")),
            StudyScene::Asset(p) => Ok(crate::import::load(p, Default::default())?),
        }
    }

    /// The scene as a file: the asset, or the hard case written as GLB into `dir` (once).
    fn file(&self, triangles: usize, dir: &Path) -> Result<PathBuf> {
        match self {
            StudyScene::Asset(p) => Ok(p.clone()),
            StudyScene::Generated(n) => {
                let path = dir.join(format!("{n}-{triangles}.glb"));
                if !path.exists() {
                    let (p, _) = gen::write(n, &gen_settings(triangles), dir, false)
                        .map_err(crate::report::output)?;
                    std::fs::rename(&p, &path)?;
                }
                Ok(path)
            }
        }
    }
}

fn gen_settings(triangles: usize) -> GenSettings {
    GenSettings {
        triangles,
        ..GenSettings::default()
    }
}

/// Which study.
#[derive(Clone, Debug, PartialEq)]
pub enum Study {
    /// Our LoD against the reference and the alternatives (paper Table 3).
    Quality,
    /// Equal-spp time and equal-time RMSE against the reference at images of `image` pixels
    /// square, LoD by footprint, each scene baked at each of `bake_res` (none: the image's).
    Speed {
        /// Image side in pixels.
        image: u32,
        /// The bakes' finest resolutions.
        bake_res: Vec<u32>,
    },
    /// The error budget: one approximation at a time replaced by its ground truth, with
    /// `samples` oracle surface samples per voxel.
    Budget {
        /// Oracle surface samples per voxel.
        samples: u32,
        /// [`BudgetSettings::abv_parts`].
        abv_parts: Vec<u8>,
        /// [`BudgetSettings::abv_cells`].
        abv_cells: Vec<u16>,
    },
}

/// Everything `aggtool eval` needs.
#[derive(Clone, Debug)]
pub struct EvalSettings {
    /// The scenes (none: every hard case).
    pub scenes: Vec<StudyScene>,
    /// Triangles of each generated hard case.
    pub triangles: usize,
    /// The study.
    pub study: Study,
    /// LoD resolutions (quality and budget; each gives an image of res² pixels).
    pub resolutions: Vec<u32>,
    /// Samples per pixel of every method.
    pub spp: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// The LoD methods normalised as the runtime renders by default.
    pub normalize: bool,
    /// Where bakes are kept and reused as NAME-RES.agg (default: the output folder).
    pub agg_dir: Option<PathBuf>,
    /// Quality and budget: the image's side in pixels (`--image`; none: each resolution's
    /// own, one voxel a pixel).
    pub image: Option<u32>,
    /// Quality study: [`crate::runtime::TraceSettings::samples_per_walk`] of the LoD methods
    /// (0: the runtime's choice).
    pub samples_per_walk: u32,
    /// Output folder.
    pub output: PathBuf,
}

impl Default for EvalSettings {
    fn default() -> Self {
        let s = StudySettings::default();
        EvalSettings {
            scenes: Vec::new(),
            triangles: 100_000,
            study: Study::Quality,
            resolutions: s.resolutions,
            spp: s.spp,
            reference_spp: s.reference_spp,
            normalize: s.normalize,
            agg_dir: None,
            image: None,
            samples_per_walk: 0,
            output: PathBuf::from("aggtool-eval"),
        }
    }
}

/// What `aggtool eval` reports: the study's table (markdown), its figures and its files.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    /// "quality", "speed" or "budget".
    pub study: &'static str,
    /// The table, as written to the output folder's markdown file.
    pub table: String,
    /// The figures, as written to its JSON file.
    pub results: serde_json::Value,
    /// The files written.
    pub outputs: Written,
}

impl fmt::Display for EvalReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{}", self.table.trim_end())?;
        write!(f, "{}", self.outputs)
    }
}

/// Runs the study `settings` name over its scenes; `notes` hears a line per scene finished.
pub fn run(settings: &EvalSettings, progress: Progress, notes: Notes) -> Result<EvalReport> {
    let s = settings;
    if let Some(r) = s
        .resolutions
        .iter()
        .find(|r| !r.is_power_of_two() || **r < 4)
    {
        return Err(usage(format!(
            "--res {r}: each resolution must be a power of two of at least 4"
        )));
    }
    if let Some(px) = s.image.filter(|&px| px < 4) {
        return Err(usage(format!("--image {px}: at least 4 pixels")));
    }
    let out = &s.output;
    std::fs::create_dir_all(out)
        .map_err(|e| crate::report::output(format!("cannot create {}: {e}", out.display())))?;
    let scenes = if s.scenes.is_empty() {
        StudyScene::hard_cases()
    } else {
        s.scenes.clone()
    };
    let agg_dir = s.agg_dir.clone().unwrap_or_else(|| out.clone());
    let mut outputs = Written::default();
    match &s.study {
        Study::Budget {
            samples,
            abv_parts,
            abv_cells,
        } => {
            std::fs::create_dir_all(&agg_dir)?;
            let mut all = Vec::new();
            for scene in &scenes {
                let (name, loaded) = (scene.name(), scene.load(s.triangles)?);
                for &r in &s.resolutions {
                    let b = BudgetSettings {
                        res: r,
                        image: s.image,
                        spp: s.spp,
                        reference_spp: s.reference_spp,
                        samples: *samples,
                        normalize: s.normalize,
                        abv_parts: abv_parts.clone(),
                        abv_cells: abv_cells.clone(),
                        ..Default::default()
                    };
                    let agg = agg_dir.join(format!("{name}-{r}.agg"));
                    let result = budget_scene(&name, &loaded, &agg, &b, out, progress)?;
                    notes(&budget_table(std::slice::from_ref(&result)));
                    all.push(result);
                }
            }
            let table = budget_table(&all);
            write_output(&out.join("budget.md"), &table)?;
            write_output(
                &out.join("budget.json"),
                serde_json::to_string_pretty(&all)?,
            )?;
            outputs.push(&out.join("budget.md"), "the table");
            outputs.push(&out.join("budget.json"), "the figures");
            outputs.push(
                &out.join("NAME-budget-RES.png"),
                "top: reference and each row; bottom: differences on one scale",
            );
            Ok(EvalReport {
                study: "budget",
                table,
                results: crate::report::json_value(&all)?,
                outputs,
            })
        }
        Study::Speed { image, bake_res } => {
            std::fs::create_dir_all(&agg_dir)?;
            let bake_res = if bake_res.is_empty() {
                vec![(*image).max(8)]
            } else {
                bake_res.clone()
            };
            let mut rows = Vec::new();
            for scene in &scenes {
                let (name, path) = (scene.name(), scene.file(s.triangles, &agg_dir)?);
                for &br in &bake_res {
                    let agg = agg_dir.join(format!("{name}-{br}.agg"));
                    let bake = crate::bake::BakeSettings {
                        max_res: br,
                        ..Default::default()
                    };
                    let input = SpeedInput {
                        name: &name,
                        asset: &path,
                        agg: &agg,
                    };
                    let r =
                        speed_scene(&input, &bake, *image, s.spp, s.reference_spp, out, progress)?;
                    notes(&format!("{}: done", r.scene));
                    rows.push(r);
                }
            }
            let table = speed_table(&rows);
            write_output(&out.join("speed.md"), &table)?;
            write_output(
                &out.join("speed.json"),
                serde_json::to_string_pretty(&rows)?,
            )?;
            outputs.push(&out.join("speed.md"), "the table");
            outputs.push(&out.join("speed.json"), "the figures");
            outputs.push(
                &out.join("NAME-RES-speed.png"),
                "reference | LoD | reference at equal spp | reference at equal time",
            );
            Ok(EvalReport {
                study: "speed",
                table,
                results: crate::report::json_value(&rows)?,
                outputs,
            })
        }
        Study::Quality => {
            if let Some(d) = &s.agg_dir {
                std::fs::create_dir_all(d)?;
            }
            let study = StudySettings {
                resolutions: s.resolutions.clone(),
                spp: s.spp,
                reference_spp: s.reference_spp,
                agg_dir: s.agg_dir.clone(),
                normalize: s.normalize,
                image: s.image,
                samples_per_walk: s.samples_per_walk,
                ..Default::default()
            };
            let mut all = Vec::new();
            for scene in &scenes {
                let t = std::time::Instant::now();
                let (name, loaded) = (scene.name(), scene.load(s.triangles)?);
                let r = study_scene(&name, &loaded, &study, out, progress)?;
                for x in &r {
                    let line: Vec<String> = x
                        .methods
                        .iter()
                        .map(|m| format!("{} {:.4}", m.method, m.rmse))
                        .collect();
                    notes(&format!(
                        "{name} {}³ at {}²: {}",
                        x.res,
                        x.image,
                        line.join(", ")
                    ));
                }
                notes(&format!("  ({:.0} s)", t.elapsed().as_secs_f64()));
                all.extend(r);
            }
            let table = format!(
                "{}\nOn the assets' own pixels (where the mesh covers at least half a pixel):\n\n{}\nMedians:\n\n{}",
                markdown_table(&all),
                object_table(&all),
                summary_table(&all)
            );
            write_output(&out.join("table.md"), &table)?;
            write_output(&out.join("table.json"), serde_json::to_string_pretty(&all)?)?;
            outputs.push(&out.join("table.md"), "the table");
            outputs.push(&out.join("table.json"), "the figures");
            outputs.push(
                &out.join("SCENE-RES.png"),
                "top: reference, ours, cube, volume, mesh, ref@spp; bottom: their differences on one scale",
            );
            Ok(EvalReport {
                study: "quality",
                table,
                results: crate::report::json_value(&all)?,
                outputs,
            })
        }
    }
}
