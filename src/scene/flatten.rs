//! Writing a [`Scene`] out as world-space OBJ files, one per material, with `materials.json`
//! beside them: the input of the Mitsuba cross-check (`tests/python`), which loads each file as
//! a mesh with a diffuse or rough-conductor BSDF built from the factors in `materials.json`.
//!
//! Instances are flattened into world space: positions by the instance's transform, normals by
//! its inverse transpose. Textures and cut-outs are not carried (the factors only), and
//! [`flatten`] says so for each material that has them.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::export::ExportError;
use super::Scene;
use crate::util::write_bytes_atomic;

/// What [`flatten`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FlattenStats {
    /// OBJ files written (materials that some triangle uses), listed in `materials.json`.
    pub files: usize,
    /// Materials whose textures or cut-outs `materials.json` does not carry, one line each.
    pub warnings: Vec<String>,
}

/// Writes `scene` into the folder `dir` (created if needed) as `material_NNN.obj` per material
/// used (world-space `v`, `vn` when the mesh has normals, and `f` lines) and `materials.json`:
/// a list of `{file, name, base_color, metallic, specular_factor, roughness}`, roughness
/// perceptual (glTF's). Every file is written atomically.
pub fn flatten(scene: &Scene, dir: &Path) -> Result<FlattenStats, ExportError> {
    let fail = |path: PathBuf, message: String| ExportError::Write { path, message };
    std::fs::create_dir_all(dir).map_err(|e| fail(dir.to_path_buf(), e.to_string()))?;
    // Per material: its OBJ text and the vertices written so far (OBJ indices are global).
    let mut per_mat: Vec<String> = vec![String::new(); scene.materials.len()];
    let mut counts = vec![0u32; scene.materials.len()];
    for inst in &scene.instances {
        let m = &scene.meshes[inst.mesh as usize];
        let nm = glam::Mat3::from(inst.transform.matrix3)
            .inverse()
            .transpose();
        let out = &mut per_mat[m.material as usize];
        let base = counts[m.material as usize];
        for p in &m.positions {
            let w = inst.transform.transform_point3(*p);
            let _ = writeln!(out, "v {} {} {}", w.x, w.y, w.z);
        }
        let has_n = !m.normals.is_empty();
        for n in &m.normals {
            let w = (nm * *n).normalize_or_zero();
            let _ = writeln!(out, "vn {} {} {}", w.x, w.y, w.z);
        }
        for t in &m.triangles {
            let [a, b, c] = t.map(|i| i + base + 1);
            if has_n {
                let _ = writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}");
            } else {
                let _ = writeln!(out, "f {a} {b} {c}");
            }
        }
        counts[m.material as usize] += m.positions.len() as u32;
    }
    let mut list = Vec::new();
    let mut warnings = Vec::new();
    for (i, text) in per_mat.iter().enumerate() {
        if text.is_empty() {
            continue;
        }
        let file = format!("material_{i:03}.obj");
        let path = dir.join(&file);
        write_bytes_atomic(&path, text.as_bytes()).map_err(|e| fail(path.clone(), e))?;
        let mat = &scene.materials[i];
        if mat.base_color_texture.is_some() || mat.has_cutout() {
            warnings.push(format!(
                "material '{}' has textures or cut-outs; materials.json gives only its factors",
                mat.name
            ));
        }
        list.push(serde_json::json!({
            "file": file,
            "name": mat.name,
            "base_color": [mat.base_color.x, mat.base_color.y, mat.base_color.z],
            "metallic": mat.metallic,
            "specular_factor": mat.specular_factor,
            "roughness": mat.perceptual_roughness,
        }));
    }
    let path = dir.join("materials.json");
    let json =
        serde_json::to_string_pretty(&list).map_err(|e| fail(path.clone(), e.to_string()))?;
    write_bytes_atomic(&path, json.as_bytes()).map_err(|e| fail(path.clone(), e))?;
    Ok(FlattenStats {
        files: list.len(),
        warnings,
    })
}
