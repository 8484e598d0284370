//! Writing a [`Scene`] out as plain data that tools without a glTF or OBJ reader can load: the
//! input of the USD integration (`integrations/usd`), since usd-core reads neither format.
//!
//! [`export`] writes three kinds of file into one folder:
//!
//! - `geometry.bin`: every mesh's arrays, little-endian, 4-byte aligned: positions (3 × f32 per
//!   vertex), normals (3 × f32, optional), texture coordinates (2 × f32, optional, glTF's
//!   convention: v = 0 at the image's top row) and triangle indices (3 × u32 per triangle);
//! - `texture_NNN_ROLE.png`: each texture a material uses, as RGBA8: `basecolor` textures
//!   sRGB-encoded (the inverse of the importer's decoding), `data` textures (metallic-roughness,
//!   specular) with their linear values;
//! - `scene.json`, written last: the index of both. Meshes in object space with views
//!   (`{"offset": bytes, "count": elements}`) into `geometry.bin`; instances as column-major
//!   object-to-world 4×4 matrices (glTF's layout); materials with their factors and texture
//!   references (file and the column-major 3×3 KHR_texture_transform of the UVs).
//!
//! Every file is written to a temporary name and renamed into place, so a failed export leaves
//! no partial file behind.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use super::{AlphaMode, Scene, TextureRef};
use crate::math::color::linear_to_srgb;
use crate::util::write_atomic;

/// Version of the `scene.json` layout written by [`export`].
pub const EXPORT_VERSION: u32 = 1;

/// Why an export failed.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The file could not be written.
    #[error("cannot write {path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// Nothing to export.
    #[error("the scene has no triangles to export")]
    Empty,
}

/// What [`export`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExportStats {
    /// Meshes written (each once, however many instances place it).
    pub meshes: usize,
    /// Instances written.
    pub instances: usize,
    /// Materials written.
    pub materials: usize,
    /// Texture files written.
    pub textures: usize,
    /// Size of `geometry.bin` in bytes.
    pub geometry_bytes: usize,
}

impl ExportStats {
    /// What was written, in one phrase ("3 meshes, 4 instances, …").
    pub fn describe(&self) -> String {
        format!(
            "{} meshes, {} instances, {} materials, {} textures, {} of geometry",
            self.meshes,
            self.instances,
            self.materials,
            self.textures,
            crate::report::mib(self.geometry_bytes as u64)
        )
    }
}

/// How a texture's values are encoded in its PNG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Role {
    /// sRGB-encoded colour, linear alpha.
    BaseColor,
    /// Linear values in every channel.
    Data,
}

/// Appends `values` to `buf` and returns their view.
fn push_f32(buf: &mut Vec<u8>, values: impl Iterator<Item = f32>, per: usize) -> Value {
    let offset = buf.len();
    for v in values {
        buf.extend_from_slice(&v.to_le_bytes());
    }
    json!({ "offset": offset, "count": (buf.len() - offset) / (4 * per) })
}

/// Writes `scene` into the folder `dir` (created if needed); see the module documentation for
/// the files and their layout.
pub fn export(scene: &Scene, dir: &Path) -> Result<ExportStats, ExportError> {
    if scene.instanced_triangle_count() == 0 {
        return Err(ExportError::Empty);
    }
    let write = |name: &str, f: &dyn Fn(&Path) -> Result<(), String>| {
        let path = dir.join(name);
        write_atomic(&path, f).map_err(|message| ExportError::Write { path, message })
    };

    // Geometry: one buffer, one view per array.
    let mut buf = Vec::new();
    let meshes: Vec<Value> = scene
        .meshes
        .iter()
        .map(|m| {
            let positions = push_f32(&mut buf, m.positions.iter().flat_map(|p| p.to_array()), 3);
            let normals = (!m.normals.is_empty())
                .then(|| push_f32(&mut buf, m.normals.iter().flat_map(|n| n.to_array()), 3));
            let uvs = (!m.uvs.is_empty())
                .then(|| push_f32(&mut buf, m.uvs.iter().flat_map(|t| t.to_array()), 2));
            let offset = buf.len();
            for i in m.triangles.iter().flatten() {
                buf.extend_from_slice(&i.to_le_bytes());
            }
            json!({
                "name": m.name,
                "material": m.material,
                "positions": positions,
                "normals": normals,
                "uvs": uvs,
                "indices": { "offset": offset, "count": m.triangles.len() * 3 },
            })
        })
        .collect();
    write("geometry.bin", &|tmp| {
        std::fs::write(tmp, &buf).map_err(|e| e.to_string())
    })?;

    // Textures: one file per (texture, role) that a material uses.
    let mut files: HashMap<(u32, Role), String> = HashMap::new();
    let mut texture_ref = |r: &Option<TextureRef>, role: Role| -> Result<Value, ExportError> {
        let Some(r) = r else { return Ok(Value::Null) };
        let key = (r.texture, role);
        if !files.contains_key(&key) {
            let tex = &scene.textures[r.texture as usize];
            let name = format!(
                "texture_{:03}_{}.png",
                r.texture,
                if role == Role::BaseColor {
                    "basecolor"
                } else {
                    "data"
                }
            );
            let encode = |c: f32| {
                let c = if role == Role::BaseColor {
                    linear_to_srgb(c)
                } else {
                    c
                };
                (c.clamp(0.0, 1.0) * 255.0).round() as u8
            };
            let rgba: Vec<u8> = tex
                .texels
                .iter()
                .flat_map(|t| {
                    [
                        encode(t.x),
                        encode(t.y),
                        encode(t.z),
                        (t.w.clamp(0.0, 1.0) * 255.0).round() as u8,
                    ]
                })
                .collect();
            write(&name, &|tmp| {
                image::save_buffer_with_format(
                    tmp,
                    &rgba,
                    tex.width,
                    tex.height,
                    image::ColorType::Rgba8,
                    image::ImageFormat::Png,
                )
                .map_err(|e| e.to_string())
            })?;
            files.insert(key, name);
        }
        Ok(json!({
            "file": files[&key],
            "uv_transform": r.transform.0.to_cols_array(),
        }))
    };
    let mut materials = Vec::with_capacity(scene.materials.len());
    for m in &scene.materials {
        materials.push(json!({
            "name": m.name,
            "base_color": m.base_color.to_array(),
            "base_color_texture": texture_ref(&m.base_color_texture, Role::BaseColor)?,
            "metallic": m.metallic,
            "roughness": m.perceptual_roughness,
            "metallic_roughness_texture": texture_ref(&m.metallic_roughness_texture, Role::Data)?,
            "specular_factor": m.specular_factor,
            "specular_texture": texture_ref(&m.specular_texture, Role::Data)?,
            "alpha_cutoff": match m.alpha_mode {
                AlphaMode::Opaque => None,
                AlphaMode::Mask(c) => Some(c),
            },
        }));
    }
    let textures = files.len();

    let instances: Vec<Value> = scene
        .instances
        .iter()
        .map(|i| {
            json!({
                "mesh": i.mesh,
                "matrix": glam::Mat4::from(i.transform).to_cols_array(),
            })
        })
        .collect();
    let index = json!({
        "version": EXPORT_VERSION,
        "source": scene.source.as_ref().map(|p| p.display().to_string()),
        "geometry": "geometry.bin",
        "meshes": meshes,
        "instances": instances,
        "materials": materials,
    });
    let text = serde_json::to_string(&index).expect("JSON values always serialise");
    write("scene.json", &|tmp| {
        std::fs::write(tmp, &text).map_err(|e| e.to_string())
    })?;
    Ok(ExportStats {
        meshes: scene.meshes.len(),
        instances: scene.instances.len(),
        materials: scene.materials.len(),
        textures,
        geometry_bytes: buf.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Instance, Material, Mesh};
    use glam::{Affine3A, Vec2, Vec3};

    fn triangle_scene() -> Scene {
        Scene {
            meshes: vec![Mesh {
                name: "tri".into(),
                positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
                normals: vec![Vec3::Z; 3],
                uvs: vec![Vec2::ZERO, Vec2::X, Vec2::Y],
                triangles: vec![[0, 1, 2]],
                material: 0,
            }],
            instances: vec![Instance {
                mesh: 0,
                transform: Affine3A::from_translation(Vec3::new(1.0, 2.0, 3.0)),
            }],
            materials: vec![Material::default()],
            ..Default::default()
        }
    }

    /// The views in scene.json address exactly the arrays of the mesh, and the instance's
    /// matrix is column-major (translation in elements 12..15).
    #[test]
    fn views_address_the_arrays() {
        let dir = tempfile::tempdir().unwrap();
        let stats = export(&triangle_scene(), dir.path()).unwrap();
        assert_eq!(stats.geometry_bytes, 4 * (9 + 9 + 6 + 3));
        let index: Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("scene.json")).unwrap()).unwrap();
        let bin = std::fs::read(dir.path().join("geometry.bin")).unwrap();
        let mesh = &index["meshes"][0];
        let read = |view: &Value, i: usize| {
            let o = view["offset"].as_u64().unwrap() as usize + 4 * i;
            f32::from_le_bytes(bin[o..o + 4].try_into().unwrap())
        };
        assert_eq!(mesh["positions"]["count"], 3);
        assert_eq!(read(&mesh["positions"], 3), 1.0); // second vertex, x
        assert_eq!(read(&mesh["normals"], 2), 1.0); // first normal, z
        assert_eq!(read(&mesh["uvs"], 5), 1.0); // third uv, v
        let o = mesh["indices"]["offset"].as_u64().unwrap() as usize;
        assert_eq!(
            u32::from_le_bytes(bin[o + 8..o + 12].try_into().unwrap()),
            2
        );
        let m = index["instances"][0]["matrix"].as_array().unwrap();
        assert_eq!(
            m[12..15]
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect::<Vec<_>>(),
            [1.0, 2.0, 3.0]
        );
    }

    /// An empty scene is refused and leaves the folder empty.
    #[test]
    fn empty_scene_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(
            export(&Scene::default(), dir.path()),
            Err(ExportError::Empty)
        ));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
