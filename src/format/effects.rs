//! What a bake kept and what it left out, and why, from the per-level counts: the text that
//! `aggtool convert` prints at the end and `aggtool inspect` lists.

use super::encode::Counts;

/// One effect's verdict.
#[derive(Clone, Debug, serde::Serialize)]
pub struct EffectLine {
    /// The effect's name, as `inspect` prints it.
    pub name: &'static str,
    /// Whether any voxel or face stores it.
    pub kept: bool,
    /// Why it was kept or dropped.
    pub why: String,
    /// Per level (finest first): resolution, voxels or faces storing the effect, out of.
    pub per_level: Vec<(u32, u64, u64)>,
}

/// The verdicts for a bake whose levels have these counts.
pub fn effect_lines(levels: &[(u32, Counts)], keep_all: bool) -> Vec<EffectLine> {
    type Get = fn(&Counts) -> (u64, u64);
    let table: [(&str, Get, &str, &str); 8] = [
        (
            "directional material moments (Eq. 23)",
            |c| (c.directional_moments, c.voxels),
            "the material varies inside these voxels; the others store one constant set",
            "the material is uniform inside every voxel: one constant set of moments each",
        ),
        (
            "metallic moments",
            |c| (c.metallic, c.voxels),
            "metal in these voxels; the others store the dielectric form (no metallic terms)",
            "no metal in the asset: dielectric moments only",
        ),
        (
            "roughness variance (two microfacet lobes, M2)",
            |c| (c.roughness_variance, c.voxels),
            "the roughness varies inside these voxels; the others use one lobe at the mean",
            "the roughness is uniform inside every voxel: one microfacet lobe",
        ),
        (
            "multi-lobe normal distribution (k > 1)",
            |c| (c.multi_lobe, c.voxels),
            "several normal clusters in these voxels; the others have k = 1",
            "one normal cluster per voxel: k = 1 everywhere",
        ),
        (
            "interior visibility trees (AIV)",
            |c| (c.aiv_trees, c.voxels),
            "directional interior visibility; the other voxels store a constant",
            "every voxel's interior visibility is constant: a value, no tree",
        ),
        (
            "boundary visibility trees (ABV)",
            |c| (c.abv_trees, c.faces),
            "directional boundary visibility; the other faces store a constant",
            "every boundary face's visibility is constant: a value, no tree",
        ),
        (
            "alpha cut-outs",
            |c| (c.cut_out, c.voxels),
            "partly cut-out voxels (their coverage is below one)",
            "no cut-out surface",
        ),
        (
            "exposure (correlated visibility, e.g. solids)",
            |c| (c.exposure, c.voxels),
            "visibility concentrates on some surface sides here: the incident AIV is divided by η",
            "every side of every surface sees alike (exposure 1): no correction stored",
        ),
    ];
    table
        .iter()
        .map(|(name, get, kept_why, dropped_why)| {
            let per_level: Vec<(u32, u64, u64)> = levels
                .iter()
                .map(|(res, c)| {
                    let (n, of) = get(c);
                    (*res, n, of)
                })
                .collect();
            let kept = per_level.iter().any(|l| l.1 > 0);
            let why = if kept && keep_all && name.contains("metallic") {
                "stored in full (--keep-all-effects)".to_string()
            } else if kept {
                kept_why.to_string()
            } else {
                dropped_why.to_string()
            };
            EffectLine {
                name,
                kept,
                why,
                per_level,
            }
        })
        .collect()
}

/// The lines as text, one effect per line with its per-level counts.
pub fn format_effects(lines: &[EffectLine]) -> String {
    let mut s = String::new();
    for l in lines {
        let counts: Vec<String> = l
            .per_level
            .iter()
            .map(|(r, n, of)| format!("{r}³ {n}/{of}"))
            .collect();
        s.push_str(&format!(
            "  {} {}: {}\n      {}\n",
            if l.kept { "kept   " } else { "dropped" },
            l.name,
            l.why,
            counts.join(", ")
        ));
    }
    s
}
