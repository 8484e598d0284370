//! `aggtool gen`: generated scenes written as files: a hard case as GLB ([`crate::gen`]), a
//! forest of generated trees with its manifest ([`super::forest`]), or a town of existing kits
//! as a manifest ([`super::city`]).

use std::path::PathBuf;

use anyhow::{bail, Result};

use crate::gen::{self, GenSettings};
use crate::report::{usage, Written};

/// What to generate.
#[derive(Clone, Debug)]
pub struct GenRequest {
    /// A hard case of [`gen::NAMES`], `all` of them, `forest` or `city`.
    pub name: String,
    /// Output folder.
    pub output: PathBuf,
    /// Triangles of each generated asset (a hard case, or one tree of a forest), lambertian
    /// materials, seed.
    pub settings: GenSettings,
    /// Store vertex data with KHR_mesh_quantization.
    pub quantize: bool,
    /// Forest: distinct trees.
    pub species: usize,
    /// Forest: trees placed; city: pieces placed.
    pub instances: usize,
    /// City: folders of assets to lay out (none: the default kits of [`default_kits`]).
    pub kits: Vec<PathBuf>,
}

impl Default for GenRequest {
    fn default() -> Self {
        GenRequest {
            name: "all".into(),
            output: PathBuf::from("."),
            settings: GenSettings::default(),
            quantize: false,
            species: 4,
            instances: 100,
            kits: Vec::new(),
        }
    }
}

/// The default kits of `gen city`: the Kenney city kit and the Quaternius village of
/// `$AGGTOOL_ASSETS`, else of `../shared/assets` from the current folder (looked for at run
/// time: a path compiled in would be the build machine's). An error when one is not a folder.
pub fn default_kits() -> Result<Vec<PathBuf>> {
    let shared = std::env::var_os("AGGTOOL_ASSETS")
        .map_or_else(|| PathBuf::from("../shared/assets"), PathBuf::from);
    let kits = vec![
        shared.join("kenney_city_kit"),
        shared.join("quaternius_medieval_village"),
    ];
    if let Some(k) = kits.iter().find(|k| !k.is_dir()) {
        bail!(
            "no --kit given, and the default kit {} is not a folder (the default kits are \
             looked for in $AGGTOOL_ASSETS, else in ../shared/assets from the current folder): \
             give --kit FOLDER (repeatable) or set AGGTOOL_ASSETS",
            k.display()
        );
    }
    Ok(kits)
}

/// Generates what `request` names into its output folder; says what was written.
pub fn generate(request: &GenRequest) -> Result<Written> {
    let r = request;
    let mut out = Written::default();
    match r.name.as_str() {
        "city" => {
            let kits = if r.kits.is_empty() {
                default_kits()?
            } else {
                r.kits.clone()
            };
            let c = super::city::write(&r.output, &kits, r.instances, r.settings.seed)?;
            let what = format!("{} pieces of {} assets", c.instances, c.assets);
            out.push(&c.manifest, what);
        }
        "forest" => {
            let f = super::forest::write(
                &r.output,
                r.species,
                r.instances,
                r.settings.triangles,
                r.settings.seed,
            )?;
            for a in &f.assets {
                out.push(a, "");
            }
            let what = format!(
                "{} trees of {} species, {} triangles each",
                f.instances, r.species, f.tree_triangles
            );
            out.push(&f.manifest, what);
        }
        name => {
            let names: Vec<&str> = if name == "all" {
                gen::NAMES.to_vec()
            } else if gen::NAMES.contains(&name) {
                vec![name]
            } else {
                return Err(usage(format!(
                    "unknown scene '{name}'; choose one of: {}, all, forest, city",
                    gen::NAMES.join(", ")
                )));
            };
            for n in names {
                let (path, tris) = gen::write(n, &r.settings, &r.output, r.quantize)
                    .map_err(crate::report::output)?;
                out.push(&path, format!("{tris} triangles"));
            }
        }
    }
    Ok(out)
}
