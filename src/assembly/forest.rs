//! `aggtool gen forest`: K distinct trees from the `foliage` generator (seeds `seed + k`) and a
//! manifest placing N instances of them on a flat ground quad, deterministically.
//!
//! Trees stand on a jittered square grid of 1-unit cells (a tree is about 0.9 wide and 1.2
//! tall), each turned about +Y by a random angle and scaled by 0.8–1.2; species are drawn
//! uniformly. The ground is one more asset (`ground.glb`), a Lambertian quad under the grid.
//! Everything is a function of the arguments and `seed`: the same call writes the same bytes.

use std::path::{Path, PathBuf};

use glam::{Quat, Vec3};

use crate::gen::glb::{to_glb, MaterialData, SceneData};
use crate::gen::{generate, shapes, GenSettings};
use crate::math::rng::Pcg32;

/// What [`write()`] wrote.
#[derive(Clone, Debug)]
pub struct ForestReport {
    /// The manifest (`DIR/forest.json`).
    pub manifest: PathBuf,
    /// The trees' GLBs (`DIR/tree_KK.glb`), then the ground's.
    pub assets: Vec<PathBuf>,
    /// Triangles of one tree (the first species).
    pub tree_triangles: usize,
    /// Instances placed (trees; the ground is one more).
    pub instances: usize,
}

/// Writes `species` trees of about `triangles` triangles each, the ground, and a manifest of
/// `instances` trees into `dir` (created if needed), each file atomically.
pub fn write(
    dir: &Path,
    species: usize,
    instances: usize,
    triangles: usize,
    seed: u64,
) -> anyhow::Result<ForestReport> {
    if species == 0 {
        return Err(crate::report::usage("--species must be at least 1"));
    }
    std::fs::create_dir_all(dir)
        .map_err(|e| crate::report::output(format!("cannot create {}: {e}", dir.display())))?;
    let put = |name: &str, bytes: &[u8]| -> anyhow::Result<PathBuf> {
        let p = dir.join(name);
        crate::util::write_atomic(&p, |tmp| {
            std::fs::write(tmp, bytes).map_err(|e| e.to_string())
        })
        .map_err(|e| crate::report::output(format!("{}: {e}", p.display())))?;
        Ok(p)
    };
    let mut assets = Vec::with_capacity(species + 1);
    let mut tree_triangles = 0;
    let mut asset_json = serde_json::Map::new();
    for k in 0..species {
        let data = generate(
            "foliage",
            &GenSettings {
                triangles,
                lambertian: false,
                seed: seed.wrapping_add(k as u64),
            },
        )
        .ok_or_else(|| anyhow::anyhow!("the foliage generator is missing"))?;
        if k == 0 {
            tree_triangles = data.instanced_triangles();
        }
        let name = format!("tree_{k:02}.glb");
        assets.push(put(&name, &to_glb(&data, false))?);
        asset_json.insert(
            format!("tree_{k:02}"),
            serde_json::json!({ "source": name }),
        );
    }
    // The grid: side cells of 1 unit, centred on the origin.
    let side = (instances as f64).sqrt().ceil().max(1.0) as usize;
    let half = 0.5 * side as f32;
    let mut ground = SceneData::single(
        shapes::quad(
            Vec3::new(-half - 1.0, 0.0, half + 1.0),
            Vec3::new(2.0 * half + 2.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, -(2.0 * half + 2.0)),
            4,
        ),
        MaterialData::new("ground", [0.3, 0.25, 0.18], 0.0, 0.9),
    );
    ground.make_lambertian();
    assets.push(put("ground.glb", &to_glb(&ground, false))?);
    asset_json.insert(
        "ground".into(),
        serde_json::json!({ "source": "ground.glb" }),
    );

    // The manifest, one instance a line (a million trees is ~110 MB of text, written as it is
    // generated rather than through a JSON tree).
    use std::fmt::Write as _;
    let mut text = String::with_capacity(128 * (instances + 8));
    let assets_text = serde_json::to_string_pretty(&asset_json)?;
    let _ = write!(
        text,
        "{{\n\"version\": 1,\n\"assets\": {assets_text},\n\"instances\": [\n{{\"asset\": \"ground\"}}"
    );
    let mut rng = Pcg32::new(seed, 0x666f_7265_7374);
    for i in 0..instances {
        let (gx, gz) = ((i % side) as f32, (i / side) as f32);
        let j = rng.next_2d();
        let x = gx + 0.25 + 0.5 * j.x - half;
        let z = gz + 0.25 + 0.5 * j.y - half;
        let k = ((rng.next_f32() * species as f32) as usize).min(species - 1);
        let q = Quat::from_rotation_y(rng.next_f32() * std::f32::consts::TAU);
        let s = 0.8 + 0.4 * rng.next_f32();
        let _ = write!(
            text,
            ",\n{{\"asset\": \"tree_{k:02}\", \"translation\": [{x:.4}, 0, {z:.4}], \"rotation\": [0, {:.7}, 0, {:.7}], \"scale\": [{s:.4}, {s:.4}, {s:.4}]}}",
            q.y, q.w
        );
    }
    text.push_str("\n]\n}\n");
    let manifest = put("forest.json", text.as_bytes())?;
    Ok(ForestReport {
        manifest,
        assets,
        tree_triangles,
        instances,
    })
}
