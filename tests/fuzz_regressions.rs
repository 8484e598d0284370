//! Inputs the fuzz targets (fuzz/fuzz_targets/gltf.rs, gltf_accessors.rs) once crashed, hung
//! or exhausted memory with, kept small in tests/data/fuzz/gltf/: each must give the
//! stated clean error through the public API, never a panic (the importer's `catch_unwind`
//! would turn a panic into "internal parser failure", which no expected message matches).
//! tests/fuzz-regressions/ holds the `.agg` reader's (tests/format.rs); the manifest target
//! (fuzz/fuzz_targets/manifest.rs) has found nothing yet.

use std::path::{Path, PathBuf};

use aggtool::import::{load, ImportOptions};

fn dir(kind: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/fuzz")
        .join(kind)
}

/// Every file of `tests/data/fuzz/KIND`, so that a new regression cannot be left out of `cases`.
fn files(kind: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir(kind))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    v.sort();
    v
}

/// glTF importer: (file, what its error must say).
/// - `glb-length-below-header.glb` (gltf, minimised by hand): a GLB header declaring a total
///   length under its own 12 bytes; the `gltf` crate's reader subtracted unchecked (a panic
///   where overflow checks are on).
/// - `image-view-no-mimetype.gltf` (gltf, minimised by hand): a texture's image in a
///   bufferView without the mimeType the spec requires; the `gltf` crate unwraps it.
/// - `image-no-source.gltf` (the same unwrap's other branch, seen in the crate's code): an
///   image with neither a uri nor a bufferView.
/// - `instancing-scalar-translation.gltf` (gltf_accessors): an EXT_mesh_gpu_instancing
///   TRANSLATION accessor of type SCALAR was read as VEC3: index out of bounds.
/// - `viewless-huge-count.gltf` (gltf_accessors): an accessor without a buffer view (zeros plus
///   one sparse value) declaring 2³² − 1 VEC3 elements: a 48 GiB allocation from 500 bytes.
/// - `position-no-accessor.gltf` (gltf, minimised by hand from a mutated GLB): a POSITION
///   naming an accessor that does not exist panicked inside gltf-json's own validation.
/// - `uri-dev-zero.gltf` (seen while writing the `gltf` target, which lets URIs reach the file
///   system): a buffer URI naming /dev/zero was read until memory ran out.
#[test]
fn gltf_regressions_give_clean_errors() {
    let cases = [
        (
            "glb-length-below-header.glb",
            "the GLB header declares 0 bytes, fewer than its own 12",
        ),
        (
            "image-view-no-mimetype.gltf",
            "images[0]: an image in a bufferView needs a mimeType",
        ),
        (
            "image-no-source.gltf",
            "images[0]: neither a uri nor a bufferView",
        ),
        (
            "instancing-scalar-translation.gltf",
            "TRANSLATION accessor 1 has 1 components per element, not 3",
        ),
        (
            "viewless-huge-count.gltf",
            "no buffer view and declares 4294967295 elements",
        ),
        (
            "position-no-accessor.gltf",
            "POSITION: accessor 0 does not exist (0 accessors)",
        ),
        ("uri-dev-zero.gltf", "/dev/zero"),
    ];
    let mut names: Vec<String> = cases.iter().map(|c| c.0.to_string()).collect();
    names.sort();
    assert_eq!(
        files("gltf"),
        names,
        "a file in tests/data/fuzz/gltf is not in `cases`"
    );
    for (name, needle) in cases {
        let path = dir("gltf").join(name);
        match load(&path, ImportOptions::default()) {
            Ok(_) => panic!("{name}: imported, expected an error mentioning '{needle}'"),
            Err(e) => {
                let msg = e.to_string();
                assert!(
                    msg.contains(needle),
                    "{name}: '{msg}' should mention '{needle}'"
                );
                assert!(msg.contains(name), "{name}: '{msg}' should name the file");
            }
        }
    }
}
