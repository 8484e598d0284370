//! Fuzzes the glTF importer on whole files in memory (`aggtool::import::load_gltf_slice`: the
//! `.glb`/`.gltf` parse, our validation, buffers, our accessor reader with its quantized,
//! normalized, strided and sparse forms, primitives, node hierarchies, EXT_mesh_gpu_instancing,
//! materials and embedded textures). Any bytes must give a clean `ImportError` or a scene that
//! the bake and the renderers can use without checking it again: indices in range, finite
//! transforms, per-vertex arrays as long as the positions.
//!
//! ```text
//! aggtool gen plane45 -o /tmp/corpus/gltf --triangles 300 --quantize   # seeds: small GLBs
//! cp ../shared/assets/kenney_city_kit/pavement.glb tests/data/fuzz/gltf/* /tmp/corpus/gltf/
//! cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run gltf /tmp/corpus/gltf -- -max_total_time=900
//! ```
//! The importer is called without the `catch_unwind` of `aggtool::import::load`, so that every
//! panic is a finding. Relative URIs resolve against a folder that does not exist.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("/nonexistent-aggtool-fuzz/input.glb");
    if let Ok(scene) = aggtool::import::load_gltf_slice(data, path) {
        check_scene(&scene);
    }
});

/// What the importer promises about every scene it returns.
fn check_scene(scene: &aggtool::scene::Scene) {
    for (k, m) in scene.meshes.iter().enumerate() {
        let n = m.positions.len();
        assert!(!m.triangles.is_empty(), "mesh {k}: no triangles");
        assert!(
            m.triangles.iter().flatten().all(|&i| (i as usize) < n),
            "mesh {k}: vertex index out of range"
        );
        assert!(
            m.normals.is_empty() || m.normals.len() == n,
            "mesh {k}: normals"
        );
        assert!(m.uvs.is_empty() || m.uvs.len() == n, "mesh {k}: uvs");
        assert!(
            (m.material as usize) < scene.materials.len(),
            "mesh {k}: material"
        );
    }
    for (k, inst) in scene.instances.iter().enumerate() {
        assert!(
            (inst.mesh as usize) < scene.meshes.len(),
            "instance {k}: mesh"
        );
        assert!(inst.transform.is_finite(), "instance {k}: transform");
    }
    for (k, mat) in scene.materials.iter().enumerate() {
        for t in [
            &mat.base_color_texture,
            &mat.metallic_roughness_texture,
            &mat.specular_texture,
        ]
        .into_iter()
        .flatten()
        {
            assert!(
                (t.texture as usize) < scene.textures.len(),
                "material {k}: texture"
            );
        }
    }
    let _ = scene.summary();
}
