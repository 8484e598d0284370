//! What a file holds, as one JSON value: `aggtool inspect --json` prints it, the Python
//! module's `Scene.inspect()` returns it.

use std::path::Path;

use super::effects::effect_lines;
use super::encode::Counts;
use super::Aggregate;

/// Header, provenance, bounds, tables, settings, per level its counts, blocks and bytes per
/// component (`components`, `quantized`), stored (`bytes`) and inflated (`inflated_bytes`,
/// `compression_ratio`: format 1.5's compressed blocks), and the effects kept and dropped.
pub fn summary(agg: &Aggregate, file: &Path) -> serde_json::Value {
    let h = agg.header();
    let s = agg.settings();
    let levels: Vec<(u32, Counts)> = (0..agg.level_count())
        .map(|l| (agg.grid(l).res, agg.counts(l)))
        .collect();
    let effects = effect_lines(&levels, s.keep_all_effects);
    let level_info: Vec<serde_json::Value> = (0..agg.level_count())
        .map(|l| {
            let (vb, fb) = agg.level_bytes(l);
            let (nv, nf) = agg.block_counts(l);
            let (components, quantized) = agg.component_bytes(l);
            let (stored, inflated) = agg.stored_and_inflated_bytes(l);
            serde_json::json!({
                "inflated_bytes": inflated,
                "compression_ratio": if stored > 0 { inflated as f64 / stored as f64 } else { 1.0 },
                "components": components,
                "quantized": quantized,
                "res": agg.grid(l).res,
                "voxels": levels[l].1.voxels,
                "faces": levels[l].1.faces,
                "voxel_blocks": nv,
                "face_blocks": nf,
                "bytes": vb + fb,
                "counts": levels[l].1,
            })
        })
        .collect();
    let (lo, hi) = agg.bounds();
    let (tables_version, tables_crc32) = agg.tables();
    serde_json::json!({
        "file": file.display().to_string(),
        "format": format!("{}.{}", h.major, h.minor),
        "bytes": h.file_size,
        "generator": agg.generator(),
        "source": agg.source(),
        "bounds": [lo.to_array(), hi.to_array()],
        "tables_version": tables_version,
        "tables_crc32": tables_crc32,
        "settings": s,
        "levels": level_info,
        "effects": effects,
    })
}
