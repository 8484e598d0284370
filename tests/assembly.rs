//! Assemblies (issue 18): manifest errors through the library, an instance renders as its asset
//! wherever it is placed (translated, rotated, scaled), an opaque wall instance hides an
//! instance behind it and casts its shadow on another, the reference renders the same
//! instances, and a 100,000-instance manifest parses and renders. The hybrid representation:
//! a screen of thin rods lets 1 − coverage through (aggregate and mesh), a mesh instance and
//! an aggregate instance shadow each other, `--no-mesh` is the aggregate-only render and a
//! far view renders the same with meshes allowed, an aggregate in front of a mesh passes it on
//! through its ABV, and tracing allocates nothing per cone.
//!
//! Bakes are tiny (16³ finest level) so that the file runs in seconds.

mod common;

use std::path::{Path, PathBuf};

use aggtool::assembly::{self, Assembly, Manifest, ManifestError};
use aggtool::bake::{bake_to_file, BakeSettings};
use aggtool::film::{Camera, Image};
use aggtool::gen::glb::{to_glb, MaterialData, SceneData};
use aggtool::gen::{generate, shapes, GenSettings};
use aggtool::lights::{Environment, Lights, Sun};
use aggtool::render::compare::compare;
use aggtool::runtime::{Cone, LodScene, TraceSettings};
use aggtool::util::no_progress;
use glam::{Affine3A, Quat, Vec3};

fn tiny() -> BakeSettings {
    BakeSettings {
        max_res: 16,
        min_res: 4,
        samples: 8,
        aiv_res: 8,
        aiv_rays: 4,
        abv_res: 8,
        abv_full_res: 8,
        ..Default::default()
    }
}

/// Writes `data` as `dir/name.glb` and bakes `dir/name.agg` beside it.
fn asset(dir: &Path, name: &str, data: &SceneData) -> PathBuf {
    let glb = dir.join(format!("{name}.glb"));
    std::fs::write(&glb, to_glb(data, false)).unwrap();
    let scene = aggtool::import::load(&glb, Default::default()).unwrap();
    bake_to_file(
        &scene,
        name,
        &tiny(),
        &glb.with_extension("agg"),
        &no_progress,
    )
    .unwrap();
    glb
}

fn tree(dir: &Path) -> PathBuf {
    let data = generate(
        "foliage",
        &GenSettings {
            triangles: 2000,
            ..Default::default()
        },
    )
    .unwrap();
    asset(dir, "tree", &data)
}

/// An opaque white box of the given half extents, centred at the origin.
fn slab(dir: &Path, name: &str, half: Vec3) -> PathBuf {
    let mut data = SceneData::single(
        shapes::cuboid(Vec3::ZERO, half, 2),
        MaterialData::new("white", [0.8, 0.8, 0.8], 0.0, 1.0),
    );
    data.make_lambertian();
    asset(dir, name, &data)
}

/// Writes a manifest: assets as (id, source file name), instances as (id, transform).
fn manifest(dir: &Path, name: &str, assets: &[(&str, &str)], inst: &[(&str, Affine3A)]) -> PathBuf {
    let assets: serde_json::Map<String, serde_json::Value> = assets
        .iter()
        .map(|(id, src)| (id.to_string(), serde_json::json!({ "source": src })))
        .collect();
    let instances: Vec<_> = inst
        .iter()
        .map(|(id, m)| serde_json::json!({ "asset": id, "matrix": assembly::matrix_json(m) }))
        .collect();
    let p = dir.join(name);
    std::fs::write(
        &p,
        serde_json::to_string(
            &serde_json::json!({ "version": 1, "assets": assets, "instances": instances }),
        )
        .unwrap(),
    )
    .unwrap();
    p
}

/// A sun from straight above and a dim constant sky: invariant under rotations about +Y.
fn lights() -> Lights {
    Lights {
        environment: Environment::Constant(Vec3::splat(0.2)),
        sun: Some(Sun {
            direction: Vec3::Y,
            irradiance: Vec3::splat(2.0),
        }),
    }
}

fn camera(m: Affine3A, w: u32, h: u32) -> Camera {
    Camera::look_at(
        m.transform_point3(Vec3::new(0.6, 1.2, 2.6)),
        m.transform_point3(Vec3::new(0.0, 0.6, 0.0)),
        Vec3::Y,
        40.0,
        w,
        h,
    )
}

fn render_asm(asm: &Assembly, cam: &Camera, spp: u32) -> Image {
    assembly::render(
        asm,
        cam,
        &lights(),
        spp,
        7,
        &TraceSettings::default(),
        &no_progress,
    )
    .0
}

fn render_single(agg: &Path, cam: &Camera, spp: u32) -> Image {
    let s = LodScene::open(agg).unwrap();
    aggtool::runtime::render(
        &s,
        cam,
        &lights(),
        spp,
        7,
        &TraceSettings::default(),
        &no_progress,
    )
    .0
}

#[test]
fn manifest_errors_name_the_asset_or_instance() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("a.glb"), b"not used").unwrap();
    // The aggregate of asset 'a' (a.agg by default) is missing: opening names the asset.
    let p = manifest(d, "m.json", &[("a", "a.glb")], &[("a", Affine3A::IDENTITY)]);
    match Assembly::open(&p) {
        Err(assembly::AssemblyError::Manifest(ManifestError::MissingFile {
            asset, what, ..
        })) => {
            assert_eq!((asset.as_str(), what), ("a", "aggregate"))
        }
        Err(e) => panic!("wrong error: {e}"),
        Ok(_) => panic!("opened without its aggregate"),
    }
    // A corrupt aggregate: an open error naming the asset.
    std::fs::write(d.join("a.agg"), b"garbage").unwrap();
    let e = Assembly::open(&p)
        .err()
        .expect("opened a corrupt aggregate")
        .to_string();
    assert!(e.contains("asset 'a'"), "{e}");
    // Singular, unknown asset, bad version.
    let p = manifest(
        d,
        "m2.json",
        &[("a", "a.glb")],
        &[
            ("a", Affine3A::IDENTITY),
            ("a", Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0))),
        ],
    );
    let e = Manifest::load(&p).unwrap_err();
    assert!(
        matches!(e, ManifestError::BadTransform { index: 1, .. }),
        "{e}"
    );
    let p = manifest(
        d,
        "m3.json",
        &[("a", "a.glb")],
        &[("b", Affine3A::IDENTITY)],
    );
    let e = Manifest::load(&p).unwrap_err();
    assert!(
        matches!(&e, ManifestError::UnknownAsset { index: 0, asset, .. } if asset == "b"),
        "{e}"
    );
    std::fs::write(
        d.join("m4.json"),
        r#"{"version": 3, "assets": {}, "instances": []}"#,
    )
    .unwrap();
    let e = Manifest::load(&d.join("m4.json")).unwrap_err();
    assert!(
        matches!(e, ManifestError::BadVersion { version: 3, .. }),
        "{e}"
    );
    let e = Manifest::load(&d.join("absent.json")).unwrap_err();
    assert!(matches!(e, ManifestError::Io { .. }), "{e}");
}

/// Two instances of one asset, one at the origin and one moved, turned a quarter about +Y
/// and doubled in size: seen from cameras placed the same way, each renders as the asset alone
/// (the other is out of view and casts no shadow under a sun from straight above).
#[test]
fn two_instances_render_as_the_asset_twice() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let glb = tree(d);
    let agg = glb.with_extension("agg");
    let moved = Affine3A::from_scale_rotation_translation(
        Vec3::splat(2.0),
        Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
        Vec3::new(40.0, 0.0, -10.0),
    );
    let p = manifest(
        d,
        "two.json",
        &[("tree", "tree.glb")],
        &[("tree", Affine3A::IDENTITY), ("tree", moved)],
    );
    let asm = Assembly::open(&p).unwrap();
    let (w, h, spp) = (48, 48, 16);
    let single = render_single(&agg, &camera(Affine3A::IDENTITY, w, h), spp);
    let first = render_asm(&asm, &camera(Affine3A::IDENTITY, w, h), spp);
    let second = render_asm(&asm, &camera(moved, w, h), spp);
    let c1 = compare(&first, &single).unwrap();
    let c2 = compare(&second, &single).unwrap();
    // The same cones in the same space up to float rounding of the transforms; rounding can
    // flip a reservoir choice in a few pixels, which at 16 spp costs ~1e-3 relative MSE.
    // Measured: first 0.000000, second 0.000094.
    eprintln!("relmse: first {:.6}, second {:.6}", c1.relmse, c2.relmse);
    assert!(
        c1.relmse < 0.003,
        "first instance differs from the asset: {c1:?}"
    );
    assert!(
        c2.relmse < 0.003,
        "moved instance differs from the asset: {c2:?}"
    );
    // The check can fail: the moved instance seen from the unmoved camera's angle (turned a
    // quarter) differs from the asset by several times the tolerance (measured 0.023).
    let turned = render_asm(
        &asm,
        &camera(
            Affine3A::from_translation(moved.translation.into())
                * Affine3A::from_scale(Vec3::splat(2.0)),
            w,
            h,
        ),
        spp,
    );
    let c3 = compare(&turned, &single).unwrap();
    eprintln!(
        "relmse of the instance seen from a quarter turn: {:.4}",
        c3.relmse
    );
    assert!(c3.relmse > 0.01, "{c3:?}");
}

/// Mean of the pixels in the central square of side `frac` of the image.
fn centre_mean(img: &Image, frac: f32) -> f32 {
    let (w, h) = (img.width as f32, img.height as f32);
    let (mut s, mut n) = (0.0, 0);
    for y in 0..img.height {
        for x in 0..img.width {
            if ((x as f32 + 0.5) / w - 0.5).abs() < 0.5 * frac
                && ((y as f32 + 0.5) / h - 0.5).abs() < 0.5 * frac
            {
                let p = img.pixels[(y * img.width + x) as usize];
                s += (p.x + p.y + p.z) / 3.0;
                n += 1;
            }
        }
    }
    s / n as f32
}

/// An opaque wall between the camera and a tree hides the tree: the image of wall and tree
/// equals the wall's alone where the wall covers the view, while the tree alone shows there.
#[test]
fn an_opaque_wall_hides_an_instance_behind_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tree(d);
    slab(d, "wall", Vec3::new(1.0, 1.0, 0.15));
    // Wall at z = 1.5 between the camera (at z ≈ 2.6 + ...) and the tree at the origin.
    let wall = Affine3A::from_translation(Vec3::new(0.2, 0.6, 1.3));
    let assets = [("tree", "tree.glb"), ("wall", "wall.glb")];
    let both = Assembly::open(&manifest(
        d,
        "both.json",
        &assets,
        &[("tree", Affine3A::IDENTITY), ("wall", wall)],
    ))
    .unwrap();
    let wall_only = Assembly::open(&manifest(d, "wall.json", &assets, &[("wall", wall)])).unwrap();
    let tree_only = Assembly::open(&manifest(
        d,
        "tree.json",
        &assets,
        &[("tree", Affine3A::IDENTITY)],
    ))
    .unwrap();
    let cam = Camera::look_at(
        Vec3::new(0.0, 0.6, 4.0),
        Vec3::new(0.0, 0.6, 0.0),
        Vec3::Y,
        30.0,
        32,
        32,
    );
    let spp = 16;
    let (b, wl, t) = (
        render_asm(&both, &cam, spp),
        render_asm(&wall_only, &cam, spp),
        render_asm(&tree_only, &cam, spp),
    );
    let sky = render_asm(
        &Assembly::open(&manifest(d, "none.json", &assets, &[])).unwrap(),
        &cam,
        spp,
    );
    let (mb, mw, mt, ms) = (
        centre_mean(&b, 0.3),
        centre_mean(&wl, 0.3),
        centre_mean(&t, 0.3),
        centre_mean(&sky, 0.3),
    );
    eprintln!("centre means: both {mb:.4}, wall {mw:.4}, tree {mt:.4}, sky {ms:.4}");
    // The tree shows in the centre on its own (measured: 0.119 against the wall's 0.150).
    assert!(
        (mt - mw).abs() > 0.02,
        "tree {mt} vs wall {mw}: the test could not fail"
    );
    // Behind the wall it changes less than a tenth of that: what the wall's ABV lets through
    // (the wall is opaque, its boundary visibility ~0) and noise (measured: 0.0004, 1.3%).
    assert!(
        (mb - mw).abs() < 0.1 * (mt - mw).abs(),
        "both {mb} vs wall {mw}"
    );
}

/// An opaque slab above a floor, lit by a sun from straight above, darkens the floor under it:
/// light reaching the floor's voxels is attenuated by the other instance's ABV.
#[test]
fn an_opaque_instance_casts_its_shadow_on_another() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    slab(d, "floor", Vec3::new(2.0, 0.1, 2.0));
    slab(d, "roof", Vec3::new(0.6, 0.1, 0.6));
    let assets = [("floor", "floor.glb"), ("roof", "roof.glb")];
    let floor = Affine3A::IDENTITY;
    // The roof high above, out of view of a camera looking down at the floor's centre from
    // below the roof's height.
    let roof = Affine3A::from_translation(Vec3::new(0.0, 3.0, 0.0));
    let lights = Lights {
        environment: Environment::Constant(Vec3::ZERO),
        sun: Some(Sun {
            direction: Vec3::Y,
            irradiance: Vec3::splat(3.0),
        }),
    };
    let cam = Camera::look_at(
        Vec3::new(0.0, 2.0, 0.8),
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::Y,
        20.0,
        24,
        24,
    );
    let render = |inst: &[(&str, Affine3A)], name: &str| {
        let asm = Assembly::open(&manifest(d, name, &assets, inst)).unwrap();
        assembly::render(
            &asm,
            &cam,
            &lights,
            16,
            3,
            &TraceSettings::default(),
            &no_progress,
        )
        .0
    };
    let lit = render(&[("floor", floor)], "lit.json");
    let shaded = render(&[("floor", floor), ("roof", roof)], "shaded.json");
    let (ml, ms) = (centre_mean(&lit, 0.3), centre_mean(&shaded, 0.3));
    eprintln!("floor centre: lit {ml:.4}, under the roof {ms:.4}");
    assert!(ml > 0.1, "the lit floor is dark: {ml}");
    // The roof is opaque: its ABV lets (almost) nothing through.
    assert!(ms < 0.1 * ml, "lit {ml} vs shaded {ms}");
}

/// The reference renders the same instances: each mesh stored once, the image of two
/// instances of one asset side by side agreeing with the LoD render of the same manifest as
/// well as a single asset's LoD agrees with its reference.
#[test]
fn reference_renders_the_same_instances() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tree(d);
    let a = Affine3A::from_translation(Vec3::new(-0.8, 0.0, 0.0));
    let b =
        Affine3A::from_rotation_translation(Quat::from_rotation_y(1.0), Vec3::new(0.8, 0.0, 0.0));
    let p = manifest(
        d,
        "two.json",
        &[("tree", "tree.glb")],
        &[("tree", a), ("tree", b)],
    );
    let m = Manifest::load(&p).unwrap();
    let sources = assembly::mesh::load_sources(&m, Default::default()).unwrap();
    let scene = assembly::mesh::scene(&m, &sources);
    assert_eq!(
        scene.meshes.len(),
        sources[0].meshes.len(),
        "meshes are stored once"
    );
    assert_eq!(
        scene.instanced_triangle_count(),
        2 * sources[0].instanced_triangle_count()
    );
    let summary = assembly::mesh::summary(&m, true).unwrap();
    assert_eq!(
        summary.unique_triangles,
        Some(sources[0].unique_triangle_count() as u64)
    );
    assert_eq!(
        summary.instanced_triangles,
        Some(2 * sources[0].instanced_triangle_count() as u64)
    );
    assert!(summary.aggregate_bytes > 0);
    let accel = aggtool::trace::Accel::build(&scene);
    let cam = Camera::look_at(
        Vec3::new(0.0, 1.0, 4.0),
        Vec3::new(0.0, 0.6, 0.0),
        Vec3::Y,
        40.0,
        48,
        32,
    );
    let settings = aggtool::render::reference::ReferenceSettings { spp: 16, seed: 1 };
    let (reference, _) =
        aggtool::render::reference::render(&accel, &cam, &lights(), settings, &no_progress);
    let lod = render_asm(&Assembly::new(m).unwrap(), &cam, 16);
    // Single asset LoD against its reference, the yardstick.
    let (ref1, _) = {
        let s1 = aggtool::import::load(&d.join("tree.glb"), Default::default()).unwrap();
        let acc1 = aggtool::trace::Accel::build(&s1);
        let cam1 = camera(Affine3A::IDENTITY, 48, 32);
        let r = aggtool::render::reference::render(&acc1, &cam1, &lights(), settings, &no_progress);
        let l = render_single(&d.join("tree.agg"), &cam1, 16);
        (compare(&l, &r.0).unwrap(), ())
    };
    let c = compare(&lod, &reference).unwrap();
    eprintln!(
        "relmse: assembly LoD vs reference {:.4}; single asset {:.4}",
        c.relmse, ref1.relmse
    );
    // A 16³ bake is coarse; the assembly is held to the single asset's agreement with slack for
    // the different framing (measured in the report).
    assert!(
        c.relmse < 2.0 * ref1.relmse + 0.05,
        "{c:?} vs single {ref1:?}"
    );
}

/// A 100,000-instance manifest (a 316 × 317 grid of small trees) parses and renders a small
/// image.
#[test]
fn a_hundred_thousand_instances_parse_and_render() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tree(d);
    let mut s =
        String::from(r#"{"version":1,"assets":{"tree":{"source":"tree.glb"}},"instances":["#);
    for i in 0..100_000 {
        if i > 0 {
            s.push(',');
        }
        let (x, z) = ((i % 316) as f32 * 0.5, (i / 316) as f32 * 0.5);
        s.push_str(&format!(
            r#"{{"asset":"tree","translation":[{x},0,{z}],"rotation":[0,{},0,{}],"scale":[0.4,0.4,0.4]}}"#,
            (i as f32 * 0.1).sin(),
            (i as f32 * 0.1).cos()
        ));
    }
    s.push_str("]}");
    let p = d.join("forest.json");
    std::fs::write(&p, s).unwrap();
    let t = std::time::Instant::now();
    let asm = Assembly::open(&p).unwrap();
    let open = t.elapsed().as_secs_f64();
    assert_eq!(asm.manifest().instance_count(), 100_000);
    // Above the forest's corner, looking across it.
    let cam = Camera::look_at(
        Vec3::new(-5.0, 6.0, -5.0),
        Vec3::new(60.0, 0.0, 60.0),
        Vec3::Y,
        50.0,
        32,
        16,
    );
    let t = std::time::Instant::now();
    let (img, stats) = assembly::render(
        &asm,
        &cam,
        &lights(),
        2,
        7,
        &TraceSettings::default(),
        &no_progress,
    );
    let render = t.elapsed().as_secs_f64();
    eprintln!("100k instances: opened in {open:.2} s, 32x16 at 2 spp in {render:.2} s");
    common::assert_clean_render(&img, &stats, "100k instances");
    // Trees fill the lower half (darker than the sky of 0.2 + sun): not the empty sky image.
    let sky = lights().environment.eval(Vec3::Y);
    let differs = img
        .pixels
        .iter()
        .filter(|p| (**p - sky).abs().max_element() > 0.02)
        .count();
    assert!(
        differs > img.pixels.len() / 4,
        "only {differs} pixels show trees"
    );
    // Only coarse levels for trees this small and far (the lazy paging at work).
    assert!(!asm.scene(0).prepared().is_empty());
}

/// `gen forest` is deterministic, `assemble` bakes what is missing and reuses what is up to
/// date (rebaking when the settings change), and the LoD render of the forest (trees standing
/// on a ground whose bounds hold them all) agrees with the reference.
#[test]
fn forest_generates_assembles_and_renders_like_the_reference() {
    use aggtool::assembly::{bake::assemble, forest};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let r = forest::write(&d.join("f"), 2, 25, 1500, 1).unwrap();
    let r2 = forest::write(&d.join("g"), 2, 25, 1500, 1).unwrap();
    for (a, b) in r
        .assets
        .iter()
        .chain([&r.manifest])
        .zip(r2.assets.iter().chain([&r2.manifest]))
    {
        assert_eq!(
            std::fs::read(a).unwrap(),
            std::fs::read(b).unwrap(),
            "{}",
            a.display()
        );
    }
    let m = Manifest::load(&r.manifest).unwrap();
    assert_eq!(m.instance_count(), 26, "25 trees and the ground");
    let quiet = |_: &assembly::bake::Outcome| {};
    let first = assemble(&m, &tiny(), Default::default(), &quiet).unwrap();
    assert!(first
        .iter()
        .all(|o| o.baked && o.reason.as_deref() == Some("missing")));
    let again = assemble(&m, &tiny(), Default::default(), &quiet).unwrap();
    assert!(again.iter().all(|o| !o.baked), "{again:?}");
    let other = BakeSettings {
        samples: 4,
        ..tiny()
    };
    let changed = assemble(&m, &other, Default::default(), &quiet).unwrap();
    assert!(changed
        .iter()
        .all(|o| o.reason.as_deref() == Some("settings changed")));
    // A source edited: only that asset is baked again.
    let tree0 = &m.assets.iter().find(|a| a.id == "tree_00").unwrap().source;
    let mut bytes = std::fs::read(tree0).unwrap();
    bytes.extend_from_slice(b"    ");
    std::fs::write(tree0, bytes).unwrap();
    let edited = assemble(&m, &other, Default::default(), &quiet).unwrap();
    let baked: Vec<&str> = edited
        .iter()
        .filter(|o| o.baked)
        .map(|o| o.asset.as_str())
        .collect();
    assert_eq!(baked, ["tree_00"]);

    let cam = Camera::look_at(
        Vec3::new(-4.0, 2.0, -4.0),
        Vec3::new(0.5, 0.3, 0.5),
        Vec3::Y,
        45.0,
        48,
        32,
    );
    let sources = assembly::mesh::load_sources(&m, Default::default()).unwrap();
    let scene = assembly::mesh::scene(&m, &sources);
    let accel = aggtool::trace::Accel::build(&scene);
    let settings = aggtool::render::reference::ReferenceSettings { spp: 16, seed: 1 };
    let (reference, _) =
        aggtool::render::reference::render(&accel, &cam, &lights(), settings, &no_progress);
    let lod = render_asm(&Assembly::new(m).unwrap(), &cam, 16);
    let c = compare(&lod, &reference).unwrap();
    eprintln!("forest relmse LoD vs reference: {:.4}", c.relmse);
    // Measured 0.051. Composing by bounds instead of first hits hid the trees behind the
    // ground: 0.26 here (checked by making that change), 0.82 on a 400-tree forest.
    assert!(c.relmse < 0.15, "{c:?}");
}

/// The command line on a manifest: gen forest, assemble (baked, then reused), inspect, render,
/// reference; a missing aggregate is an error naming the asset, not a panic.
#[test]
fn command_line_on_a_manifest() {
    use std::process::Command;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let run = |args: &[&str]| {
        let o = Command::new(env!("CARGO_BIN_EXE_aggtool"))
            .args(args)
            .current_dir(d)
            .output()
            .unwrap();
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stdout).into_owned(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let (okg, out, err) = run(&[
        "gen",
        "forest",
        "-o",
        "f",
        "--species",
        "2",
        "--instances",
        "9",
        "--triangles",
        "1200",
    ]);
    assert!(okg, "{err}");
    assert!(out.contains("forest.json"), "{out}");
    let (ok, _, err) = run(&["render", "f/forest.json", "--view", "v.json", "-o", "x.exr"]);
    assert!(!ok && !err.contains("panicked"), "{err}");
    std::fs::write(
        d.join("v.json"),
        r#"{"version":1,"camera":{"eye":[-4,2,-4],"target":[0,0.3,0],"width":24,"height":16},"spp":2}"#,
    )
    .unwrap();
    let (ok, _, err) = run(&["render", "f/forest.json", "--view", "v.json", "-o", "x.exr"]);
    assert!(
        !ok && err.contains("asset 'ground'") && err.contains("aggregate"),
        "{err}"
    );
    let bake = [
        "--max-res",
        "16",
        "--min-res",
        "4",
        "--samples",
        "8",
        "--aiv-res",
        "8",
        "--aiv-rays",
        "4",
        "--abv-res",
        "8",
        "--abv-full-res",
        "8",
    ];
    let args = |first: &[&'static str]| -> Vec<&'static str> {
        first.iter().chain(bake.iter()).copied().collect()
    };
    let (ok, out, err) = run(&args(&["assemble", "f/forest.json"]));
    assert!(ok, "{err}");
    assert!(out.contains("3 assets: 3 baked, 0 reused"), "{out}");
    let (ok, out, err) = run(&args(&["assemble", "f/forest.json"]));
    assert!(ok && out.contains("0 baked, 3 reused"), "{out}{err}");
    let (ok, out, err) = run(&["inspect", "f/forest.json", "--json"]);
    assert!(ok, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(j["instances"], 10);
    assert!(j["aggregate_bytes"].as_u64().unwrap() > 0);
    assert!(j["instanced_triangles"].as_u64().unwrap() > j["unique_triangles"].as_u64().unwrap());
    let (ok, out, err) = run(&[
        "render",
        "f/forest.json",
        "--view",
        "v.json",
        "-o",
        "lod.exr",
    ]);
    assert!(ok && out.contains("levels used"), "{out}{err}");
    let (ok, out, err) = run(&[
        "reference",
        "f/forest.json",
        "--view",
        "v.json",
        "-o",
        "ref.exr",
    ]);
    assert!(ok && out.contains("TLAS entries"), "{out}{err}");
    assert!(d.join("lod.exr").is_file() && d.join("ref.png").is_file());
}

/// `gen city` lays out a kit as a town: the same bytes twice, a manifest that loads with every
/// source resolving (relative paths from the manifest's folder, nothing copied), roads on every
/// fourth row and column (here the kit's road tile), each piece fitted into its cell (a
/// footprint of at most one cell, standing on y = 0), and an error for a kit with nothing to
/// place. With ../shared/assets present, its default kits lay out too.
#[test]
fn gen_city_lays_out_a_kit() {
    let d = tempfile::tempdir().unwrap();
    let kit = d.path().join("kit");
    std::fs::create_dir_all(&kit).unwrap();
    // A tall box as a building, a flat one as a road tile.
    let write = |name: &str, half: Vec3| {
        let data = SceneData::single(
            shapes::cuboid(Vec3::new(3.0, half.y, -2.0), half, 1),
            MaterialData::new("m", [0.5, 0.5, 0.5], 0.0, 1.0),
        );
        std::fs::write(kit.join(format!("{name}.glb")), to_glb(&data, false)).unwrap();
    };
    write("house", Vec3::new(2.0, 3.0, 1.0));
    write("road-straight", Vec3::new(0.5, 0.05, 0.5));
    let out = d.path().join("town");
    let r = assembly::city::write(&out, std::slice::from_ref(&kit), 30, 7).unwrap();
    assert_eq!((r.assets, r.instances), (2, 30));
    let first = std::fs::read(&r.manifest).unwrap();
    assembly::city::write(&out, std::slice::from_ref(&kit), 30, 7).unwrap();
    assert_eq!(std::fs::read(&r.manifest).unwrap(), first, "deterministic");
    let m = Manifest::load(&r.manifest).unwrap();
    m.require_sources().unwrap();
    assert_eq!(m.instance_count(), 30);
    let doc: serde_json::Value = serde_json::from_slice(&first).unwrap();
    assert!(doc["assets"]["house"]["source"]
        .as_str()
        .unwrap()
        .starts_with("../kit/"));
    let side = 6; // ceil(sqrt(30))
    let ids: Vec<&str> = m.assets.iter().map(|a| a.id.as_str()).collect();
    for i in 0..30 {
        let asset = ids[m.asset_of(i)];
        let road = (i % side) % 4 == 0 || (i / side) % 4 == 0;
        assert_eq!(asset == "road-straight", road, "instance {i}: {asset}");
        // The house's footprint (4 × 2) is scaled to 0.9 of a cell and stands on y = 0.
        if asset == "house" {
            let xf = m.transform(i);
            let s = xf.matrix3.x_axis.length();
            assert!((s * 4.0 - 0.9).abs() < 1e-4, "scale {s}");
            let base = xf.transform_point3(Vec3::new(3.0, 0.0, -2.0));
            assert!(base.y.abs() < 1e-4, "base at {base}");
        }
    }
    let empty = d.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = assembly::city::write(&d.path().join("t2"), &[empty], 4, 1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no building"), "{e}");
    let Some(shared) = common::shared_assets("gen_city_lays_out_a_kit (the shared kits)") else {
        return;
    };
    let kits = [
        shared.join("kenney_city_kit"),
        shared.join("quaternius_medieval_village"),
    ];
    let r = assembly::city::write(&d.path().join("shared-town"), &kits, 64, 3).unwrap();
    let m = Manifest::load(&r.manifest).unwrap();
    m.require_sources().unwrap();
    assert!(r.assets >= 20 && m.instance_count() == 64);
}

// ---- The hybrid representation (issue 18, item 3) ----

/// Counts this thread's heap allocations, to check that tracing allocates nothing per cone.
mod counting {
    use std::alloc::{GlobalAlloc, Layout, System};
    use std::cell::Cell;

    thread_local! {
        static COUNT: Cell<u64> = const { Cell::new(0) };
    }

    pub struct Counting;

    unsafe impl GlobalAlloc for Counting {
        unsafe fn alloc(&self, l: Layout) -> *mut u8 {
            let _ = COUNT.try_with(|c| c.set(c.get() + 1));
            unsafe { System.alloc(l) }
        }
        unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
            unsafe { System.dealloc(p, l) }
        }
        unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
            let _ = COUNT.try_with(|c| c.set(c.get() + 1));
            unsafe { System.realloc(p, l, n) }
        }
    }

    /// Allocations made by this thread so far.
    pub fn count() -> u64 {
        COUNT.with(|c| c.get())
    }
}

#[global_allocator]
static ALLOC: counting::Counting = counting::Counting;

/// A screen of `n` parallel black rods (thin boxes along y) over the square [-1, 1]² in the
/// z = 0 plane, covering the fraction `c` of it.
fn rods(dir: &Path, n: usize, c: f32) -> PathBuf {
    let pitch = 2.0 / n as f32;
    let mut mesh = aggtool::gen::glb::MeshData::default();
    for k in 0..n {
        let x = -1.0 + pitch * (k as f32 + 0.5);
        mesh.append(&shapes::cuboid(
            Vec3::new(x, 0.0, 0.0),
            Vec3::new(0.5 * c * pitch, 1.0, 0.001),
            1,
        ));
    }
    let mut data = SceneData::single(mesh, MaterialData::new("black", [0.0, 0.0, 0.0], 0.0, 1.0));
    data.make_lambertian();
    asset(dir, "rods", &data)
}

/// The screen seen head-on against a white sky (no sun): where the rods cover the fraction c
/// of the view, the sky shows through 1 − c of it, drawn from the aggregate (its ABV) and from
/// the mesh (the hybrid render, the camera close enough for the mesh).
#[test]
fn a_screen_of_thin_rods_lets_the_rest_through() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let c = 0.25;
    rods(d, 16, c);
    let p = manifest(
        d,
        "screen.json",
        &[("rods", "rods.glb")],
        &[("rods", Affine3A::IDENTITY)],
    );
    let sky = Lights {
        environment: Environment::Constant(Vec3::ONE),
        sun: None,
    };
    // One unit of the screen across the view: 8 rod pitches exactly, 8 whole rods.
    let cam = Camera::look_at(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::ZERO,
        Vec3::Y,
        2.0 * (0.5f32 / 3.0).atan().to_degrees(),
        32,
        32,
    );
    let render = |asm: &Assembly| {
        let img = assembly::render(
            asm,
            &cam,
            &sky,
            16,
            5,
            // The ABV itself. With the per-cone normalisation (the default) the rods' coverage
            // weights, over-estimated for rods a quarter of a voxel wide, take a share of the
            // sky: measured 0.686 through the screen and a ratio of 0.648 behind it.
            &TraceSettings {
                normalize: false,
                ..Default::default()
            },
            &no_progress,
        )
        .0;
        centre_mean(&img, 1.0)
    };
    let mut asm = Assembly::open(&p).unwrap();
    let agg = render(&asm);
    asm.set_representation(assembly::Representation::Hybrid);
    // Towards the middle of rod 8 (x = 1/16).
    let centre = Cone::new(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::new(0.0625, 0.0, -3.0),
        cam.pixel_angle(),
    );
    assert_eq!(
        asm.first_hit(&centre, &TraceSettings::default())
            .map(|f| f.drawn),
        Some(assembly::Drawn::Mesh),
        "a close-up screen goes to mesh"
    );
    let mesh = render(&asm);
    eprintln!(
        "sky through rods covering {c}: aggregate {agg:.4}, mesh {mesh:.4}, expected {:.4}",
        1.0 - c
    );
    // The mesh: exact geometry (8 whole rods in the view; their sides, 0.002 deep, seen at
    // up to 0.17 rad, add < 0.003 of coverage), sampled by 16 stratified rays in each of 32²
    // pixels: the standard deviation of the share is below sqrt(c(1 − c) / 16384) = 0.0034,
    // so 0.015 is over 4σ. Measured 0.7484 (and 0.7390 with a view of 9.6 pitches whose
    // exact share was 0.7396).
    assert!((mesh - (1.0 - c)).abs() < 0.015, "mesh lets {mesh} through");
    // The aggregate: what its ABV lets through, rods a quarter of a voxel wide in a 16³ bake
    // estimated by 8 rays on 8² face cells and quantised. Measured 0.729 (0.722 to 0.730 with
    // 64² face cells or the rods off a voxel boundary); 0.04 still fails a screen of
    // coverage 0.5 or an opaque or missing one by far.
    assert!(
        (agg - (1.0 - c)).abs() < 0.04,
        "aggregate lets {agg} through"
    );
}

/// Along a camera cone an aggregate in front of a mesh passes it on through its ABV: the rod
/// screen drawn from its aggregate in front of a white wall drawn from its mesh shows the wall
/// through 1 − c of it.
#[test]
fn an_aggregate_in_front_of_a_mesh_lets_it_through() {
    use assembly::Representation::{Aggregate, Mesh};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let c = 0.25;
    rods(d, 16, c);
    slab(d, "wall", Vec3::new(2.0, 2.0, 0.1));
    let assets = [("rods", "rods.glb"), ("wall", "wall.glb")];
    let wall = Affine3A::from_translation(Vec3::new(0.0, 0.0, -2.0));
    let sky = Lights {
        environment: Environment::Constant(Vec3::ONE),
        sun: None,
    };
    let cam = Camera::look_at(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::ZERO,
        Vec3::Y,
        2.0 * (0.5f32 / 3.0).atan().to_degrees(),
        32,
        32,
    );
    let render = |inst: &[(&str, Affine3A)], name: &str| {
        let mut asm = Assembly::open(&manifest(d, name, &assets, inst)).unwrap();
        asm.set_asset_representation(0, Aggregate);
        asm.set_asset_representation(1, Mesh);
        let img = assembly::render(
            &asm,
            &cam,
            &sky,
            16,
            5,
            // The ABV itself. With the per-cone normalisation (the default) the rods' coverage
            // weights, over-estimated for rods a quarter of a voxel wide, take a share of the
            // sky: measured 0.686 through the screen and a ratio of 0.648 behind it.
            &TraceSettings {
                normalize: false,
                ..Default::default()
            },
            &no_progress,
        )
        .0;
        centre_mean(&img, 1.0)
    };
    let alone = render(&[("wall", wall)], "wall.json");
    let behind = render(&[("rods", Affine3A::IDENTITY), ("wall", wall)], "both.json");
    let ratio = behind / alone;
    eprintln!("wall alone {alone:.4}, behind the rods {behind:.4}: ratio {ratio:.4}");
    assert!(alone > 0.3, "the wall is dark: {alone}");
    // The aggregate's ABV as in the rods test (measured 0.729 for 1 − c = 0.75, tolerance
    // 0.04), and the screen also shades the wall from part of the sky: it spans at most a
    // fifth of the wall's hemisphere, cosine-weighted, and blocks a quarter of that, < 0.05.
    // An opaque screen (0), no screen (1) or a mesh hidden behind the aggregate's radiance
    // alone (black rods: ~0) all fail. Measured 0.690 (0.800 alone, 0.552 behind).
    assert!(
        ratio > 1.0 - c - 0.04 - 0.05 && ratio < 1.0 - c + 0.04,
        "ratio {ratio}"
    );
}

/// A floor and a roof above it under a sun from straight above: the roof darkens the floor
/// under it whichever is drawn as a mesh and which from its aggregate (the mesh's shadow rays
/// pass the aggregate through its ABV; light reaching the aggregate's voxels meets the mesh's
/// triangles).
#[test]
fn a_mesh_instance_and_an_aggregate_instance_shadow_each_other() {
    use assembly::Representation::{Aggregate, Mesh};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    slab(d, "floor", Vec3::new(2.0, 0.1, 2.0));
    slab(d, "roof", Vec3::new(0.6, 0.1, 0.6));
    let assets = [("floor", "floor.glb"), ("roof", "roof.glb")];
    let roof = Affine3A::from_translation(Vec3::new(0.0, 3.0, 0.0));
    let lights = Lights {
        environment: Environment::Constant(Vec3::ZERO),
        sun: Some(Sun {
            direction: Vec3::Y,
            irradiance: Vec3::splat(3.0),
        }),
    };
    let cam = Camera::look_at(
        Vec3::new(0.0, 2.0, 0.8),
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::Y,
        20.0,
        24,
        24,
    );
    let lit_p = manifest(d, "lit.json", &assets, &[("floor", Affine3A::IDENTITY)]);
    let shaded_p = manifest(
        d,
        "shaded.json",
        &assets,
        &[("floor", Affine3A::IDENTITY), ("roof", roof)],
    );
    let render = |p: &Path, floor: assembly::Representation, roof: assembly::Representation| {
        let mut asm = Assembly::open(p).unwrap();
        asm.set_asset_representation(0, floor);
        asm.set_asset_representation(1, roof);
        let img = assembly::render(
            &asm,
            &cam,
            &lights,
            16,
            3,
            &TraceSettings::default(),
            &no_progress,
        )
        .0;
        let (o, dir) = cam.ray(glam::Vec2::new(12.0, 12.0));
        let drawn = asm
            .first_hit(
                &Cone::new(o, dir, cam.pixel_angle()),
                &TraceSettings::default(),
            )
            .map(|f| f.drawn);
        (centre_mean(&img, 0.3), drawn)
    };
    for (floor, roof) in [(Mesh, Aggregate), (Aggregate, Mesh)] {
        let (lit, drawn) = render(&lit_p, floor, roof);
        let (shaded, drawn2) = render(&shaded_p, floor, roof);
        eprintln!("floor {floor:?}, roof {roof:?}: lit {lit:.4}, under the roof {shaded:.4}");
        let want = if floor == Mesh {
            assembly::Drawn::Mesh
        } else {
            assembly::Drawn::Level(0)
        };
        assert_eq!(drawn, Some(want));
        assert_eq!(drawn2, Some(want));
        assert!(lit > 0.1, "the lit floor is dark: {lit}");
        // The roof is opaque as a mesh and as an aggregate (its ABV ~0). Measured: floor as
        // mesh 0.764 lit, 0.0105 under the roof's aggregate; floor as aggregate 0.720 lit,
        // 0.0000 under the roof's mesh.
        assert!(
            shaded < 0.1 * lit,
            "floor {floor:?}: lit {lit} vs shaded {shaded}"
        );
    }
}

/// Once warm (levels prepared, meshes loaded, scratch grown), tracing a cone through an
/// assembly allocates nothing, from aggregates and in the hybrid render.
#[test]
fn tracing_an_assembly_allocates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tree(d);
    let p = manifest(
        d,
        "trees.json",
        &[("tree", "tree.glb")],
        &[
            ("tree", Affine3A::IDENTITY),
            (
                "tree",
                Affine3A::from_translation(Vec3::new(0.3, 0.0, -1.0)),
            ),
            (
                "tree",
                Affine3A::from_translation(Vec3::new(-0.4, 0.0, -2.5)),
            ),
        ],
    );
    let mut asm = Assembly::open(&p).unwrap();
    let cam = camera(Affine3A::IDENTITY, 16, 16);
    let mut rng = aggtool::math::rng::Pcg32::new(1, 2);
    for hybrid in [false, true] {
        if hybrid {
            asm.set_representation(assembly::Representation::Hybrid);
        }
        let cones: Vec<Cone> = (0..256)
            .map(|k| {
                let (o, dir) = cam.ray(glam::Vec2::new(
                    (k % 16) as f32 + 0.5,
                    (k / 16) as f32 + 0.5,
                ));
                Cone::new(o, dir, cam.pixel_angle())
            })
            .collect();
        let settings = TraceSettings::default();
        // The runtime builds a voxel's ABSDF the first time it is shaded (a cache, not
        // per-cone work), and the reservoir picks voxels at random: passes over the same cones
        // allocate less and less, until none. The per-cone vectors this replaced allocated at
        // least once per cone (256 a pass) for ever.
        let every = TraceSettings {
            shading: aggtool::runtime::Shading::Every,
            ..settings
        };
        for c in &cones {
            asm.trace(c, &lights(), &every, &mut rng);
        }
        let mut counts = Vec::new();
        for _ in 0..12 {
            let before = counting::count();
            for c in &cones {
                asm.trace(c, &lights(), &settings, &mut rng);
            }
            counts.push(counting::count() - before);
            if counts.last() == Some(&0) {
                break;
            }
        }
        eprintln!("hybrid {hybrid}: allocations per pass of 256 cones: {counts:?}");
        assert_eq!(counts.last(), Some(&0), "hybrid {hybrid}: {counts:?}");
    }
    assert!(asm.mesh_loaded(0), "the close-up trees went to mesh");
}

/// The command line: `--no-mesh` renders as the library's aggregate-only assembly (today's
/// render, bit for bit); a view where every instance is far renders the same with and
/// without `--no-mesh` and loads no mesh; close up, the default (hybrid) render loads meshes
/// and differs; `--level-map` writes its picture and key.
#[test]
fn command_line_hybrid_and_no_mesh() {
    use std::process::Command;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tree(d);
    let p = manifest(
        d,
        "m.json",
        &[("tree", "tree.glb")],
        &[
            ("tree", Affine3A::IDENTITY),
            (
                "tree",
                Affine3A::from_translation(Vec3::new(1.5, 0.0, -1.0)),
            ),
        ],
    );
    let run = |args: &[&str]| {
        let o = Command::new(env!("CARGO_BIN_EXE_aggtool"))
            .args(args)
            .current_dir(d)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let view = |name: &str, eye: Vec3| {
        std::fs::write(
            d.join(name),
            format!(
                r#"{{"version":1,"camera":{{"eye":[{},{},{}],"target":[0.7,0.5,-0.5],"fov_y_deg":40,"width":32,"height":24}},"spp":4,"seed":9}}"#,
                eye.x, eye.y, eye.z
            ),
        )
        .unwrap();
    };
    view("near.json", Vec3::new(0.5, 1.0, 2.5));
    view("far.json", Vec3::new(4.0, 3.0, 8.0));
    let read = |f: &str| Image::read_exr(&d.join(f)).unwrap();
    let m = p.to_str().unwrap();
    // --no-mesh against the library's default (aggregates only).
    run(&[
        "render",
        m,
        "--view",
        "near.json",
        "-o",
        "nomesh.exr",
        "--no-mesh",
    ]);
    let v = aggtool::render::View::load(&d.join("near.json")).unwrap();
    let lib = assembly::render(
        &Assembly::open(&p).unwrap(),
        &v.camera(),
        &v.lights().unwrap(),
        v.spp,
        v.seed,
        &TraceSettings::default(),
        &no_progress,
    )
    .0;
    assert!(
        read("nomesh.exr").pixels == lib.pixels,
        "--no-mesh differs from the aggregate-only render"
    );
    // Close up: hybrid loads the mesh and differs (this tree's 2,000 triangles are drawn
    // from its mesh everywhere by default: `--mesh-below 0` keeps the hybrid).
    let out = run(&[
        "render",
        m,
        "--view",
        "near.json",
        "-o",
        "hybrid.exr",
        "--level-map",
        "map.png",
        "--mesh-below",
        "0",
    ]);
    assert!(out.contains("mesh loaded"), "{out}");
    assert!(
        out.contains("level map:") && d.join("map.png").is_file(),
        "{out}"
    );
    // Its key names levels by their resolution, as `inspect` does ("64³ 12.0%"), not by index.
    let key = out.lines().find(|l| l.starts_with("level map:")).unwrap();
    assert!(key.contains("³ ") && !key.contains(" l0 "), "{key}");
    assert!(read("hybrid.exr").pixels != lib.pixels);
    // Far: identical, no mesh loaded.
    let out = run(&[
        "render",
        m,
        "--view",
        "far.json",
        "-o",
        "far.exr",
        "--mesh-below",
        "0",
    ]);
    assert!(!out.contains("mesh loaded"), "{out}");
    // By default an asset of at most 16,384 triangles is drawn from its mesh at every
    // distance: the far view is then the library's all-mesh render, bit for bit.
    let n = aggtool::import::triangle_count(&d.join("tree.glb"), u64::MAX).unwrap();
    let loaded = aggtool::import::load(&d.join("tree.glb"), Default::default()).unwrap();
    assert_eq!(n, loaded.instanced_triangle_count() as u64);
    let out = run(&["render", m, "--view", "far.json", "-o", "far-small.exr"]);
    assert!(
        out.contains(&format!("drawn from its mesh ({n} triangles)")),
        "{out}"
    );
    let vf = aggtool::render::View::load(&d.join("far.json")).unwrap();
    let mut all_mesh = Assembly::open(&p).unwrap();
    all_mesh.set_representation(assembly::Representation::Mesh);
    let lib_mesh = assembly::render(
        &all_mesh,
        &vf.camera(),
        &vf.lights().unwrap(),
        vf.spp,
        vf.seed,
        &TraceSettings::default(),
        &no_progress,
    )
    .0;
    assert!(read("far-small.exr").pixels == lib_mesh.pixels);
    let out = run(&[
        "render",
        m,
        "--view",
        "far.json",
        "-o",
        "far-fewer.exr",
        "--mesh-below",
        &(n - 1).to_string(),
    ]);
    assert!(!out.contains("drawn from its mesh"), "{out}");
    assert!(read("far-fewer.exr").pixels == read("far.exr").pixels);
    // A small asset whose mesh fails to import (its JSON whole, its buffer cut off): the
    // error says why the mesh was needed and how to do without it.
    let glb = std::fs::read(d.join("tree.glb")).unwrap();
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    std::fs::write(d.join("tree.glb"), &glb[..20 + json_len]).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_aggtool"))
        .args(["render", m, "--view", "far.json", "-o", "broken.exr"])
        .current_dir(d)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("asset 'tree': its mesh is needed (it has at most 16384 triangles")
            && err.contains("--mesh-below 0"),
        "{err}"
    );
    run(&[
        "render",
        m,
        "--view",
        "far.json",
        "-o",
        "broken.exr",
        "--mesh-below",
        "0",
    ]);
    std::fs::write(d.join("tree.glb"), &glb).unwrap();
    // (The far view does show the trees: not all sky, the default white environment.)
    assert!(read("far.exr")
        .pixels
        .iter()
        .any(|p| (*p - Vec3::ONE).abs().max_element() > 0.1));
    run(&[
        "render",
        m,
        "--view",
        "far.json",
        "-o",
        "far-nomesh.exr",
        "--no-mesh",
    ]);
    assert!(read("far.exr").pixels == read("far-nomesh.exr").pixels);
    // The flags are for manifests.
    let o = Command::new(env!("CARGO_BIN_EXE_aggtool"))
        .args([
            "render",
            "tree.agg",
            "--view",
            "far.json",
            "-o",
            "x.exr",
            "--no-mesh",
        ])
        .current_dir(d)
        .output()
        .unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--no-mesh"));
    // A mesh needed but its source gone: an error naming the asset, no image written.
    std::fs::remove_file(d.join("tree.glb")).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_aggtool"))
        .args(["render", m, "--view", "near.json", "-o", "gone.exr"])
        .current_dir(d)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("asset 'tree'") && err.contains("tree.glb"),
        "{err}"
    );
    assert!(!d.join("gone.exr").exists() && !err.contains("panicked"));
}

/// Shared walks in an assembly ([`TraceSettings::samples_per_walk`]): a tree's aggregate
/// standing on a floor drawn as its mesh renders, with 4 samples a walk, to the same image
/// mean as with a walk a sample (within 1%: 576 pixels × 128 samples), per pixel within twice
/// the difference of two one-walk-a-sample renders with other seeds, and to the same bits on
/// one thread as on two.
#[test]
fn shared_walks_in_an_assembly_estimate_the_same_image() {
    use assembly::Representation::{Aggregate, Mesh};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tree(d);
    slab(d, "floor", Vec3::new(2.0, 0.05, 2.0));
    let p = manifest(
        d,
        "scene.json",
        &[("tree", "tree.glb"), ("floor", "floor.glb")],
        &[("tree", Affine3A::IDENTITY), ("floor", Affine3A::IDENTITY)],
    );
    let mut asm = Assembly::open(&p).unwrap();
    asm.set_asset_representation(0, Aggregate);
    asm.set_asset_representation(1, Mesh);
    let cam = camera(Affine3A::IDENTITY, 24, 24);
    let render = |reuse: u32, seed: u64| {
        let s = TraceSettings {
            samples_per_walk: reuse,
            ..Default::default()
        };
        assembly::render(&asm, &cam, &lights(), 128, seed, &s, &no_progress).0
    };
    common::assert_shared_walks_agree(render);
}

/// A host's layer of an assembly (`Assembly::layer_into`, what the Mitsuba host picks from):
/// two trees, one behind the other along the cones. The front tree's hits are the aggregate's
/// own layer; the back tree's are its own layer times what the front one lets through; the
/// weights and the transmittance behind add up to 1 (each layer is normalised, and composing
/// normalised layers keeps the sum).
#[test]
fn layers_compose_instances_front_to_back() {
    use aggtool::runtime::LayerHit;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let agg = tree(d).with_extension("agg");
    let single = LodScene::open(&agg).unwrap();
    let (lo, hi) = single.aggregate().bounds();
    let depth = hi.z - lo.z;
    let behind = Vec3::new(0.0, 0.0, -1.5 * depth);
    let p = manifest(
        d,
        "row.json",
        &[("tree", "tree.glb")],
        &[
            ("tree", Affine3A::IDENTITY),
            ("tree", Affine3A::from_translation(behind)),
        ],
    );
    let asm = Assembly::open(&p).unwrap();
    let settings = TraceSettings::default();
    let (mut both, mut front, mut back) = (Vec::new(), Vec::new(), Vec::new());
    let (mut composed, mut met_both) = (0, 0);
    for i in 0..24 {
        for j in 0..24 {
            let x = lo.x + (hi.x - lo.x) * (i as f32 + 0.5) / 24.0;
            let y = lo.y + (hi.y - lo.y) * (j as f32 + 0.5) / 24.0;
            let cone = Cone::new(Vec3::new(x, y, hi.z + 2.0), Vec3::NEG_Z, 0.002);
            both.clear();
            front.clear();
            back.clear();
            let t = asm.layer_into(&cone, &settings, &mut both);
            let t1 = single.layer_into(&cone, &settings, 0, &mut front);
            let moved = Cone {
                origin: cone.origin - behind,
                ..cone
            };
            let t2 = single.layer_into(&moved, &settings, 1, &mut back);
            let sum: f32 = both.iter().map(|h| h.weight).sum::<f32>() + t;
            assert!((sum - 1.0).abs() < 1e-4, "cone ({i}, {j}): Σw + T = {sum}");
            let t12 = if t1 > 1e-4 && t1 * t2 > 1e-4 {
                t1 * t2
            } else {
                0.0
            };
            assert!(
                (t - t12).abs() < 1e-5,
                "cone ({i}, {j}): T {t} vs {t1}·{t2}"
            );
            // Nothing is traced behind a layer that lets (almost) nothing through (the
            // runtime's MIN_TRANSMITTANCE, 1e-4).
            let seen = if t1 > 1e-4 { &back[..] } else { &[] };
            let want: Vec<LayerHit> = front
                .iter()
                .copied()
                .chain(seen.iter().map(|h| LayerHit {
                    weight: h.weight * t1,
                    ..*h
                }))
                .collect();
            assert_eq!(both.len(), want.len(), "cone ({i}, {j})");
            for (a, b) in both.iter().zip(&want) {
                assert_eq!((a.instance, a.level, a.key), (b.instance, b.level, b.key));
                assert!(
                    (a.weight - b.weight).abs() < 1e-5,
                    "cone ({i}, {j}): {a:?} {b:?}"
                );
                assert!(
                    (a.t - b.t).abs() < 1e-3 * depth,
                    "cone ({i}, {j}): {a:?} {b:?}"
                );
            }
            composed += both.len();
            met_both += (!front.is_empty() && !seen.is_empty()) as usize;
        }
    }
    // Both trees are seen on many cones (measured: 227 of 576 cones, 2,594 hits).
    eprintln!("{met_both} cones met both trees, {composed} hits");
    assert!(met_both > 100 && composed > 1000);
}

/// `import::triangle_count`, which decides which assets are drawn from their meshes: the
/// count `load` finds, faces of k corners as k − 2 triangles, stopped once past the limit, and
/// an error (the asset keeps its aggregate) for a file that is not one.
#[test]
fn triangle_count_counts_without_importing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let obj = d.join("quads.obj");
    let mut text = String::from("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\n");
    for _ in 0..100 {
        text.push_str("f 1 2 3 4\nf 1/1 2/2 5/3\n");
    }
    std::fs::write(&obj, text).unwrap();
    assert_eq!(
        aggtool::import::triangle_count(&obj, u64::MAX).unwrap(),
        300
    );
    // Past the limit it stops reading: the first two faces already pass 2.
    assert_eq!(aggtool::import::triangle_count(&obj, 2).unwrap(), 3);
    let glb = tree(d);
    let n = aggtool::import::triangle_count(&glb, u64::MAX).unwrap();
    let scene = aggtool::import::load(&glb, Default::default()).unwrap();
    assert_eq!(n, scene.instanced_triangle_count() as u64);
    // A damaged GLB (its JSON chunk cut short) and a file of another kind are errors.
    let bytes = std::fs::read(&glb).unwrap();
    std::fs::write(d.join("cut.glb"), &bytes[..40]).unwrap();
    assert!(aggtool::import::triangle_count(&d.join("cut.glb"), 10).is_err());
    std::fs::write(d.join("x.ply"), b"ply").unwrap();
    assert!(aggtool::import::triangle_count(&d.join("x.ply"), 10).is_err());
}
