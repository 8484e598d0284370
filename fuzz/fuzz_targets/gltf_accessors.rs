//! Fuzzes the glTF importer's own accessor reader from deep inside: the input is not a file but
//! a description (`arbitrary`) of accessors over one binary buffer, which the target writes as
//! a well-formed GLB (valid JSON, every index in range, the buffer's bytes from the input) and
//! imports with `aggtool::import::load_gltf_slice`. So the fuzzer spends its time on counts,
//! offsets, strides, component types, normalization, sparse substitution, index buffers,
//! primitive modes and EXT_mesh_gpu_instancing attributes, never on JSON syntax (the `gltf`
//! target does that).
//!
//! ```text
//! cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run gltf_accessors /tmp/corpus/gltf_accessors -- -max_total_time=900
//! ```
//! (it needs no seeds; `cargo fuzz fmt gltf_accessors FILE` prints an input as its description.)
#![no_main]

use std::path::Path;

use arbitrary::Arbitrary;
use libfuzzer_sys::fuzz_target;
use serde_json::{json, Value};

/// A byte range of the buffer, as a glTF buffer view.
#[derive(Arbitrary, Debug)]
struct View {
    /// Taken modulo the buffer's length + 1 (so that most views fit in the buffer) unless
    /// `raw`, which probes the reader's range checks.
    offset: u16,
    length: u16,
    raw: bool,
    /// Written as a valid glTF stride: 4 × (1 + stride % 63), in 4..=252.
    stride: Option<u8>,
}

/// Mostly small counts, sometimes any: big ones probe overflow and allocation bounds.
#[derive(Arbitrary, Debug)]
enum Count {
    Small(u8),
    Any(u32),
}

#[derive(Arbitrary, Debug)]
struct Sparse {
    count: Count,
    indices: View,
    indices_offset: u8,
    /// U8, U16 or U32 (taken modulo 3).
    index_type: u8,
    values: View,
    values_offset: u8,
}

#[derive(Arbitrary, Debug)]
struct Accessor {
    /// None: no buffer view (zeros, then the sparse values).
    view: Option<View>,
    offset: u16,
    count: Count,
    /// One of the six glTF component types (taken modulo 6).
    component: u8,
    /// SCALAR, VEC2, VEC3, VEC4, MAT2, MAT3, MAT4 (modulo 7).
    kind: u8,
    normalized: bool,
    sparse: Option<Sparse>,
}

/// A primitive; accessor references are taken modulo the number of accessors.
#[derive(Arbitrary, Debug)]
struct Primitive {
    /// glTF mode 0..=6 (modulo 7): points, lines, line loop, line strip, triangles, strip, fan.
    mode: u8,
    position: u8,
    normal: Option<u8>,
    texcoord: Option<u8>,
    indices: Option<u8>,
}

#[derive(Arbitrary, Debug)]
struct Input {
    accessors: Vec<Accessor>,
    primitives: Vec<Primitive>,
    /// EXT_mesh_gpu_instancing on the first node: TRANSLATION, ROTATION, SCALE accessors.
    instancing: Option<[Option<u8>; 3]>,
    /// The binary chunk (the rest of the input).
    buffer: Vec<u8>,
}

const COMPONENTS: [u32; 6] = [5120, 5121, 5122, 5123, 5125, 5126];
const KINDS: [&str; 7] = ["SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT3", "MAT4"];
const INDEX_TYPES: [u32; 3] = [5121, 5123, 5125];

fn count(c: &Count) -> u64 {
    match *c {
        Count::Small(n) => n as u64,
        Count::Any(n) => n as u64,
    }
}

fn view(views: &mut Vec<Value>, v: &View, buffer_len: usize) -> usize {
    let (mut offset, mut length) = (v.offset as usize, v.length as usize);
    if !v.raw {
        offset %= buffer_len + 1;
        length %= buffer_len - offset + 1;
    }
    let mut j = json!({"buffer": 0, "byteOffset": offset, "byteLength": length});
    if let Some(s) = v.stride {
        j["byteStride"] = json!(4 * (1 + s as usize % 63));
    }
    views.push(j);
    views.len() - 1
}

fn glb(input: &Input) -> Option<Vec<u8>> {
    if input.accessors.is_empty() || input.accessors.len() > 16 || input.primitives.len() > 8 {
        return None;
    }
    let n = input.accessors.len();
    let len = input.buffer.len();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    for a in &input.accessors {
        let mut j = json!({
            "componentType": COMPONENTS[a.component as usize % 6],
            "type": KINDS[a.kind as usize % 7],
            "count": count(&a.count),
            // Required on POSITION accessors (as 3 floats), and harmless on the others.
            "min": [0.0, 0.0, 0.0],
            "max": [1.0, 1.0, 1.0],
        });
        if a.normalized {
            j["normalized"] = json!(true);
        }
        if let Some(v) = &a.view {
            j["bufferView"] = json!(view(&mut views, v, len));
            j["byteOffset"] = json!(a.offset);
        }
        if let Some(s) = &a.sparse {
            j["sparse"] = json!({
                "count": count(&s.count),
                "indices": {"bufferView": view(&mut views, &s.indices, len),
                            "byteOffset": s.indices_offset,
                            "componentType": INDEX_TYPES[s.index_type as usize % 3]},
                "values": {"bufferView": view(&mut views, &s.values, len),
                           "byteOffset": s.values_offset},
            });
        }
        accessors.push(j);
    }
    let mut meshes = Vec::new();
    for p in &input.primitives {
        let mut attributes = json!({"POSITION": p.position as usize % n});
        if let Some(a) = p.normal {
            attributes["NORMAL"] = json!(a as usize % n);
        }
        if let Some(a) = p.texcoord {
            attributes["TEXCOORD_0"] = json!(a as usize % n);
        }
        let mut prim = json!({"attributes": attributes, "mode": p.mode % 7});
        if let Some(a) = p.indices {
            prim["indices"] = json!(a as usize % n);
        }
        meshes.push(json!({"primitives": [prim]}));
    }
    let mut nodes: Vec<Value> = (0..meshes.len()).map(|m| json!({"mesh": m})).collect();
    if let (Some(inst), Some(first)) = (&input.instancing, nodes.first_mut()) {
        let mut attributes = json!({});
        for (name, a) in ["TRANSLATION", "ROTATION", "SCALE"].iter().zip(inst) {
            if let Some(a) = a {
                attributes[*name] = json!(*a as usize % n);
            }
        }
        first["extensions"] = json!({"EXT_mesh_gpu_instancing": {"attributes": attributes}});
    }
    let doc = json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_mesh_quantization", "EXT_mesh_gpu_instancing"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scene": 0,
        "scenes": [{"nodes": (0..nodes.len()).collect::<Vec<_>>()}],
        "nodes": nodes,
        "meshes": meshes,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": input.buffer.len()}],
    });
    let glb = gltf::binary::Glb {
        header: gltf::binary::Header {
            magic: *b"glTF",
            version: 2,
            length: 0,
        },
        json: serde_json::to_vec(&doc).ok()?.into(),
        bin: Some(input.buffer.as_slice().into()),
    };
    glb.to_vec().ok()
}

fuzz_target!(|input: Input| {
    let Some(bytes) = glb(&input) else {
        return;
    };
    let path = Path::new("/nonexistent-aggtool-fuzz/accessors.glb");
    if let Some(out) = std::env::var_os("FUZZ_GLB") {
        // To keep a finding as a GLB (tests/data/fuzz/gltf/): FUZZ_GLB=x.glb cargo fuzz run …
        std::fs::write(out, &bytes).expect("FUZZ_GLB: cannot write");
    }
    let debug = std::env::var_os("FUZZ_DEBUG").is_some();
    if debug {
        // To see what an input becomes: FUZZ_DEBUG=1 cargo fuzz run gltf_accessors INPUT
        eprintln!(
            "{}",
            String::from_utf8_lossy(&bytes[20..bytes.len().min(4000)])
        );
    }
    let result = aggtool::import::load_gltf_slice(&bytes, path);
    if debug {
        match &result {
            Ok(s) => eprintln!("imported: {}", s.summary()),
            Err(e) => eprintln!("refused: {e}"),
        }
    }
    if let Ok(scene) = result {
        for m in &scene.meshes {
            let n = m.positions.len();
            assert!(m.triangles.iter().flatten().all(|&i| (i as usize) < n));
            assert!(m.normals.is_empty() || m.normals.len() == n);
            assert!(m.uvs.is_empty() || m.uvs.len() == n);
        }
        for inst in &scene.instances {
            assert!((inst.mesh as usize) < scene.meshes.len());
            assert!(inst.transform.is_finite());
        }
    }
});
