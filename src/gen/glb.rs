//! A small glTF 2.0 binary (GLB) writer for generated scenes: meshes with one or more
//! primitives, metallic-roughness materials with KHR_materials_specular, alpha-mask textures,
//! node transforms, EXT_mesh_gpu_instancing and optional KHR_mesh_quantization.

use glam::{Mat4, Quat, Vec2, Vec3};
use image::ImageEncoder;
use serde_json::{json, Value};

/// Indexed triangle geometry with per-vertex normals and optional UVs.
#[derive(Clone, Debug, Default)]
pub struct MeshData {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Unit vertex normals.
    pub normals: Vec<Vec3>,
    /// Vertex UVs: one per position, or none.
    pub uvs: Vec<Vec2>,
    /// Triangle list: three vertex indices a triangle.
    pub indices: Vec<u32>,
}

impl MeshData {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Appends another mesh (UVs kept only if both have them).
    pub fn append(&mut self, o: &MeshData) {
        let base = self.positions.len() as u32;
        let keep_uv = self.uvs.len() == self.positions.len() && o.uvs.len() == o.positions.len();
        self.positions.extend_from_slice(&o.positions);
        self.normals.extend_from_slice(&o.normals);
        if keep_uv {
            self.uvs.extend_from_slice(&o.uvs);
        } else {
            self.uvs.clear();
        }
        self.indices.extend(o.indices.iter().map(|i| i + base));
    }

    /// Applies an affine transform (normals by the inverse transpose).
    pub fn transform(&mut self, m: Mat4) {
        let nm = glam::Mat3::from_mat4(m).inverse().transpose();
        for p in &mut self.positions {
            *p = m.transform_point3(*p);
        }
        for n in &mut self.normals {
            *n = (nm * *n).normalize_or_zero();
        }
    }
}

/// A material of a generated scene.
#[derive(Clone, Debug)]
pub struct MaterialData {
    /// The glTF material's name.
    pub name: String,
    /// Base colour factor β^c (linear RGBA).
    pub base_color: [f32; 4],
    /// Metallic factor β^m.
    pub metallic: f32,
    /// Perceptual roughness (α = roughness²).
    pub roughness: f32,
    /// KHR_materials_specular specularFactor; `None` leaves the extension out (factor 1).
    pub specular_factor: Option<f32>,
    /// Alpha-mask cutoff; with `texture`, a cut-out material.
    pub alpha_cutoff: Option<f32>,
    /// RGBA8 base colour texture (width, height, bytes).
    pub texture: Option<(u32, u32, Vec<u8>)>,
}

impl MaterialData {
    /// An opaque material without texture or specular extension.
    pub fn new(name: &str, rgb: [f32; 3], metallic: f32, roughness: f32) -> Self {
        MaterialData {
            name: name.into(),
            base_color: [rgb[0], rgb[1], rgb[2], 1.0],
            metallic,
            roughness,
            specular_factor: None,
            alpha_cutoff: None,
            texture: None,
        }
    }
}

/// A node: a mesh placed by a matrix, optionally repeated by EXT_mesh_gpu_instancing
/// (translation, rotation, scale per instance).
#[derive(Clone, Debug)]
pub struct NodeData {
    /// Index of the mesh in [`SceneData::meshes`].
    pub mesh: usize,
    /// The node's local-to-world matrix.
    pub matrix: Mat4,
    /// EXT_mesh_gpu_instancing placements (translation, rotation, scale), empty for one placement by `matrix`.
    pub gpu_instances: Vec<(Vec3, Quat, Vec3)>,
}

/// A generated scene: meshes of (primitive geometry, material index) lists.
#[derive(Clone, Debug, Default)]
pub struct SceneData {
    /// Meshes, each a list of primitives: geometry and an index into `materials`.
    pub meshes: Vec<Vec<(MeshData, usize)>>,
    /// The materials.
    pub materials: Vec<MaterialData>,
    /// The nodes placing the meshes.
    pub nodes: Vec<NodeData>,
}

impl SceneData {
    /// One mesh with one material, placed once.
    pub fn single(mesh: MeshData, material: MaterialData) -> Self {
        SceneData {
            meshes: vec![vec![(mesh, 0)]],
            materials: vec![material],
            nodes: vec![NodeData {
                mesh: 0,
                matrix: Mat4::IDENTITY,
                gpu_instances: Vec::new(),
            }],
        }
    }

    /// Triangles placed in the world.
    pub fn instanced_triangles(&self) -> usize {
        self.nodes
            .iter()
            .map(|n| {
                let t: usize = self.meshes[n.mesh]
                    .iter()
                    .map(|(m, _)| m.triangle_count())
                    .sum();
                t * n.gpu_instances.len().max(1)
            })
            .sum()
    }

    /// Sets every material to Lambertian (metallic 0, KHR_materials_specular factor 0).
    pub fn make_lambertian(&mut self) {
        for m in &mut self.materials {
            m.metallic = 0.0;
            m.specular_factor = Some(0.0);
        }
    }
}

impl SceneData {
    /// The scene as the importer would produce it from [`to_glb`] (without the file): for
    /// tests and benchmarks that need a scene in memory.
    pub fn to_scene(&self) -> crate::scene::Scene {
        use crate::scene::{
            AlphaMode, Instance, Material, Mesh, Scene, Texture, TextureRef, WrapMode,
        };
        let mut scene = Scene::default();
        for m in &self.materials {
            let base_color_texture = m.texture.as_ref().map(|(w, h, rgba)| {
                let lut = crate::math::color::srgb8_table();
                scene.textures.push(Texture {
                    name: m.name.clone(),
                    width: *w,
                    height: *h,
                    texels: rgba
                        .chunks_exact(4)
                        .map(|p| {
                            glam::Vec4::new(
                                lut[p[0] as usize],
                                lut[p[1] as usize],
                                lut[p[2] as usize],
                                p[3] as f32 / 255.0,
                            )
                        })
                        .collect(),
                    wrap_s: WrapMode::ClampToEdge,
                    wrap_t: WrapMode::ClampToEdge,
                });
                TextureRef {
                    texture: scene.textures.len() as u32 - 1,
                    transform: Default::default(),
                }
            });
            scene.materials.push(Material {
                name: m.name.clone(),
                base_color: glam::Vec4::from(m.base_color),
                base_color_texture,
                metallic: m.metallic,
                perceptual_roughness: m.roughness,
                metallic_roughness_texture: None,
                specular_factor: m.specular_factor.unwrap_or(1.0),
                specular_texture: None,
                alpha_mode: m
                    .alpha_cutoff
                    .map(AlphaMode::Mask)
                    .unwrap_or(AlphaMode::Opaque),
            });
        }
        let mut first_mesh = Vec::new();
        for prims in &self.meshes {
            first_mesh.push(scene.meshes.len() as u32);
            for (m, mat) in prims {
                scene.meshes.push(Mesh {
                    name: format!("generated {}", scene.meshes.len()),
                    positions: m.positions.clone(),
                    normals: m.normals.clone(),
                    uvs: m.uvs.clone(),
                    triangles: m
                        .indices
                        .chunks_exact(3)
                        .map(|c| [c[0], c[1], c[2]])
                        .collect(),
                    material: *mat as u32,
                });
            }
        }
        for n in &self.nodes {
            let placements: Vec<Mat4> = if n.gpu_instances.is_empty() {
                vec![n.matrix]
            } else {
                n.gpu_instances
                    .iter()
                    .map(|&(t, r, s)| n.matrix * Mat4::from_scale_rotation_translation(s, r, t))
                    .collect()
            };
            for m in placements {
                for k in 0..self.meshes[n.mesh].len() {
                    scene.instances.push(Instance {
                        mesh: first_mesh[n.mesh] + k as u32,
                        transform: glam::Affine3A::from_mat4(m),
                    });
                }
            }
        }
        scene
    }
}

struct Bin {
    data: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Bin {
    fn align(&mut self) {
        while self.data.len() % 4 != 0 {
            self.data.push(0);
        }
    }

    fn view(&mut self, bytes: &[u8], stride: Option<usize>) -> usize {
        self.align();
        let mut v = json!({"buffer": 0, "byteOffset": self.data.len(), "byteLength": bytes.len()});
        if let Some(s) = stride {
            v["byteStride"] = json!(s);
        }
        self.data.extend_from_slice(bytes);
        self.views.push(v);
        self.views.len() - 1
    }

    fn accessor(
        &mut self,
        view: usize,
        ctype: u32,
        count: usize,
        ty: &str,
        normalized: bool,
        minmax: Option<(Vec<f32>, Vec<f32>)>,
    ) -> usize {
        let mut a = json!({"bufferView": view, "componentType": ctype, "count": count, "type": ty});
        if normalized {
            a["normalized"] = json!(true);
        }
        if let Some((lo, hi)) = minmax {
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }

    fn f32s(&mut self, vals: &[f32], dims: usize, ty: &str, minmax: bool) -> usize {
        let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes, None);
        let mm = minmax.then(|| {
            let mut lo = vec![f32::INFINITY; dims];
            let mut hi = vec![f32::NEG_INFINITY; dims];
            for c in vals.chunks_exact(dims) {
                for k in 0..dims {
                    lo[k] = lo[k].min(c[k]);
                    hi[k] = hi[k].max(c[k]);
                }
            }
            (lo, hi)
        });
        self.accessor(view, 5126, vals.len() / dims, ty, false, mm)
    }
}

const BYTE: u32 = 5120;
const SHORT: u32 = 5122;
const UNSIGNED_SHORT: u32 = 5123;
const UNSIGNED_INT: u32 = 5125;

/// Encodes the scene as GLB bytes. With `quantize`, positions are stored as normalized SHORT
/// in each primitive's bounds (the node matrix undoes it), normals as normalized BYTE and UVs as
/// normalized UNSIGNED_SHORT where they lie in [0, 1] (KHR_mesh_quantization).
pub fn to_glb(scene: &SceneData, quantize: bool) -> Vec<u8> {
    let mut bin = Bin {
        data: Vec::new(),
        views: Vec::new(),
        accessors: Vec::new(),
    };
    let mut images = Vec::new();
    let mut textures = Vec::new();
    let mut uses_specular = false;
    let materials: Vec<Value> = scene
        .materials
        .iter()
        .map(|m| {
            let mut pbr = json!({"baseColorFactor": m.base_color, "metallicFactor": m.metallic, "roughnessFactor": m.roughness});
            if let Some((w, h, rgba)) = &m.texture {
                let mut png = Vec::new();
                image::codecs::png::PngEncoder::new(&mut png)
                    .write_image(rgba, *w, *h, image::ExtendedColorType::Rgba8)
                    .expect("encoding a PNG in memory");
                let view = bin.view(&png, None);
                images.push(json!({"bufferView": view, "mimeType": "image/png"}));
                textures.push(json!({"source": images.len() - 1, "sampler": 0}));
                pbr["baseColorTexture"] = json!({"index": textures.len() - 1});
            }
            let mut v = json!({"name": m.name, "pbrMetallicRoughness": pbr, "doubleSided": true});
            if let Some(c) = m.alpha_cutoff {
                v["alphaMode"] = json!("MASK");
                v["alphaCutoff"] = json!(c);
            }
            if let Some(s) = m.specular_factor {
                uses_specular = true;
                v["extensions"] = json!({"KHR_materials_specular": {"specularFactor": s}});
            }
            v
        })
        .collect();
    // Per mesh: the dequantisation matrix of its first primitive applies to the node, so every
    // primitive of a mesh shares one quantisation box.
    let mut dequant = Vec::new();
    let meshes: Vec<Value> = scene
        .meshes
        .iter()
        .map(|prims| {
            let (lo, hi) = prims.iter().flat_map(|(m, _)| m.positions.iter()).fold(
                (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                |(a, b), &p| (a.min(p), b.max(p)),
            );
            let center = 0.5 * (lo + hi);
            let half = (0.5 * (hi - lo)).max(Vec3::splat(1e-12));
            dequant.push(Mat4::from_translation(center) * Mat4::from_scale(half));
            let primitives: Vec<Value> = prims
                .iter()
                .map(|(m, mat)| {
                    let mut attrs = serde_json::Map::new();
                    if quantize {
                        let q: Vec<u8> = m
                            .positions
                            .iter()
                            .flat_map(|p| {
                                let n = ((*p - center) / half).clamp(Vec3::splat(-1.0), Vec3::ONE);
                                let s = |x: f32| ((x * 32767.0).round() as i16).to_le_bytes();
                                let mut e = Vec::with_capacity(8);
                                e.extend(s(n.x));
                                e.extend(s(n.y));
                                e.extend(s(n.z));
                                e.extend([0, 0]);
                                e
                            })
                            .collect();
                        let v = bin.view(&q, Some(8));
                        let a = bin.accessor(
                            v,
                            SHORT,
                            m.positions.len(),
                            "VEC3",
                            true,
                            Some((vec![-1.0; 3], vec![1.0; 3])),
                        );
                        attrs.insert("POSITION".into(), json!(a));
                        let nb: Vec<u8> = m
                            .normals
                            .iter()
                            .flat_map(|n| {
                                let b = |x: f32| (x.clamp(-1.0, 1.0) * 127.0).round() as i8 as u8;
                                [b(n.x), b(n.y), b(n.z), 0]
                            })
                            .collect();
                        let v = bin.view(&nb, Some(4));
                        let a = bin.accessor(v, BYTE, m.normals.len(), "VEC3", true, None);
                        attrs.insert("NORMAL".into(), json!(a));
                    } else {
                        let p: Vec<f32> = m.positions.iter().flat_map(|p| p.to_array()).collect();
                        attrs.insert("POSITION".into(), json!(bin.f32s(&p, 3, "VEC3", true)));
                        let n: Vec<f32> = m.normals.iter().flat_map(|p| p.to_array()).collect();
                        attrs.insert("NORMAL".into(), json!(bin.f32s(&n, 3, "VEC3", false)));
                    }
                    if m.uvs.len() == m.positions.len() && !m.uvs.is_empty() {
                        let unit = m
                            .uvs
                            .iter()
                            .all(|u| u.x >= 0.0 && u.x <= 1.0 && u.y >= 0.0 && u.y <= 1.0);
                        let a = if quantize && unit {
                            let b: Vec<u8> = m
                                .uvs
                                .iter()
                                .flat_map(|u| {
                                    let s = |x: f32| ((x * 65535.0).round() as u16).to_le_bytes();
                                    [s(u.x), s(u.y)].concat()
                                })
                                .collect();
                            let v = bin.view(&b, None);
                            bin.accessor(v, UNSIGNED_SHORT, m.uvs.len(), "VEC2", true, None)
                        } else {
                            let t: Vec<f32> = m.uvs.iter().flat_map(|p| p.to_array()).collect();
                            bin.f32s(&t, 2, "VEC2", false)
                        };
                        attrs.insert("TEXCOORD_0".into(), json!(a));
                    }
                    let ib: Vec<u8> = m.indices.iter().flat_map(|i| i.to_le_bytes()).collect();
                    let v = bin.view(&ib, None);
                    let ia = bin.accessor(v, UNSIGNED_INT, m.indices.len(), "SCALAR", false, None);
                    json!({"attributes": attrs, "indices": ia, "material": mat, "mode": 4})
                })
                .collect();
            json!({"primitives": primitives})
        })
        .collect();
    let mut uses_instancing = false;
    let nodes: Vec<Value> = scene
        .nodes
        .iter()
        .map(|n| {
            let instanced = !n.gpu_instances.is_empty();
            // Dequantisation applies first: in the node matrix, or baked into each instance's
            // TRS when instanced (TRS · T(c) · S(h) = T(t + R(s∘c)) · R · S(s∘h)).
            let m = if quantize && !instanced { n.matrix * dequant[n.mesh] } else { n.matrix };
            let (c, h) = {
                let d = dequant[n.mesh];
                (d.w_axis.truncate(), Vec3::new(d.x_axis.x, d.y_axis.y, d.z_axis.z))
            };
            let mut v = json!({"mesh": n.mesh});
            if m != Mat4::IDENTITY {
                v["matrix"] = json!(m.to_cols_array());
            }
            if !n.gpu_instances.is_empty() {
                uses_instancing = true;
                let (mut t, mut r, mut s) = (Vec::new(), Vec::new(), Vec::new());
                for &(tr, ro, sc) in &n.gpu_instances {
                    let (tr, sc) = if quantize { (tr + ro * (sc * c), sc * h) } else { (tr, sc) };
                    t.extend(tr.to_array());
                    r.extend(ro.to_array());
                    s.extend(sc.to_array());
                }
                let ta = bin.f32s(&t, 3, "VEC3", false);
                let ra = bin.f32s(&r, 4, "VEC4", false);
                let sa = bin.f32s(&s, 3, "VEC3", false);
                v["extensions"] = json!({"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": ta, "ROTATION": ra, "SCALE": sa}}});
            }
            v
        })
        .collect();
    let mut ext_used = Vec::new();
    let mut ext_req = Vec::new();
    if uses_specular {
        ext_used.push("KHR_materials_specular");
    }
    if uses_instancing {
        ext_used.push("EXT_mesh_gpu_instancing");
    }
    if quantize {
        ext_used.push("KHR_mesh_quantization");
        ext_req.push("KHR_mesh_quantization");
    }
    bin.align();
    let mut root = json!({
        "asset": {"version": "2.0", "generator": "aggtool gen"},
        "scene": 0,
        "scenes": [{"nodes": (0..nodes.len()).collect::<Vec<_>>()}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "accessors": bin.accessors,
        "bufferViews": bin.views,
        "buffers": [{"byteLength": bin.data.len()}],
    });
    if !images.is_empty() {
        root["images"] = json!(images);
        root["textures"] = json!(textures);
        root["samplers"] = json!([{"wrapS": 33071, "wrapT": 33071}]);
    }
    if !ext_used.is_empty() {
        root["extensionsUsed"] = json!(ext_used);
    }
    if !ext_req.is_empty() {
        root["extensionsRequired"] = json!(ext_req);
    }
    let mut js = serde_json::to_vec(&root).expect("JSON of generated scene");
    while js.len() % 4 != 0 {
        js.push(b' ');
    }
    let total = 12 + 8 + js.len() + 8 + bin.data.len();
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((js.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(js);
    out.extend((bin.data.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(bin.data);
    out
}
