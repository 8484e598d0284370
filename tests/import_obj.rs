//! OBJ/MTL import: the Phong to metallic-roughness mapping and bad input.

use aggtool::import::load;

fn write(dir: &std::path::Path, obj: &str, mtl: Option<&str>) -> std::path::PathBuf {
    if let Some(m) = mtl {
        std::fs::write(dir.join("a.mtl"), m).unwrap();
    }
    let p = dir.join("a.obj");
    std::fs::write(&p, obj).unwrap();
    p
}

const QUAD: &str = "mtllib a.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3 4/4\n";

#[test]
fn phong_mapping() {
    let d = tempfile::tempdir().unwrap();
    // Dark diffuse, bright specular: a metal; Ns 98 gives α = sqrt(2/100).
    let s = load(
        &write(
            d.path(),
            QUAD,
            Some("newmtl m\nKd 0.03 0.03 0.03\nKs 0.7 0.7 0.7\nNs 98\n"),
        ),
        Default::default(),
    )
    .unwrap();
    assert_eq!(s.instanced_triangle_count(), 2, "the quad is triangulated");
    let p = s.materials[0].eval(&s.textures, glam::Vec2::ZERO);
    assert!(p.metallic > 0.9);
    assert!(
        (p.alpha - (2.0f32 / 100.0).sqrt()).abs() < 1e-4,
        "{}",
        p.alpha
    );
    // Ks 0: Lambertian.
    let s = load(
        &write(
            d.path(),
            QUAD,
            Some("newmtl m\nKd 0.8 0.2 0.1\nKs 0 0 0\nNs 10\n"),
        ),
        Default::default(),
    )
    .unwrap();
    let p = s.materials[0].eval(&s.textures, glam::Vec2::ZERO);
    assert_eq!((p.metallic, p.specular, p.f90), (0.0, 0.0, 0.0));
    assert_eq!(p.base_color, glam::Vec3::new(0.8, 0.2, 0.1));
    // PBR keys win.
    let s = load(
        &write(
            d.path(),
            QUAD,
            Some("newmtl m\nKd 0.8 0.8 0.8\nKs 0.5 0.5 0.5\nPr 0.5\nPm 0.25\n"),
        ),
        Default::default(),
    )
    .unwrap();
    let p = s.materials[0].eval(&s.textures, glam::Vec2::ZERO);
    assert!((p.alpha - 0.25).abs() < 1e-6 && (p.metallic - 0.25).abs() < 1e-6);
}

#[test]
fn problems_are_warned_or_rejected() {
    let d = tempfile::tempdir().unwrap();
    // Missing material library: default material, warning.
    let s = load(&write(d.path(), QUAD, None), Default::default()).unwrap();
    assert!(s.warnings.iter().any(|w| w.contains("material library")));
    // Missing texture: warning, factor kept.
    let s = load(
        &write(
            d.path(),
            QUAD,
            Some("newmtl m\nKd 0.5 0.5 0.5\nmap_Kd gone.png\n"),
        ),
        Default::default(),
    )
    .unwrap();
    assert!(s.materials[0].base_color_texture.is_none());
    assert!(s.warnings.iter().any(|w| w.contains("gone.png")));
    // Glass: warned, opaque.
    let s = load(
        &write(d.path(), QUAD, Some("newmtl m\nKd 0.5 0.5 0.5\nd 0.3\n")),
        Default::default(),
    )
    .unwrap();
    assert!(s.warnings.iter().any(|w| w.contains("d < 1")));
    // NaN vertex: its triangle goes, the other stays.
    let obj = QUAD.replace("v 1 0 0", "v nan 0 0");
    let s = load(
        &write(d.path(), &obj, Some("newmtl m\n")),
        Default::default(),
    )
    .unwrap();
    assert_eq!(s.instanced_triangle_count(), 1);
    assert!(s.warnings.iter().any(|w| w.contains("NaN")));
    // Garbage: an error naming the file.
    let p = write(d.path(), "f 1 2 3\nv x y z\n", None);
    let e = load(&p, Default::default()).err().expect("error");
    assert!(e.to_string().contains("a.obj"), "{e}");
}

/// A texture with the image's v axis flipped as OBJ requires: vt (0, 1) is the image's top row.
#[test]
fn obj_texture_orientation() {
    let d = tempfile::tempdir().unwrap();
    // 1x2 image: top red, bottom blue.
    image::RgbaImage::from_raw(1, 2, vec![255, 0, 0, 255, 0, 0, 255, 255])
        .unwrap()
        .save(d.path().join("t.png"))
        .unwrap();
    let s = load(
        &write(d.path(), QUAD, Some("newmtl m\nKd 1 1 1\nmap_Kd t.png\n")),
        Default::default(),
    )
    .unwrap();
    let m = &s.meshes[0];
    // Vertex 4 has vt (0, 1): the image's top-left corner.
    assert_eq!(m.uvs[3], glam::Vec2::new(0.0, 0.0));
    // The upper half of the texture (v < 0.5 after the flip) is red.
    let top = s.materials[0]
        .eval(&s.textures, glam::Vec2::new(0.5, 0.25))
        .base_color;
    assert!(top.x > 0.9 && top.z < 0.1, "{top}");
}
