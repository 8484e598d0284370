//! glTF 2.0 (`.gltf` and `.glb`) import.
//!
//! The `gltf` crate parses the JSON; its own validation is replaced by ours (the same checks,
//! minus the rejection of extensions we implement) and its accessor reader by ours, because the
//! crate panics on the integer accessors that KHR_mesh_quantization allows. Supported:
//! node hierarchies and transforms, every triangle primitive (strips and fans converted),
//! meshes shared by several nodes (kept once, instanced), EXT_mesh_gpu_instancing,
//! KHR_mesh_quantization, KHR_texture_transform and KHR_materials_specular.
//!
//! Normal maps are ignored (with a warning): the reference renderer and the bake both shade
//! with the interpolated vertex normals, so they agree; the bake's surface NDF captures
//! geometric detail above the texel scale only.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use base64::Engine;
use glam::{Affine3A, Mat4, Quat, Vec2, Vec3, Vec4};
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use gltf::Semantic;

use super::{sanitize_normals, ImportError, TriangleFilter};
use crate::scene::{AlphaMode, Instance, Material, Mesh, Scene, TextureRef, UvTransform, WrapMode};

/// Extensions whose presence in `extensionsRequired` we accept.
const SUPPORTED_REQUIRED: &[&str] = &[
    "KHR_mesh_quantization",
    "KHR_texture_transform",
    "KHR_materials_specular",
    "EXT_mesh_gpu_instancing",
];

/// Deepest node hierarchy we follow (a cycle is an error long before this).
const MAX_DEPTH: usize = 256;

/// Most elements an accessor without a buffer view may declare. Such an accessor is zeros
/// (then its sparse values) and its `count` is bounded by no data in the file, so a few bytes
/// of JSON could otherwise ask for any amount of memory (found by fuzz/fuzz_targets/
/// gltf_accessors.rs). 2²² elements, 64 MiB as VEC4 floats, is far more than the attributes we
/// read ever hold without data.
const MAX_VIEWLESS_ELEMENTS: usize = 1 << 22;

struct Ctx<'a> {
    path: &'a Path,
    base: PathBuf,
    buffers: Vec<Vec<u8>>,
    warnings: Vec<String>,
}

impl Ctx<'_> {
    fn err(&self, element: impl Into<String>, message: impl Into<String>) -> ImportError {
        ImportError::Invalid {
            path: self.path.to_path_buf(),
            element: element.into(),
            message: message.into(),
        }
    }
}

/// The root nodes [`load`] and [`triangle_count`] walk: the default scene's (or the first
/// scene's), or every node that is no node's child when the file has no scene.
fn scene_roots(doc: &gltf::Document) -> Vec<gltf::Node<'_>> {
    match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(s) => s.nodes().collect(),
        None => {
            let mut is_child = vec![false; doc.nodes().count()];
            for n in doc.nodes() {
                for c in n.children() {
                    is_child[c.index()] = true;
                }
            }
            doc.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    }
}

/// [`super::triangle_count`] for glTF: the JSON alone (a `.glb`'s first chunk, its buffers
/// unread), each triangle primitive counted by its accessors (indices, else positions) once
/// for every node that places its mesh in the scene [`load`] reads, stopped once past
/// `at_most`.
pub fn triangle_count(path: &Path, at_most: u64) -> Result<u64, ImportError> {
    use std::io::Read;
    let io = |source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    };
    let parse_err = |message: String| ImportError::Parse {
        path: path.to_path_buf(),
        message,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    // The first 20 bytes (fewer for a shorter file), whatever a single read returns.
    let mut head = Vec::with_capacity(20);
    (&mut file).take(20).read_to_end(&mut head).map_err(io)?;
    let n = head.len();
    let json = if n >= 4 && &head[..4] == b"glTF" {
        // Header (magic, version, length), then the JSON chunk's length and type.
        if n < 20 || &head[16..20] != b"JSON" {
            return Err(parse_err(
                "not a valid glTF file: no JSON chunk first".into(),
            ));
        }
        let len = u32::from_le_bytes([head[12], head[13], head[14], head[15]]) as u64;
        let size = std::fs::metadata(path).map_err(io)?.len();
        if len > size.saturating_sub(20) {
            return Err(parse_err(format!(
                "not a valid glTF file: a JSON chunk of {len} bytes in a file of {size}"
            )));
        }
        let mut json = vec![0u8; len as usize];
        file.read_exact(&mut json).map_err(io)?;
        json
    } else {
        let mut json = head[..n].to_vec();
        file.read_to_end(&mut json).map_err(io)?;
        json
    };
    let doc = gltf::Gltf::from_slice_without_validation(&json)
        .map_err(|e| parse_err(format!("not a valid glTF file: {e}")))?
        .document;
    let per_mesh: Vec<u64> = doc
        .meshes()
        .map(|m| {
            m.primitives()
                .map(|p| {
                    let n = p
                        .indices()
                        .or_else(|| p.get(&Semantic::Positions))
                        .map_or(0, |a| a.count() as u64);
                    match p.mode() {
                        Mode::Triangles => n / 3,
                        Mode::TriangleStrip | Mode::TriangleFan => n.saturating_sub(2),
                        _ => 0,
                    }
                })
                .sum()
        })
        .collect();
    // The scene's nodes as `load` walks them. A valid file's nodes form trees, each visited
    // once: more visits than nodes is a cycle or a node with two parents.
    let mut stack: Vec<(gltf::Node, u32)> = scene_roots(&doc).into_iter().map(|n| (n, 0)).collect();
    let (mut count, mut visits, nodes) = (0u64, 0usize, doc.nodes().count());
    while let Some((node, depth)) = stack.pop() {
        if count > at_most {
            break;
        }
        visits += 1;
        if visits > nodes || depth as usize > MAX_DEPTH {
            return Err(parse_err(
                "not a valid glTF file: its node hierarchy is not a tree".into(),
            ));
        }
        if let Some(m) = node.mesh() {
            count += per_mesh.get(m.index()).copied().unwrap_or(0);
        }
        stack.extend(node.children().map(|c| (c, depth + 1)));
    }
    Ok(count)
}

pub fn load(path: &Path) -> Result<Scene, ImportError> {
    let bytes = std::fs::read(path).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    load_slice(&bytes, path)
}

/// [`load`] on the bytes of a `.gltf` or `.glb` already in memory; `path` names the file in
/// errors and places relative URIs.
pub fn load_slice(bytes: &[u8], path: &Path) -> Result<Scene, ImportError> {
    let parse_err = |message: String| ImportError::Parse {
        path: path.to_path_buf(),
        message,
    };
    // gltf 1.4's GLB reader subtracts the 12-byte header from the length the header declares
    // without a check (an overflow panic where overflow checks are on, as in debug and fuzz
    // builds; found by fuzz/fuzz_targets/gltf.rs): refuse such a header first.
    if let [b'g', b'l', b'T', b'F', _, _, _, _, l0, l1, l2, l3, ..] = *bytes {
        let declared = u32::from_le_bytes([l0, l1, l2, l3]);
        if declared < 12 {
            return Err(parse_err(format!(
                "not a valid glTF file: the GLB header declares {declared} bytes, fewer than its own 12"
            )));
        }
    }
    let gltf = gltf::Gltf::from_slice_without_validation(bytes)
        .map_err(|e| parse_err(format!("not a valid glTF file: {e}")))?;
    validate(&gltf.document).map_err(parse_err)?;

    let mut ctx = Ctx {
        path,
        base: path.parent().map(Path::to_path_buf).unwrap_or_default(),
        buffers: Vec::new(),
        warnings: Vec::new(),
    };
    ctx.buffers = load_buffers(&ctx, &gltf.document, gltf.blob.as_deref())?;

    let mut scene = Scene::default();
    let mut textures = TextureCache::default();
    // Materials: index i of the file is scene material i; the default material is appended.
    let mut normal_maps = 0;
    for m in gltf.document.materials() {
        if m.normal_texture().is_some() {
            normal_maps += 1;
        }
        let mat = convert_material(&mut ctx, &m, &mut textures, &mut scene)?;
        scene.materials.push(mat);
    }
    if normal_maps > 0 {
        ctx.warnings.push(format!(
            "{normal_maps} materials have normal maps: they are ignored (vertex normals are used by the reference and the bake alike)"
        ));
    }
    let default_material = scene.materials.len() as u32;
    scene.materials.push(Material::default());

    // Meshes: each triangle primitive becomes one scene mesh; a glTF mesh maps to a list.
    let mut mesh_map: Vec<Vec<u32>> = Vec::new();
    for mesh in gltf.document.meshes() {
        let mut ids = Vec::new();
        for prim in mesh.primitives() {
            let element = format!(
                "mesh {} '{}' primitive {}",
                mesh.index(),
                mesh.name().unwrap_or(""),
                prim.index()
            );
            if let Some(m) = convert_primitive(&mut ctx, &prim, &element, default_material)? {
                ids.push(scene.meshes.len() as u32);
                scene.meshes.push(m);
            }
        }
        mesh_map.push(ids);
    }

    let roots = scene_roots(&gltf.document);
    let mut on_path = vec![false; gltf.document.nodes().count()];
    for root in roots {
        visit_node(
            &mut ctx,
            &gltf.document,
            &root,
            Mat4::IDENTITY,
            &mesh_map,
            &mut scene,
            &mut on_path,
            0,
        )?;
    }
    scene.warnings = ctx.warnings;
    Ok(scene)
}

/// The crate's validation, keeping the checks and dropping the complaint about required
/// extensions that we implement ourselves.
fn validate(doc: &gltf::Document) -> Result<(), String> {
    use gltf::json::validation::{Checked, Validate};
    let root = doc.as_json();
    // gltf-json 1.4's primitive check indexes `accessors` with POSITION before the index is
    // checked, so a POSITION naming no accessor panics inside `validate` (found by
    // fuzz/fuzz_targets/gltf.rs): look first.
    let position = Checked::Valid(gltf::json::mesh::Semantic::Positions);
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            if let Some(a) = prim.attributes.get(&position) {
                if a.value() >= root.accessors.len() {
                    return Err(format!(
                        "invalid glTF: meshes[{m}].primitives[{p}].attributes.POSITION: accessor {} does not exist ({} accessors)",
                        a.value(),
                        root.accessors.len()
                    ));
                }
            }
        }
    }
    // The `gltf` crate's `Image::source` unwraps a bufferView image's mimeType (which the spec
    // requires) and an image's uri when it has no bufferView; gltf-json checks neither (found
    // by fuzz/fuzz_targets/gltf.rs).
    for (i, image) in root.images.iter().enumerate() {
        if image.buffer_view.is_some() && image.mime_type.is_none() {
            return Err(format!(
                "invalid glTF: images[{i}]: an image in a bufferView needs a mimeType"
            ));
        }
        if image.buffer_view.is_none() && image.uri.is_none() {
            return Err(format!(
                "invalid glTF: images[{i}]: neither a uri nor a bufferView"
            ));
        }
    }
    let mut errors = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |path, error| {
        let p = path().to_string();
        if !p.starts_with("extensionsRequired") {
            errors.push(format!("{p}: {error}"));
        }
    });
    for ext in doc.extensions_required() {
        if !SUPPORTED_REQUIRED.contains(&ext)
            && !gltf::json::extensions::ENABLED_EXTENSIONS.contains(&ext)
        {
            errors.push(format!(
                "requires extension {ext}, which aggtool does not support"
            ));
        }
    }
    if errors.is_empty() {
        Ok(())
    } else {
        Err(format!("invalid glTF: {}", errors.join("; ")))
    }
}

fn decode_data_uri(uri: &str) -> Option<Result<Vec<u8>, String>> {
    let rest = uri.strip_prefix("data:")?;
    let (meta, data) = match rest.split_once(',') {
        Some(x) => x,
        None => return Some(Err("malformed data URI".into())),
    };
    if !meta.ends_with(";base64") {
        return Some(Err("data URI is not base64".into()));
    }
    Some(
        base64::engine::general_purpose::STANDARD
            .decode(data)
            .map_err(|e| format!("bad base64 in data URI: {e}")),
    )
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let Ok(v) = u8::from_str_radix(&s[i + 1..i + 3], 16) {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn read_uri(ctx: &Ctx, uri: &str, element: &str) -> Result<Vec<u8>, ImportError> {
    if let Some(r) = decode_data_uri(uri) {
        return r.map_err(|m| ctx.err(element, m));
    }
    if uri.contains("://") {
        return Err(ctx.err(element, format!("external URI '{uri}' is not a local file")));
    }
    let file = ctx.base.join(percent_decode(uri));
    // Only regular files: a URI naming /dev/zero, a FIFO or a terminal would never end.
    let meta = std::fs::metadata(&file)
        .map_err(|e| ctx.err(element, format!("cannot read {}: {e}", file.display())))?;
    if !meta.is_file() {
        return Err(ctx.err(element, format!("{} is not a regular file", file.display())));
    }
    std::fs::read(&file)
        .map_err(|e| ctx.err(element, format!("cannot read {}: {e}", file.display())))
}

fn load_buffers(
    ctx: &Ctx,
    doc: &gltf::Document,
    blob: Option<&[u8]>,
) -> Result<Vec<Vec<u8>>, ImportError> {
    let mut out = Vec::new();
    for b in doc.buffers() {
        let element = format!("buffer {}", b.index());
        let data = match b.source() {
            gltf::buffer::Source::Bin => match blob {
                Some(d) => d.to_vec(),
                None => {
                    return Err(ctx.err(element, "refers to the GLB binary chunk, which is missing"))
                }
            },
            gltf::buffer::Source::Uri(uri) => read_uri(ctx, uri, &element)?,
        };
        if data.len() < b.length() {
            return Err(ctx.err(
                element,
                format!("holds {} bytes but declares {}", data.len(), b.length()),
            ));
        }
        out.push(data);
    }
    Ok(out)
}

fn component_size(t: DataType) -> usize {
    match t {
        DataType::I8 | DataType::U8 => 1,
        DataType::I16 | DataType::U16 => 2,
        DataType::U32 | DataType::F32 => 4,
    }
}

#[inline]
fn read_component(bytes: &[u8], t: DataType, normalized: bool) -> f32 {
    match t {
        DataType::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
        DataType::U32 => u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as f32,
        DataType::I8 => {
            let v = bytes[0] as i8 as f32;
            if normalized {
                (v / 127.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U8 => {
            let v = bytes[0] as f32;
            if normalized {
                v / 255.0
            } else {
                v
            }
        }
        DataType::I16 => {
            let v = i16::from_le_bytes([bytes[0], bytes[1]]) as f32;
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = u16::from_le_bytes([bytes[0], bytes[1]]) as f32;
            if normalized {
                v / 65535.0
            } else {
                v
            }
        }
    }
}

/// Reads `count` elements of `dims` components of type `t` laid out from `offset` in `view`
/// with `stride`, each component converted by `read` (given its bytes).
#[allow(clippy::too_many_arguments)]
fn read_elements<T>(
    ctx: &Ctx,
    element: &str,
    view: &gltf::buffer::View,
    offset: usize,
    count: usize,
    dims: usize,
    t: DataType,
    stride: Option<usize>,
    read: impl Fn(&[u8]) -> T,
    out: &mut Vec<T>,
) -> Result<(), ImportError> {
    let csize = component_size(t);
    let esize = dims * csize;
    let stride = stride.unwrap_or(esize).max(esize);
    let buf = ctx
        .buffers
        .get(view.buffer().index())
        .ok_or_else(|| ctx.err(element, "buffer view refers to a missing buffer"))?;
    let start = view.offset().checked_add(offset);
    let need = count
        .checked_sub(1)
        .map(|c| c.checked_mul(stride).and_then(|x| x.checked_add(esize)))
        .unwrap_or(Some(0));
    let (start, need) = match (start, need) {
        (Some(s), Some(n)) => (s, n),
        _ => return Err(ctx.err(element, "accessor range overflows")),
    };
    let view_end = view.offset().saturating_add(view.length());
    if offset.saturating_add(need) > view.length() || view_end > buf.len() {
        return Err(ctx.err(
            element,
            format!(
                "accessor reads {need} bytes at offset {offset} of a {}-byte buffer view (buffer has {} bytes)",
                view.length(),
                buf.len()
            ),
        ));
    }
    out.reserve(count * dims);
    for i in 0..count {
        let e = start + i * stride;
        for c in 0..dims {
            let p = e + c * csize;
            out.push(read(&buf[p..p + csize]));
        }
    }
    Ok(())
}

/// Reads an accessor as flat f32 values (`count × components`), with quantized and normalized
/// integer types converted as KHR_mesh_quantization specifies, and sparse substitution applied.
fn read_accessor(
    ctx: &Ctx,
    acc: &gltf::Accessor,
    element: &str,
) -> Result<(Vec<f32>, usize), ImportError> {
    let normalized = acc.normalized();
    read_accessor_as(ctx, acc, element, 0.0, |b, t| {
        read_component(b, t, normalized)
    })
}

/// Reads an index accessor: unsigned integers exactly (through f32 an index above 2²⁴ would
/// round to another vertex), other types as their values.
fn read_indices(ctx: &Ctx, acc: &gltf::Accessor, element: &str) -> Result<Vec<u32>, ImportError> {
    read_accessor_as(ctx, acc, element, 0, read_index).map(|(v, _)| v)
}

fn read_index(bytes: &[u8], t: DataType) -> u32 {
    match t {
        DataType::U8 => bytes[0] as u32,
        DataType::U16 => u16::from_le_bytes([bytes[0], bytes[1]]) as u32,
        DataType::U32 => u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
        _ => read_component(bytes, t, false) as u32,
    }
}

/// [`read_accessor`] with each component converted by `read` (given its bytes and type) and
/// `zero` for the elements an accessor without a buffer view leaves unset.
fn read_accessor_as<T: Copy>(
    ctx: &Ctx,
    acc: &gltf::Accessor,
    element: &str,
    zero: T,
    read: impl Fn(&[u8], DataType) -> T,
) -> Result<(Vec<T>, usize), ImportError> {
    let dims = match acc.dimensions() {
        Dimensions::Scalar => 1,
        Dimensions::Vec2 => 2,
        Dimensions::Vec3 => 3,
        Dimensions::Vec4 => 4,
        d => return Err(ctx.err(element, format!("unsupported accessor type {d:?}"))),
    };
    let count = acc.count();
    let t = acc.data_type();
    let mut out = Vec::new();
    match acc.view() {
        Some(view) => read_elements(
            ctx,
            element,
            &view,
            acc.offset(),
            count,
            dims,
            t,
            view.stride(),
            |b| read(b, t),
            &mut out,
        )?,
        None if count > MAX_VIEWLESS_ELEMENTS => {
            return Err(ctx.err(
                element,
                format!(
                    "accessor has no buffer view and declares {count} elements (at most {MAX_VIEWLESS_ELEMENTS} are accepted without data)"
                ),
            ))
        }
        None => out.resize(count * dims, zero),
    }
    if let Some(sparse) = acc.sparse() {
        let n = sparse.count();
        let idx = sparse.indices();
        let it = match idx.index_type() {
            gltf::accessor::sparse::IndexType::U8 => DataType::U8,
            gltf::accessor::sparse::IndexType::U16 => DataType::U16,
            gltf::accessor::sparse::IndexType::U32 => DataType::U32,
        };
        let mut indices = Vec::new();
        read_elements(
            ctx,
            element,
            &idx.view(),
            idx.offset(),
            n,
            1,
            it,
            None,
            |b| read_index(b, it),
            &mut indices,
        )?;
        let vals = sparse.values();
        let mut values = Vec::new();
        read_elements(
            ctx,
            element,
            &vals.view(),
            vals.offset(),
            n,
            dims,
            t,
            None,
            |b| read(b, t),
            &mut values,
        )?;
        for (k, &i) in indices.iter().enumerate() {
            let i = i as usize;
            if i >= count {
                return Err(ctx.err(element, format!("sparse index {i} out of range ({count})")));
            }
            out[i * dims..(i + 1) * dims].copy_from_slice(&values[k * dims..(k + 1) * dims]);
        }
    }
    Ok((out, dims))
}

fn read_vec3s(ctx: &Ctx, acc: &gltf::Accessor, element: &str) -> Result<Vec<Vec3>, ImportError> {
    let (v, d) = read_accessor(ctx, acc, element)?;
    if d < 3 {
        return Err(ctx.err(element, "expected a VEC3 accessor"));
    }
    Ok(v.chunks_exact(d)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect())
}

fn convert_primitive(
    ctx: &mut Ctx,
    prim: &gltf::Primitive,
    element: &str,
    default_material: u32,
) -> Result<Option<Mesh>, ImportError> {
    let mode = prim.mode();
    if !matches!(
        mode,
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
    ) {
        ctx.warnings.push(format!(
            "{element}: skipped ({mode:?} primitives are not surfaces)"
        ));
        return Ok(None);
    }
    let Some(pos_acc) = prim.get(&Semantic::Positions) else {
        ctx.warnings
            .push(format!("{element}: skipped (no POSITION attribute)"));
        return Ok(None);
    };
    let positions = read_vec3s(ctx, &pos_acc, &format!("{element} POSITION"))?;
    let n = positions.len();
    let mut normals = match prim.get(&Semantic::Normals) {
        Some(a) => read_vec3s(ctx, &a, &format!("{element} NORMAL"))?,
        None => Vec::new(),
    };
    if !normals.is_empty() && normals.len() != n {
        ctx.warnings.push(format!(
            "{element}: NORMAL count differs from POSITION; normals ignored"
        ));
        normals.clear();
    }
    sanitize_normals(&mut normals);
    let mut uvs = match prim.get(&Semantic::TexCoords(0)) {
        Some(a) => {
            let (v, d) = read_accessor(ctx, &a, &format!("{element} TEXCOORD_0"))?;
            if d < 2 {
                return Err(ctx.err(element, "TEXCOORD_0 is not VEC2"));
            }
            v.chunks_exact(d).map(|c| Vec2::new(c[0], c[1])).collect()
        }
        None => Vec::new(),
    };
    if !uvs.is_empty() && uvs.len() != n {
        ctx.warnings.push(format!(
            "{element}: TEXCOORD_0 count differs from POSITION; ignored"
        ));
        uvs.clear();
    }
    let indices: Vec<u32> = match prim.indices() {
        Some(a) => read_indices(ctx, &a, &format!("{element} indices"))?,
        None => (0..n as u32).collect(),
    };
    let tris: Vec<[u32; 3]> = match mode {
        Mode::Triangles => indices
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        Mode::TriangleStrip => (2..indices.len())
            .map(|i| {
                if i % 2 == 0 {
                    [indices[i - 2], indices[i - 1], indices[i]]
                } else {
                    [indices[i - 1], indices[i - 2], indices[i]]
                }
            })
            .collect(),
        _ => (2..indices.len())
            .map(|i| [indices[0], indices[i - 1], indices[i]])
            .collect(),
    };
    let mut filter = TriangleFilter::new();
    let mut triangles = Vec::with_capacity(tris.len());
    for t in tris {
        if filter
            .accept(&positions, t)
            .map_err(|m| ctx.err(element, m))?
        {
            triangles.push(t);
        }
    }
    filter.report(element, &mut ctx.warnings);
    if triangles.is_empty() {
        ctx.warnings
            .push(format!("{element}: skipped (no valid triangles)"));
        return Ok(None);
    }
    Ok(Some(Mesh {
        name: element.to_string(),
        positions,
        normals,
        uvs,
        triangles,
        material: prim
            .material()
            .index()
            .map(|i| i as u32)
            .unwrap_or(default_material),
    }))
}

#[allow(clippy::too_many_arguments)]
fn visit_node(
    ctx: &mut Ctx,
    doc: &gltf::Document,
    node: &gltf::Node,
    parent: Mat4,
    mesh_map: &[Vec<u32>],
    scene: &mut Scene,
    on_path: &mut [bool],
    depth: usize,
) -> Result<(), ImportError> {
    let element = format!("node {} '{}'", node.index(), node.name().unwrap_or(""));
    if depth > MAX_DEPTH || on_path[node.index()] {
        return Err(ctx.err(element, "node hierarchy has a cycle or is too deep"));
    }
    on_path[node.index()] = true;
    let local = Mat4::from_cols_array_2d(&node.transform().matrix());
    let world = parent * local;
    if let Some(mesh) = node.mesh() {
        let mut placements = vec![world];
        if let Some(ext) = node.extension_value("EXT_mesh_gpu_instancing") {
            placements = gpu_instances(ctx, doc, ext, &element)?
                .into_iter()
                .map(|m| world * m)
                .collect();
        }
        let mut skipped = 0;
        for m in placements {
            match checked_affine(m) {
                Some(t) => {
                    for &id in &mesh_map[mesh.index()] {
                        scene.instances.push(Instance {
                            mesh: id,
                            transform: t,
                        });
                    }
                }
                None => skipped += 1,
            }
        }
        if skipped > 0 {
            ctx.warnings.push(format!(
                "{element}: skipped {skipped} placements with a non-finite, singular or absurd transform"
            ));
        }
    }
    for child in node.children() {
        visit_node(ctx, doc, &child, world, mesh_map, scene, on_path, depth + 1)?;
    }
    on_path[node.index()] = false;
    Ok(())
}

/// An affine transform if `m` is finite, non-singular and of sane scale (|scale| in
/// [1e-8, 1e8], translation below 1e12), else `None`.
fn checked_affine(m: Mat4) -> Option<Affine3A> {
    if !m.is_finite() {
        return None;
    }
    let a = Affine3A::from_mat4(m);
    let det = a.matrix3.determinant().abs();
    if !(1e-24..=1e24).contains(&det) || a.translation.abs().max_element() > 1e12 {
        return None;
    }
    Some(a)
}

fn gpu_instances(
    ctx: &mut Ctx,
    doc: &gltf::Document,
    ext: &gltf::json::Value,
    element: &str,
) -> Result<Vec<Mat4>, ImportError> {
    let element = format!("{element} EXT_mesh_gpu_instancing");
    let attrs = ext
        .get("attributes")
        .and_then(|a| a.as_object())
        .ok_or_else(|| ctx.err(&element, "missing 'attributes'"))?;
    // Each attribute with the width the extension specifies (VEC3, VEC4, VEC3); another width
    // is an error, not a short read (a SCALAR TRANSLATION once panicked here: found by
    // fuzz/fuzz_targets/gltf_accessors.rs).
    let read = |name: &str, width: usize| -> Result<Option<(Vec<f32>, usize)>, ImportError> {
        match attrs.get(name).and_then(|v| v.as_u64()) {
            None => Ok(None),
            Some(i) => {
                let acc = doc.accessors().nth(i as usize).ok_or_else(|| {
                    ctx.err(&element, format!("{name} accessor {i} does not exist"))
                })?;
                let (v, d) = read_accessor(ctx, &acc, &format!("{element} {name}"))?;
                if d != width {
                    return Err(ctx.err(
                        &element,
                        format!("{name} accessor {i} has {d} components per element, not {width}"),
                    ));
                }
                Ok(Some((v, d)))
            }
        }
    };
    let t = read("TRANSLATION", 3)?;
    let r = read("ROTATION", 4)?;
    let s = read("SCALE", 3)?;
    let count = [&t, &r, &s]
        .iter()
        .filter_map(|x| x.as_ref().map(|(v, d)| v.len() / d))
        .max()
        .unwrap_or(0);
    let mut out = Vec::with_capacity(count);
    for i in 0..count {
        fn get(x: &Option<(Vec<f32>, usize)>, k: usize) -> Option<&[f32]> {
            x.as_ref().and_then(|(v, d)| v.get(k * d..(k + 1) * d))
        }
        let tr = get(&t, i)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .unwrap_or(Vec3::ZERO);
        let ro = get(&r, i)
            .map(|c| Quat::from_xyzw(c[0], c[1], c[2], c[3]).normalize())
            .unwrap_or(Quat::IDENTITY);
        let sc = get(&s, i)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .unwrap_or(Vec3::ONE);
        out.push(Mat4::from_scale_rotation_translation(sc, ro, tr));
    }
    Ok(out)
}

#[derive(Default)]
struct TextureCache {
    /// (glTF texture index, sRGB) to scene texture index, or None when it failed to load.
    map: HashMap<(usize, bool), Option<u32>>,
}

fn wrap_mode(m: gltf::texture::WrappingMode) -> WrapMode {
    match m {
        gltf::texture::WrappingMode::ClampToEdge => WrapMode::ClampToEdge,
        gltf::texture::WrappingMode::MirroredRepeat => WrapMode::MirroredRepeat,
        gltf::texture::WrappingMode::Repeat => WrapMode::Repeat,
    }
}

fn texture_ref(
    ctx: &mut Ctx,
    info: Option<gltf::texture::Info>,
    srgb: bool,
    cache: &mut TextureCache,
    scene: &mut Scene,
    mat_element: &str,
) -> Option<TextureRef> {
    let info = info?;
    let tex = info.texture();
    let mut tex_coord = info.tex_coord();
    let mut transform = UvTransform::default();
    if let Some(t) = info.texture_transform() {
        transform = UvTransform::from_offset_rotation_scale(
            Vec2::from(t.offset()),
            t.rotation(),
            Vec2::from(t.scale()),
        );
        if let Some(tc) = t.tex_coord() {
            tex_coord = tc;
        }
    }
    if tex_coord != 0 {
        ctx.warnings.push(format!(
            "{mat_element}: texture {} uses TEXCOORD_{tex_coord}; only TEXCOORD_0 is supported and is used instead",
            tex.index()
        ));
    }
    let key = (tex.index(), srgb);
    if let Some(&id) = cache.map.get(&key) {
        return id.map(|texture| TextureRef { texture, transform });
    }
    let element = format!("texture {} (image {})", tex.index(), tex.source().index());
    let bytes = match tex.source().source() {
        gltf::image::Source::View { view, .. } => {
            let buf = ctx.buffers.get(view.buffer().index());
            match buf
                .and_then(|b| b.get(view.offset()..view.offset().saturating_add(view.length())))
            {
                Some(b) => Ok(b.to_vec()),
                None => Err(format!("{element}: image buffer view out of range")),
            }
        }
        gltf::image::Source::Uri { uri, .. } => {
            read_uri(ctx, uri, &element).map_err(|e| e.to_string())
        }
    };
    let sampler = tex.sampler();
    let decoded = bytes.and_then(|b| {
        super::decode_texture(
            &b,
            tex.source().name().unwrap_or(&element),
            srgb,
            (wrap_mode(sampler.wrap_s()), wrap_mode(sampler.wrap_t())),
        )
        .map_err(|m| format!("{element}: {m}"))
    });
    let id = match decoded {
        Ok(t) => {
            scene.textures.push(t);
            Some(scene.textures.len() as u32 - 1)
        }
        Err(m) => {
            ctx.warnings
                .push(format!("{mat_element}: {m}; the texture is ignored"));
            None
        }
    };
    cache.map.insert(key, id);
    id.map(|texture| TextureRef { texture, transform })
}

fn convert_material(
    ctx: &mut Ctx,
    m: &gltf::Material,
    cache: &mut TextureCache,
    scene: &mut Scene,
) -> Result<Material, ImportError> {
    let element = format!(
        "material {} '{}'",
        m.index().unwrap_or(0),
        m.name().unwrap_or("")
    );
    let pbr = m.pbr_metallic_roughness();
    let bc = pbr.base_color_factor();
    let alpha_mode = match m.alpha_mode() {
        gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
        gltf::material::AlphaMode::Mask => AlphaMode::Mask(m.alpha_cutoff().unwrap_or(0.5)),
        gltf::material::AlphaMode::Blend => {
            ctx.warnings.push(format!(
                "{element}: alphaMode BLEND is treated as MASK with cutoff 0.5"
            ));
            AlphaMode::Mask(0.5)
        }
    };
    let base_color_texture =
        texture_ref(ctx, pbr.base_color_texture(), true, cache, scene, &element);
    let metallic_roughness_texture = texture_ref(
        ctx,
        pbr.metallic_roughness_texture(),
        false,
        cache,
        scene,
        &element,
    );
    let (specular_factor, specular_texture) = match m.specular() {
        Some(s) => (
            s.specular_factor(),
            texture_ref(ctx, s.specular_texture(), false, cache, scene, &element),
        ),
        None => (1.0, None),
    };
    Ok(Material {
        name: m.name().unwrap_or("").to_string(),
        base_color: Vec4::from(bc),
        base_color_texture,
        metallic: pbr.metallic_factor(),
        perceptual_roughness: pbr.roughness_factor(),
        metallic_roughness_texture,
        specular_factor,
        specular_texture,
        alpha_mode,
    })
}
