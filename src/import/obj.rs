//! Wavefront OBJ/MTL import with `tobj`.
//!
//! Phong materials are mapped onto the metallic-roughness model of Eq. 11 as follows (the
//! Sweet Home 3D assets use exactly these keys):
//! - GGX roughness `α = sqrt(2 / (Ns + 2))`, the Blinn-Phong exponent to Beckmann/GGX width of
//!   Walter et al. 2007 (Ns 0 → α 1, Ns 100 → α 0.14, Ns 1000 → α 0.045).
//! - Specular strength `s = lum(Ks)`. Metallic `= clamp((s − lum(Kd)) / s, 0, 1)` when
//!   `s > 0.04` (a specular reflectance above any dielectric's and above the diffuse one means
//!   metal), else 0.
//! - Base colour `= (1 − metallic) · Kd + metallic · Ks` (times `map_Kd`, linearised).
//! - Dielectric specular: `specularFactor = clamp(s / 0.04, 0, 1)`, so `Ks = 0` is Lambertian
//!   and any `Ks ≥ 0.04` has the standard F0 = 0.04.
//! - PBR keys override: `Pr` (perceptual roughness, α = Pr²) and `Pm` (metallic).
//! - `d < 1` or `Tr > 0` (glass) is warned about and treated as opaque.

use std::collections::HashMap;
use std::path::Path;

use glam::{Vec2, Vec3, Vec4};

use super::{sanitize_normals, ImportError, TriangleFilter};
use crate::math::color::luminance;
use crate::scene::{AlphaMode, Instance, Material, Mesh, Scene, TextureRef, UvTransform, WrapMode};

/// [`super::triangle_count`] for OBJ: the faces' triangles (k − 2 for k corners), read a
/// line at a time and stopped once past `at_most`.
pub fn triangle_count(path: &Path, at_most: u64) -> Result<u64, ImportError> {
    use std::io::BufRead;
    let io = |source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut reader = std::io::BufReader::new(std::fs::File::open(path).map_err(io)?);
    let mut line = Vec::new();
    let mut count = 0u64;
    while count <= at_most {
        line.clear();
        if reader.read_until(b'\n', &mut line).map_err(io)? == 0 {
            break;
        }
        let mut words = line
            .split(|b| b.is_ascii_whitespace())
            .filter(|w| !w.is_empty());
        if words.next() == Some(b"f".as_slice()) {
            count += (words.count() as u64).saturating_sub(2);
        }
    }
    Ok(count)
}

pub fn load(path: &Path) -> Result<Scene, ImportError> {
    if let Err(source) = std::fs::metadata(path) {
        return Err(ImportError::Io {
            path: path.to_path_buf(),
            source,
        });
    }
    let opts = tobj::LoadOptions {
        single_index: true,
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, materials) = tobj::load_obj(path, &opts).map_err(|e| ImportError::Parse {
        path: path.to_path_buf(),
        message: format!("cannot parse OBJ: {e}"),
    })?;
    let mut scene = Scene::default();
    let mut warnings = Vec::new();
    let base = path.parent().unwrap_or(Path::new("."));

    let materials = match materials {
        Ok(m) => m,
        Err(e) => {
            warnings.push(format!(
                "material library not loaded ({e}); default materials used"
            ));
            Vec::new()
        }
    };
    let mut tex_cache: HashMap<String, Option<u32>> = HashMap::new();
    let mut glass = Vec::new();
    for m in &materials {
        let (mat, is_glass) = convert_material(m, base, &mut scene, &mut tex_cache, &mut warnings);
        if is_glass {
            glass.push(m.name.clone());
        }
        scene.materials.push(mat);
    }
    if !glass.is_empty() {
        warnings.push(format!(
            "materials {} are partly transparent (d < 1): treated as opaque",
            glass.join(", ")
        ));
    }
    // OBJ files have no PBR default; a grey Lambertian-ish dielectric is the usual assumption.
    let default_material = scene.materials.len() as u32;
    scene.materials.push(Material {
        name: "obj-default".into(),
        base_color: Vec4::new(0.8, 0.8, 0.8, 1.0),
        metallic: 0.0,
        perceptual_roughness: 1.0,
        ..Material::default()
    });

    for (mi, model) in models.iter().enumerate() {
        let element = format!("object {mi} '{}'", model.name);
        let m = &model.mesh;
        let positions: Vec<Vec3> = m
            .positions
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
        let mut normals: Vec<Vec3> = m
            .normals
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
        if normals.len() != positions.len() {
            normals.clear();
        }
        sanitize_normals(&mut normals);
        let mut uvs: Vec<Vec2> = m
            .texcoords
            .chunks_exact(2)
            // OBJ's v axis points up; textures are stored top row first.
            .map(|c| Vec2::new(c[0], 1.0 - c[1]))
            .collect();
        if uvs.len() != positions.len() {
            uvs.clear();
        }
        let mut filter = TriangleFilter::new();
        let mut triangles = Vec::with_capacity(m.indices.len() / 3);
        for c in m.indices.chunks_exact(3) {
            let t = [c[0], c[1], c[2]];
            if filter
                .accept(&positions, t)
                .map_err(|message| ImportError::Invalid {
                    path: path.to_path_buf(),
                    element: element.clone(),
                    message,
                })?
            {
                triangles.push(t);
            }
        }
        filter.report(&element, &mut warnings);
        if triangles.is_empty() {
            continue;
        }
        let material = match m.material_id {
            Some(id) if id < materials.len() => id as u32,
            Some(id) => {
                warnings.push(format!(
                    "{element}: material {id} does not exist; default used"
                ));
                default_material
            }
            None => default_material,
        };
        scene.instances.push(Instance {
            mesh: scene.meshes.len() as u32,
            transform: glam::Affine3A::IDENTITY,
        });
        scene.meshes.push(Mesh {
            name: element,
            positions,
            normals,
            uvs,
            triangles,
            material,
        });
    }
    scene.warnings = warnings;
    Ok(scene)
}

fn convert_material(
    m: &tobj::Material,
    base: &Path,
    scene: &mut Scene,
    cache: &mut HashMap<String, Option<u32>>,
    warnings: &mut Vec<String>,
) -> (Material, bool) {
    let kd = Vec3::from(m.diffuse.unwrap_or([0.8; 3]));
    let ks = Vec3::from(m.specular.unwrap_or([0.0; 3]));
    let ns = m.shininess.unwrap_or(0.0).max(0.0);
    let s = luminance(ks).max(0.0);
    let mut metallic = if s > 0.04 {
        ((s - luminance(kd)) / s).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let mut alpha = (2.0 / (ns + 2.0)).sqrt();
    let param = |k: &str| {
        m.unknown_param
            .get(k)
            .and_then(|v| v.trim().parse::<f32>().ok())
    };
    if let Some(pr) = param("Pr") {
        alpha = pr.clamp(0.0, 1.0).powi(2);
    }
    if let Some(pm) = param("Pm") {
        metallic = pm.clamp(0.0, 1.0);
    }
    let base_rgb = (1.0 - metallic) * kd + metallic * ks;
    let is_glass = m.dissolve.is_some_and(|d| d < 1.0) || param("Tr").is_some_and(|t| t > 0.0);
    let base_color_texture = m.diffuse_texture.as_ref().and_then(|name| {
        let id = *cache.entry(name.clone()).or_insert_with(|| {
            let file = base.join(name.replace('\\', "/"));
            let loaded = std::fs::read(&file)
                .map_err(|e| format!("cannot read {}: {e}", file.display()))
                .and_then(|b| {
                    super::decode_texture(&b, name, true, (WrapMode::Repeat, WrapMode::Repeat))
                });
            match loaded {
                Ok(t) => {
                    scene.textures.push(t);
                    Some(scene.textures.len() as u32 - 1)
                }
                Err(e) => {
                    warnings.push(format!(
                        "material '{}': map_Kd {e}; the texture is ignored",
                        m.name
                    ));
                    None
                }
            }
        });
        id.map(|texture| TextureRef {
            texture,
            transform: UvTransform::default(),
        })
    });
    (
        Material {
            name: m.name.clone(),
            base_color: base_rgb.extend(1.0),
            base_color_texture,
            metallic,
            perceptual_roughness: alpha.sqrt(),
            metallic_roughness_texture: None,
            specular_factor: (s / 0.04).clamp(0.0, 1.0),
            specular_texture: None,
            alpha_mode: AlphaMode::Opaque,
        },
        is_glass,
    )
}
