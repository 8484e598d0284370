//! glTF import: features and bad input, on small hand-written files (buffers as data URIs).

mod common;

use std::path::Path;

use aggtool::import::{load, ImportError, ImportOptions};
use base64::Engine;
use serde_json::{json, Value};

/// A unit quad (2 triangles) as a glTF document with one embedded buffer; `edit` adjusts it.
fn quad_gltf(edit: impl FnOnce(&mut Value, &mut Vec<u8>)) -> (Value, Vec<u8>) {
    let mut bin = Vec::new();
    for v in [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ] {
        for c in v {
            bin.extend(c.to_le_bytes());
        }
    }
    for uv in [[0.0f32, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]] {
        for c in uv {
            bin.extend(c.to_le_bytes());
        }
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend(i.to_le_bytes());
    }
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.5}}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0,0,0], "max": [1,1,0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 32},
            {"buffer": 0, "byteOffset": 80, "byteLength": 12}
        ],
        "buffers": [{"byteLength": 92}]
    });
    edit(&mut doc, &mut bin);
    (doc, bin)
}

fn write(dir: &Path, name: &str, doc: &Value, bin: &[u8]) -> std::path::PathBuf {
    let mut doc = doc.clone();
    if doc["buffers"][0].get("uri").is_none() {
        doc["buffers"][0]["uri"] = json!(format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(bin)
        ));
    }
    let p = dir.join(name);
    std::fs::write(&p, serde_json::to_vec(&doc).unwrap()).unwrap();
    p
}

fn load_edit(
    edit: impl FnOnce(&mut Value, &mut Vec<u8>),
) -> Result<aggtool::scene::Scene, ImportError> {
    let dir = tempfile::tempdir().unwrap();
    let (doc, bin) = quad_gltf(edit);
    load(
        &write(dir.path(), "a.gltf", &doc, &bin),
        ImportOptions::default(),
    )
}

#[test]
fn plain_quad_and_materials() {
    let s = load_edit(|_, _| {}).unwrap();
    assert_eq!(s.instanced_triangle_count(), 2);
    assert_eq!(s.meshes[0].uvs.len(), 4);
    assert!(
        s.meshes[0].normals.is_empty(),
        "no NORMAL: geometric normals are used"
    );
    let p = s.materials[0].eval(&s.textures, glam::Vec2::ZERO);
    assert!((p.alpha - 0.25).abs() < 1e-6, "alpha = roughness²");
    assert_eq!(p.base_color, glam::Vec3::new(0.5, 0.25, 1.0));
    assert!((p.specular - 0.04).abs() < 1e-7 && p.f90 == 1.0);
}

#[test]
fn khr_materials_specular_and_texture_transform() {
    let s = load_edit(|d, _| {
        d["extensionsUsed"] = json!(["KHR_materials_specular", "KHR_texture_transform"]);
        d["materials"][0]["extensions"] =
            json!({"KHR_materials_specular": {"specularFactor": 0.0}});
    })
    .unwrap();
    let p = s.materials[0].eval(&s.textures, glam::Vec2::ZERO);
    assert_eq!((p.specular, p.f90), (0.0, 0.0));
    let s = load_edit(|d, _| {
        d["materials"][0]["extensions"] =
            json!({"KHR_materials_specular": {"specularFactor": 0.5}});
    })
    .unwrap();
    let p = s.materials[0].eval(&s.textures, glam::Vec2::ZERO);
    assert!((p.specular - 0.02).abs() < 1e-7 && (p.f90 - 0.5).abs() < 1e-7);
}

#[test]
fn shared_mesh_is_instanced_not_copied() {
    let s = load_edit(|d, _| {
        d["nodes"] = json!([
            {"children": [1, 2], "translation": [0, 0, 5]},
            {"mesh": 0},
            {"mesh": 0, "matrix": [2,0,0,0, 0,2,0,0, 0,0,2,0, 10,0,0,1]}
        ]);
    })
    .unwrap();
    assert_eq!(s.meshes.len(), 1);
    assert_eq!(s.instances.len(), 2);
    assert_eq!(s.instanced_triangle_count(), 4);
    let (lo, hi) = s.bounds();
    assert_eq!(lo, glam::Vec3::new(0.0, 0.0, 5.0));
    assert_eq!(hi, glam::Vec3::new(12.0, 2.0, 5.0));
}

#[test]
fn quantized_generated_scenes_match_float_ones() {
    let dir = tempfile::tempdir().unwrap();
    for name in aggtool::gen::NAMES {
        let s = aggtool::gen::GenSettings {
            triangles: 3000,
            ..Default::default()
        };
        let (pf, _) = aggtool::gen::write(name, &s, dir.path(), false).unwrap();
        let f = load(&pf, Default::default()).unwrap();
        let qdir = dir.path().join("q");
        let (pq, _) = aggtool::gen::write(name, &s, &qdir, true).unwrap();
        let q = load(&pq, Default::default()).unwrap();
        let (flo, fhi) = f.bounds();
        let (qlo, qhi) = q.bounds();
        // 16-bit positions: error below 2^-15 of the extent (plus float slack).
        let tol = (fhi - flo).max_element() * 1e-4;
        assert!(
            (flo - qlo).abs().max_element() < tol && (fhi - qhi).abs().max_element() < tol,
            "{name}"
        );
        assert_eq!(f.instances.len(), q.instances.len(), "{name}");
        let (af, aq) = (f.world_area(), q.world_area());
        assert!((af - aq).abs() / af < 2e-3, "{name}: area {af} vs {aq}");
    }
}

#[test]
fn gpu_instancing_expands_placements() {
    let (_d, s) = common::generated("buildings", 5000, false);
    // One window mesh placed by EXT_mesh_gpu_instancing many times.
    let mut uses = vec![0usize; s.meshes.len()];
    for i in &s.instances {
        uses[i.mesh as usize] += 1;
    }
    assert!(uses.iter().any(|&u| u > 100), "{uses:?}");
    assert!(s.instanced_triangle_count() > 2 * s.unique_triangle_count());
}

fn expect_invalid(r: Result<aggtool::scene::Scene, ImportError>, needle: &str) {
    match r {
        Ok(_) => panic!("expected an error mentioning '{needle}'"),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains(needle), "'{msg}' should mention '{needle}'");
        }
    }
}

#[test]
fn bad_input_gives_clear_errors() {
    expect_invalid(
        load_edit(|d, _| d["meshes"][0]["primitives"][0]["indices"] = json!(7)),
        "invalid glTF",
    );
    expect_invalid(
        load_edit(|_, b| {
            // Index 9 on a 4-vertex mesh.
            let n = b.len();
            b[n - 2] = 9;
        }),
        "out of range",
    );
    expect_invalid(
        load_edit(|d, _| d["bufferViews"][0]["byteLength"] = json!(4800)),
        "buffer has 92 bytes",
    );
    expect_invalid(
        load_edit(|d, _| d["accessors"][0]["count"] = json!(400)),
        "accessor reads",
    );
    expect_invalid(
        load_edit(|d, _| d["extensionsRequired"] = json!(["KHR_draco_mesh_compression"])),
        "KHR_draco_mesh_compression",
    );
    expect_invalid(
        load_edit(|d, _| d["nodes"] = json!([{"mesh": 0, "children": [0]}])),
        "cycle",
    );
    expect_invalid(
        load_edit(|d, _| d["buffers"][0]["uri"] = json!("missing.bin")),
        "missing.bin",
    );
    expect_invalid(
        load_edit(|d, _| {
            d["buffers"][0]["uri"] = json!("data:application/octet-stream;base64,AAAA")
        }),
        "buffer 0",
    );
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("junk.glb");
    std::fs::write(&p, b"glTF\x02\0\0\0garbage").unwrap();
    expect_invalid(load(&p, Default::default()), "junk.glb");
    std::fs::write(dir.path().join("x.fbx"), b"").unwrap();
    expect_invalid(
        load(&dir.path().join("x.fbx"), Default::default()),
        "unsupported file type",
    );
    expect_invalid(
        load(&dir.path().join("nope.gltf"), Default::default()),
        "nope.gltf",
    );
}

#[test]
fn skippable_problems_are_warnings() {
    // NaN vertex: its triangle is skipped, the other stays.
    let s = load_edit(|_, b| b[12..16].copy_from_slice(&f32::NAN.to_le_bytes())).unwrap();
    assert_eq!(s.instanced_triangle_count(), 1);
    assert!(s.warnings.iter().any(|w| w.contains("NaN")));
    // Points are not surfaces.
    let s = load_edit(|d, _| {
        let p = d["meshes"][0]["primitives"][0].clone();
        let mut pts = p.clone();
        pts["mode"] = json!(0);
        d["meshes"][0]["primitives"] = json!([p, pts]);
    })
    .unwrap();
    assert_eq!(s.meshes.len(), 1);
    assert!(s.warnings.iter().any(|w| w.contains("Points")));
    // A missing texture: warned, the factor is used.
    let s = load_edit(|d, _| {
        d["images"] = json!([{"uri": "nowhere.png"}]);
        d["textures"] = json!([{"source": 0}]);
        d["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": 0});
    })
    .unwrap();
    assert!(s.materials[0].base_color_texture.is_none());
    assert!(s.warnings.iter().any(|w| w.contains("nowhere.png")));
    // Absurd transforms: skipped with a warning; the import fails only if nothing is left.
    let r = load_edit(|d, _| d["nodes"][0]["scale"] = json!([0, 0, 0]));
    expect_invalid(r, "no usable triangles");
    let s = load_edit(|d, _| {
        d["scenes"][0]["nodes"] = json!([0, 1]);
        d["nodes"] = json!([{"mesh": 0}, {"mesh": 0, "translation": [1e30, 0, 0]}]);
    })
    .unwrap();
    assert_eq!(s.instances.len(), 1);
    assert!(s.warnings.iter().any(|w| w.contains("absurd")));
    // Strict mode turns the first warning into an error.
    let dir = tempfile::tempdir().unwrap();
    let (doc, bin) = quad_gltf(|_, b| b[12..16].copy_from_slice(&f32::NAN.to_le_bytes()));
    let p = write(dir.path(), "s.gltf", &doc, &bin);
    expect_invalid(load(&p, ImportOptions { strict: true }), "strict");
}

#[test]
fn every_truncated_glb_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let s = aggtool::gen::GenSettings {
        triangles: 200,
        ..Default::default()
    };
    let (p, _) = aggtool::gen::write("foliage", &s, dir.path(), false).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    let t = dir.path().join("t.glb");
    let step = (bytes.len() / 300).max(1);
    for n in (0..bytes.len()).step_by(step) {
        std::fs::write(&t, &bytes[..n]).unwrap();
        // Must return (an error or, for a prefix that happens to be complete, a scene): never panic.
        let _ = load(&t, Default::default());
    }
}

/// 32-bit indices are read exactly: through f32 (as they once were) 16,777,217 rounds to
/// 16,777,216, another vertex. Seen while fuzzing the accessor reader; the out-of-range error
/// shows the index as read.
#[test]
fn u32_indices_are_exact() {
    let r = load_edit(|d, b| {
        d["accessors"][2]["componentType"] = json!(5125);
        d["accessors"][2]["count"] = json!(3);
        b.truncate(80);
        for i in [0u32, 1, 16_777_217] {
            b.extend(i.to_le_bytes());
        }
    });
    expect_invalid(r, "vertex index 16777217 out of range (4 vertices)");
}
