//! Every shared asset imports with sane counts, bounds and materials (skips when
//! ../shared/assets is absent).

mod common;

use aggtool::import::{load, ImportOptions};

/// Every mesh file under ../shared/assets, sorted; none (after saying that `test` skipped) when
/// the folder is absent.
fn assets(test: &str) -> Vec<std::path::PathBuf> {
    let Some(root) = common::shared_assets(test) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    let mut stack = vec![root];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if matches!(
                p.extension().and_then(|e| e.to_str()),
                Some("glb" | "gltf" | "obj")
            ) {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn every_shared_asset_imports_sanely() {
    let list = assets("every_shared_asset_imports_sanely");
    for path in &list {
        let scene = load(path, ImportOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        let tris = scene.instanced_triangle_count();
        assert!(tris > 0, "{}", path.display());
        let (lo, hi) = scene.bounds();
        let ext = hi - lo;
        assert!(
            lo.is_finite() && hi.is_finite(),
            "{}: bounds {lo} {hi}",
            path.display()
        );
        assert!(
            ext.max_element() > 1e-3 && ext.max_element() < 1e4,
            "{}: extent {ext}",
            path.display()
        );
        assert!(scene.world_area() > 0.0);
        for m in &scene.meshes {
            assert!(m.positions.iter().all(|p| p.is_finite()));
            assert!(m.normals.is_empty() || m.normals.len() == m.positions.len());
            assert!(m.uvs.is_empty() || m.uvs.len() == m.positions.len());
            assert!((m.material as usize) < scene.materials.len());
            assert!(m
                .triangles
                .iter()
                .flatten()
                .all(|&i| (i as usize) < m.positions.len()));
        }
        for mat in &scene.materials {
            let p = mat.eval(&scene.textures, glam::Vec2::new(0.3, 0.7));
            assert!(p.base_color.is_finite() && p.base_color.max_element() <= 1.0);
            assert!((0.0..=1.0).contains(&p.metallic) && (0.0..=1.0).contains(&p.alpha));
        }
    }
    if !list.is_empty() {
        assert!(
            list.len() >= 30,
            "expected the whole shared asset set, found {}",
            list.len()
        );
    }
}

/// Counts and materials of the assets the issues name, against the asset README.
#[test]
fn known_assets_have_expected_content() {
    let Some(root) = common::shared_assets("known_assets_have_expected_content") else {
        return;
    };
    let chandelier = load(
        &root.join("sh3d_chandelier_scopia/chandelier-lamp.obj"),
        Default::default(),
    )
    .unwrap();
    // The README counts 133,112 triangles; none are degenerate.
    assert_eq!(chandelier.instanced_triangle_count(), 133_112);
    let metal = chandelier
        .materials
        .iter()
        .find(|m| m.name == "black-metal")
        .unwrap();
    assert!(
        metal.metallic > 0.9,
        "black-metal maps to a metal: {}",
        metal.metallic
    );
    let plastic = chandelier
        .materials
        .iter()
        .find(|m| m.name == "white-plastic")
        .unwrap();
    assert_eq!(plastic.metallic, 0.0);
    assert!(chandelier.warnings.iter().any(|w| w.contains("d < 1")));

    let maple = load(
        &root.join("sh3d_japanese_maple_scopia/japaneseMaple.obj"),
        Default::default(),
    )
    .unwrap();
    assert!((198_000..=198_402).contains(&maple.instanced_triangle_count()));
    assert_eq!(maple.textures.len(), 1, "the diffuse atlas is loaded once");
    let trunk = maple.materials.iter().find(|m| m.name == "Trunk").unwrap();
    assert_eq!(trunk.specular_factor, 0.0, "Ks 0 is Lambertian");

    // Kenney's city kit declares KHR_texture_transform (an identity one) on its colour map.
    let kenney = load(
        &root.join("kenney_city_kit/road-straight.glb"),
        Default::default(),
    )
    .unwrap();
    assert!(kenney
        .materials
        .iter()
        .any(|m| m.base_color_texture.is_some()));
    assert_eq!(kenney.textures.len(), 1);

    // The fern's leaves are alpha cut-outs with textures.
    let fern = load(
        &root.join("polyhaven_fern_moss/fern_02.glb"),
        Default::default(),
    )
    .unwrap();
    assert!(fern
        .materials
        .iter()
        .any(|m| m.has_cutout() && m.base_color_texture.is_some()));
}
