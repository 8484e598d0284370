//! `aggtool gen city`: a town laid out from existing asset kits (by default the Kenney city kit
//! and the Quaternius medieval village of `../shared/assets`), referenced by relative path from
//! the manifest, never copied.
//!
//! The town is a square grid of cells: every fourth row and column is a road (road tiles,
//! intersections where two cross), the other cells hold a building, a market piece or greenery
//! drawn from the kits; their aggregates go to `DIR/aggregates/` (`aggtool assemble` bakes
//! them there). Each asset is fitted to its cell by its imported bounds: scaled
//! uniformly so that its footprint spans `FILL` of the cell, stood on y = 0, centred, and
//! turned by a multiple of 90° about +Y. Everything is a function of the arguments and `seed`.

use std::path::{Component, Path, PathBuf};

use glam::{Quat, Vec3};

use crate::import::{load, ImportOptions};
use crate::math::rng::Pcg32;

/// Side of a cell (world units; the Kenney kit's tile).
pub const CELL: f32 = 1.0;
/// Fraction of a cell a building's footprint spans.
pub const FILL: f32 = 0.9;

/// What [`write()`] wrote.
#[derive(Clone, Debug)]
pub struct CityReport {
    /// The manifest (`DIR/city.json`).
    pub manifest: PathBuf,
    /// Distinct assets referenced.
    pub assets: usize,
    /// Instances placed.
    pub instances: usize,
}

/// Road tiles (straight, crossing) and the rest, by file name, among the kits' assets.
fn kind(name: &str) -> Kind {
    if name.starts_with("road-straight") {
        Kind::Road
    } else if name.starts_with("road-intersection") {
        Kind::Crossing
    } else if name.starts_with("road-") {
        Kind::Skip
    } else {
        Kind::Lot
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    Road,
    Crossing,
    Lot,
    Skip,
}

/// `to` relative to the folder `from` (both made absolute first), as a manifest writes paths.
fn relative(to: &Path, from: &Path) -> PathBuf {
    let abs = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let (to, from) = (abs(to), abs(from));
    let (a, b): (Vec<Component>, Vec<Component>) =
        (to.components().collect(), from.components().collect());
    let common = a.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut out = PathBuf::new();
    for _ in common..b.len() {
        out.push("..");
    }
    for c in &a[common..] {
        out.push(c);
    }
    out
}

/// Writes `DIR/city.json` placing `instances` assets of the `.glb`/`.gltf`/`.obj` files found
/// in `kits` (folders, not searched recursively), in file-name order.
pub fn write(
    dir: &Path,
    kits: &[PathBuf],
    instances: usize,
    seed: u64,
) -> anyhow::Result<CityReport> {
    std::fs::create_dir_all(dir)
        .map_err(|e| crate::report::output(format!("cannot create {}: {e}", dir.display())))?;
    // The kits' assets, sorted by name, with the bounds they import with.
    let mut files: Vec<PathBuf> = Vec::new();
    for k in kits {
        let rd = std::fs::read_dir(k).map_err(|e| anyhow::anyhow!("{}: {e}", k.display()))?;
        for e in rd.flatten() {
            let p = e.path();
            let ext = p
                .extension()
                .and_then(|x| x.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            if matches!(ext.as_str(), "glb" | "gltf" | "obj") {
                files.push(p);
            }
        }
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()).then(a.cmp(b)));
    struct Entry {
        id: String,
        kind: Kind,
        lo: Vec3,
        hi: Vec3,
    }
    let mut entries = Vec::new();
    let mut assets_json = serde_json::Map::new();
    for f in &files {
        let name = f
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("asset")
            .to_string();
        let k = kind(&name);
        if k == Kind::Skip {
            continue;
        }
        let scene = load(f, ImportOptions::default())
            .map_err(|e| anyhow::anyhow!("{}: {e}", f.display()))?;
        let (lo, hi) = scene.bounds();
        if !(lo.is_finite() && hi.is_finite()) || (hi - lo).max_element() <= 0.0 {
            continue;
        }
        let mut id = name.clone();
        while assets_json.contains_key(&id) {
            id.push('_');
        }
        let source = relative(f, dir);
        // Aggregates go beside the manifest (the kits' folders may be read-only).
        assets_json.insert(
            id.clone(),
            serde_json::json!({ "source": source, "aggregate": format!("aggregates/{id}.agg") }),
        );
        entries.push(Entry {
            id,
            kind: k,
            lo,
            hi,
        });
    }
    let pick = |k: Kind| -> Vec<usize> {
        (0..entries.len())
            .filter(|&i| entries[i].kind == k)
            .collect()
    };
    let (roads, crossings, lots) = (pick(Kind::Road), pick(Kind::Crossing), pick(Kind::Lot));
    if lots.is_empty() {
        anyhow::bail!("the kits hold no building or prop to place");
    }
    let side = (instances as f64).sqrt().ceil().max(1.0) as usize;
    let half = 0.5 * side as f32 * CELL;
    let mut rng = Pcg32::new(seed, 0x6369_7479);
    let mut placed = Vec::with_capacity(instances);
    for i in 0..instances {
        let (gx, gz) = (i % side, i / side);
        let (road_x, road_z) = (gx % 4 == 0, gz % 4 == 0);
        // Crossings where two roads meet (a straight tile where the kit has no crossing).
        let (list, quarter) = match (road_x, road_z) {
            (true, true) if !crossings.is_empty() => (&crossings, 0),
            (true, _) if !roads.is_empty() => (&roads, 0),
            (false, true) if !roads.is_empty() => (&roads, 1),
            _ => (&lots, (rng.next_u32() % 4) as i32),
        };
        let e = &entries[list[(rng.next_u32() as usize) % list.len()]];
        let size = e.hi - e.lo;
        let s = FILL * CELL / size.x.max(size.z).max(1e-6);
        let q = Quat::from_rotation_y(quarter as f32 * std::f32::consts::FRAC_PI_2);
        // Stand the asset on y = 0 with its footprint centred in the cell.
        let centre = 0.5 * (e.lo + e.hi);
        let local = q * (Vec3::new(-centre.x, -e.lo.y, -centre.z) * s);
        let t = Vec3::new(
            (gx as f32 + 0.5) * CELL - half,
            0.0,
            (gz as f32 + 0.5) * CELL - half,
        ) + local;
        placed.push(serde_json::json!({
            "asset": e.id,
            "translation": [t.x, t.y, t.z],
            "rotation": [q.x, q.y, q.z, q.w],
            "scale": [s, s, s],
        }));
    }
    // Only the assets placed: a small town of a large kit names a few, and `assemble` bakes
    // every asset its manifest lists.
    let used: std::collections::HashSet<&str> =
        placed.iter().filter_map(|p| p["asset"].as_str()).collect();
    let assets_json: serde_json::Map<String, serde_json::Value> = assets_json
        .into_iter()
        .filter(|(id, _)| used.contains(id.as_str()))
        .collect();
    let distinct = assets_json.len();
    let doc = serde_json::json!({ "version": 1, "assets": assets_json, "instances": placed });
    let text = serde_json::to_string_pretty(&doc)?;
    let manifest = dir.join("city.json");
    crate::util::write_atomic(&manifest, |tmp| {
        std::fs::write(tmp, text.as_bytes()).map_err(|e| e.to_string())
    })
    .map_err(|e| crate::report::output(format!("{}: {e}", manifest.display())))?;
    Ok(CityReport {
        manifest,
        assets: distinct,
        instances,
    })
}

#[cfg(test)]
mod tests {
    use super::relative;
    use std::path::Path;

    #[test]
    fn relative_paths() {
        assert_eq!(
            relative(Path::new("/a/b/c.glb"), Path::new("/a/d")),
            Path::new("../b/c.glb")
        );
        assert_eq!(
            relative(Path::new("/a/c.glb"), Path::new("/a")),
            Path::new("c.glb")
        );
    }
}
