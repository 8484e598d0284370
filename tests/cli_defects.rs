//! Small defects of the command line (issue 40), each as its user met it: a flag value that
//! was accepted or explained wrongly, an input that was silently misread, an error said twice,
//! and work done before a refusal that could have come first. Most tests run the built binary.

mod common;

use std::path::Path;
use std::process::{Command, Output};

use common::{aggtool, ok};

/// stderr of a run that must have failed with exit status `code`, without a panic.
fn failed(o: &Output, code: i32) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(code), "stderr: {err}");
    assert!(!err.contains("panicked"), "{err}");
    err
}

/// Exit status of usage errors (clap's).
const USAGE: i32 = 2;
/// Exit status of input errors (an input missing, unreadable or invalid).
const INPUT: i32 = 3;
/// Exit status of output errors (an output that cannot be written).
const OUTPUT: i32 = 4;

/// `render --nee 0` was accepted and rendered as `--nee 1`: now a usage error naming the flag.
#[test]
fn render_nee_zero_is_a_usage_error() {
    let d = tempfile::tempdir().unwrap();
    let o = aggtool(
        &[
            "render", "x.agg", "--view", "v.json", "-o", "x.exr", "--nee", "0",
        ],
        d.path(),
    );
    let err = failed(&o, USAGE);
    assert!(err.contains("--nee") && err.contains("'0'"), "{err}");
    assert!(!d.path().join("x.exr").exists());
}

/// `reference --auto-view --width 0` said "camera eye, target and up must be finite" (the
/// framing of a zero-wide image puts the eye at infinity): now a usage error naming the flag,
/// and a view of that size says what is wrong with it, its size.
#[test]
fn reference_zero_size_names_the_size() {
    let d = tempfile::tempdir().unwrap();
    for flag in ["--width", "--height"] {
        let o = aggtool(
            &[
                "reference",
                "a.glb",
                "--auto-view",
                flag,
                "0",
                "-o",
                "a.exr",
            ],
            d.path(),
        );
        let err = failed(&o, USAGE);
        assert!(err.contains(flag) && err.contains("'0'"), "{err}");
        assert!(!err.contains("finite"), "{err}");
    }
    let view = aggtool::render::View::framing(glam::Vec3::ZERO, 1.0, 0, 256, 16);
    let e = view.validate().unwrap_err();
    assert!(e.contains("image size 0x256"), "{e}");
}

/// `--keep 2` reported "--keep must be in (0, 1] and --energy in [0, 1]": now only what is
/// wrong, with the value given. Settings are checked before the asset is read (which is
/// missing here).
#[test]
fn bad_keep_or_energy_names_only_itself() {
    let d = tempfile::tempdir().unwrap();
    let o = aggtool(&["convert", "missing.glb", "--keep", "2"], d.path());
    let err = failed(&o, USAGE);
    assert!(err.contains("--keep must be in (0, 1], got 2"), "{err}");
    assert!(!err.contains("--energy"), "{err}");
    let o = aggtool(&["convert", "missing.glb", "--energy", "1.5"], d.path());
    let err = failed(&o, USAGE);
    assert!(err.contains("--energy must be in [0, 1], got 1.5"), "{err}");
    assert!(!err.contains("--keep"), "{err}");
}

/// A manifest without `"instances"` was read as an empty assembly: now an error naming the
/// missing field (an empty one says `"instances": []`).
#[test]
fn manifest_without_instances_is_an_error() {
    let d = tempfile::tempdir().unwrap();
    let m = d.path().join("m.json");
    std::fs::write(
        &m,
        r#"{"version": 1, "assets": {"a": {"source": "a.glb"}}}"#,
    )
    .unwrap();
    let err = failed(&aggtool(&["inspect", "m.json"], d.path()), INPUT);
    assert!(err.contains("missing field `instances`"), "{err}");
    let e = aggtool::assembly::Manifest::load(&m).unwrap_err();
    assert!(
        matches!(e, aggtool::assembly::ManifestError::Malformed { .. }),
        "{e}"
    );
    std::fs::write(
        &m,
        r#"{"version": 1, "assets": {"a": {"source": "a.glb"}}, "instances": []}"#,
    )
    .unwrap();
    let m = aggtool::assembly::Manifest::load(&m).unwrap();
    assert_eq!(m.instance_count(), 0);
}

/// `compare` read a PNG (tonemapped, clamped, sRGB) as if it held radiance: now refused with
/// the formats it takes; the EXR beside it compares.
#[test]
fn compare_refuses_non_linear_images() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let mut img = aggtool::film::Image::new(4, 3);
    img.pixels[5] = glam::Vec3::new(2.0, 0.5, 0.25);
    img.write_exr(&p.join("a.exr")).unwrap();
    img.write_png(&p.join("a.png"), 0.0).unwrap();
    std::fs::copy(p.join("a.png"), p.join("a.jpg")).unwrap();
    for (a, b, bad) in [
        ("a.png", "a.exr", "a.png"),
        ("a.exr", "a.png", "a.png"),
        ("a.jpg", "a.exr", "a.jpg"),
    ] {
        let err = failed(&aggtool(&["compare", a, b], p), INPUT);
        assert!(
            err.contains(bad) && err.contains("not linear") && err.contains("EXR, PFM or HDR"),
            "{err}"
        );
    }
    let out = ok(&aggtool(&["compare", "a.exr", "a.exr", "--json"], p));
    let c: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(c["rmse"], 0.0);
}

/// A missing file printed its cause twice: in the message ("cannot read F: No such file or
/// directory") and again as "caused by: No such file or directory". Now once, whichever
/// command meets it.
#[test]
fn a_missing_file_says_its_cause_once() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let view = r#"{"version": 1, "camera": {"eye": [0, 0, 2], "target": [0, 0, 0], "fov_y_deg": 40, "width": 8, "height": 8}, "spp": 1}"#;
    std::fs::write(p.join("view.json"), view).unwrap();
    let runs: &[&[&str]] = &[
        &["info", "missing.glb"],
        &["convert", "missing.obj"],
        &["inspect", "missing.agg"],
        &["inspect", "missing.json"],
        &["compare", "missing.exr", "other.exr"],
        &[
            "render",
            "missing.agg",
            "--view",
            "view.json",
            "-o",
            "x.exr",
        ],
        &["render", "x.agg", "--view", "missing.json", "-o", "x.exr"],
        &["reference", "missing.glb", "--auto-view", "-o", "x.exr"],
        &["assemble", "missing.json"],
    ];
    for args in runs {
        let err = failed(&aggtool(args, p), INPUT);
        let missing = args.iter().find(|a| a.starts_with("missing")).unwrap();
        assert!(err.contains(missing), "{args:?}: {err}");
        // The OS's words for a missing file, once ("(os error 2)" on every platform).
        assert_eq!(err.matches("(os error 2)").count(), 1, "{args:?}: {err}");
    }
}

/// `convert -o DIR` (an existing folder) imported and baked, then failed to write: now it
/// fails first. The asset here does not even exist: the output is checked before it is read.
/// The same for `--report`, and for a folder above the output that is a file.
#[test]
fn convert_checks_its_output_before_baking() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    std::fs::create_dir(p.join("out")).unwrap();
    std::fs::write(p.join("file"), b"x").unwrap();
    let cases: &[(&[&str], &str)] = &[
        (&["-o", "out"], "is a folder"),
        (&["-o", "out/", "--shard", "0/2"], "is a folder"),
        (&["-o", "x.agg", "--report", "out"], "is a folder"),
        (&["-o", "file/x.agg"], "is a file, not a folder"),
    ];
    for (extra, needle) in cases {
        let mut args = vec!["convert", "missing.glb"];
        args.extend_from_slice(extra);
        let err = failed(&aggtool(&args, p), OUTPUT);
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(
            !err.contains("missing.glb"),
            "{args:?}: the asset was read before the output was checked: {err}"
        );
    }
    assert_eq!(std::fs::read_dir(p.join("out")).unwrap().count(), 0);
}

/// The library refuses the folder too, before baking: `bake_to_file` is what the Python
/// module and `assemble` call.
#[test]
fn bake_to_a_folder_fails_before_baking() {
    let d = tempfile::tempdir().unwrap();
    let scene = common::gen_scene("foliage", 500);
    let settings = aggtool::bake::BakeSettings {
        max_res: 8,
        min_res: 4,
        ..Default::default()
    };
    // A bake reports progress as soon as it starts: none may be reported.
    let no_work = |stage: &str, _: u64, _: u64| panic!("the bake started ({stage})");
    for shard in [
        None,
        Some(aggtool::format::part::Shard { index: 0, count: 2 }),
    ] {
        let e = match shard {
            None => aggtool::bake::bake_to_file(&scene, "f.glb", &settings, d.path(), &no_work),
            Some(s) => {
                aggtool::bake::bake_shard_to_file(&scene, "f.glb", &settings, s, d.path(), &no_work)
            }
        }
        .unwrap_err();
        assert!(e.to_string().contains("is a folder"), "{shard:?}: {e}");
    }
}

/// `assemble --require-reuse` baked every stale asset, then refused: now it refuses first,
/// naming the assets and why, and bakes nothing.
#[test]
fn assemble_require_reuse_refuses_before_baking() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    ok(&aggtool(
        &[
            "gen",
            "forest",
            "-o",
            "f",
            "--species",
            "2",
            "--instances",
            "4",
            "--triangles",
            "400",
        ],
        p,
    ));
    let tiny = common::tiny_bake_flags("8");
    let mut args = vec!["assemble", "f/forest.json", "--require-reuse"];
    args.extend(&tiny);
    let err = failed(&aggtool(&args, p), INPUT);
    assert!(
        err.contains("would have had to be baked, so nothing was baked"),
        "{err}"
    );
    assert!(err.contains("(missing)"), "{err}");
    let m = aggtool::assembly::Manifest::load(&p.join("f/forest.json")).unwrap();
    for a in &m.assets {
        assert!(err.contains(&format!("asset '{}'", a.id)), "{err}");
        assert!(!a.aggregate.exists(), "{} was baked", a.aggregate.display());
    }
    // Baked, then reused: --require-reuse passes.
    let mut args = vec!["assemble", "f/forest.json"];
    args.extend(&tiny);
    ok(&aggtool(&args, p));
    let mut args = vec!["assemble", "f/forest.json", "--require-reuse"];
    args.extend(&tiny);
    let out = ok(&aggtool(&args, p));
    assert!(out.contains("0 baked, 3 reused"), "{out}");
}

/// `gen city` without `--kit` in `cwd`, with `AGGTOOL_ASSETS` set to `assets` or unset.
fn gen_city(cwd: &Path, assets: Option<&Path>) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_aggtool"));
    c.args(["gen", "city", "-o", "town", "--instances", "4"])
        .current_dir(cwd);
    match assets {
        Some(a) => c.env("AGGTOOL_ASSETS", a),
        None => c.env_remove("AGGTOOL_ASSETS"),
    };
    c.output().expect("run aggtool")
}

/// Writes the two default kits, one small generated asset each, under `root`.
fn fake_kits(root: &Path) {
    for (kit, name) in [
        ("kenney_city_kit", "buildings"),
        ("quaternius_medieval_village", "foliage"),
    ] {
        let dir = root.join(kit);
        std::fs::create_dir_all(&dir).unwrap();
        ok(&aggtool(
            &[
                "gen",
                name,
                "-o",
                dir.to_str().unwrap(),
                "--triangles",
                "300",
            ],
            root,
        ));
    }
}

/// The asset sources of `town/city.json` under `cwd`, resolved and canonical.
fn city_sources(cwd: &Path) -> Vec<std::path::PathBuf> {
    let m = aggtool::assembly::Manifest::load(&cwd.join("town/city.json")).unwrap();
    m.assets
        .iter()
        .map(|a| std::fs::canonicalize(&a.source).unwrap())
        .collect()
}

/// `gen city`'s default kits came from `env!("CARGO_MANIFEST_DIR")`, the build machine's
/// checkout compiled into the binary: now from `$AGGTOOL_ASSETS`, else `../shared/assets`
/// from the current folder, with an error saying so when neither has them.
#[test]
fn gen_city_finds_its_default_kits_at_run_time() {
    let d = tempfile::tempdir().unwrap();
    let root = std::fs::canonicalize(d.path()).unwrap();
    let work = root.join("work");
    std::fs::create_dir_all(&work).unwrap();
    // Neither: an error naming both ways out (the build's own ../shared/assets is not used).
    let err = failed(&gen_city(&work, None), INPUT);
    assert!(
        err.contains("--kit") && err.contains("AGGTOOL_ASSETS") && err.contains("kenney_city_kit"),
        "{err}"
    );
    assert!(!work.join("town/city.json").exists());
    // ../shared/assets from the current folder.
    let shared = root.join("shared/assets");
    fake_kits(&shared);
    ok(&gen_city(&work, None));
    let sources = city_sources(&work);
    assert!(!sources.is_empty());
    assert!(
        sources.iter().all(|s| s.starts_with(&shared)),
        "{sources:?}"
    );
    // $AGGTOOL_ASSETS first.
    let other = root.join("other");
    fake_kits(&other);
    std::fs::remove_dir_all(work.join("town")).unwrap();
    ok(&gen_city(&work, Some(&other)));
    let sources = city_sources(&work);
    assert!(sources.iter().all(|s| s.starts_with(&other)), "{sources:?}");
    // A variable naming a folder without the kits is an error, not a fallback.
    let err = failed(&gen_city(&work, Some(&root.join("nothing"))), INPUT);
    assert!(err.contains("nothing"), "{err}");
}

/// `render -o out.png` printed "output: out.png and out.png" and kept no EXR (the PNG was
/// written over the EXR data): now the EXR goes beside it as out.exr, and the PNG is a PNG.
/// The same for `reference`.
#[test]
fn a_png_output_keeps_its_exr_beside_it() {
    let d = tempfile::tempdir().unwrap();
    let cwd = d.path();
    common::tiny_plane(cwd);
    ok(&aggtool(
        &[
            "reference",
            "plane45.glb",
            "--auto-view",
            "--width",
            "16",
            "--height",
            "16",
            "--spp",
            "2",
            "--save-view",
            "v.json",
            "-o",
            "ref.png",
        ],
        cwd,
    ));
    let out = ok(&aggtool(
        &["render", "plane45.agg", "--view", "v.json", "-o", "lod.png"],
        cwd,
    ));
    assert!(
        out.contains("lod.exr and") && out.contains("lod.png"),
        "{out}"
    );
    for name in ["ref", "lod"] {
        let png = std::fs::read(cwd.join(format!("{name}.png"))).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "{name}.png is not a PNG");
        let exr = std::fs::read(cwd.join(format!("{name}.exr"))).unwrap();
        assert!(
            exr.starts_with(&[0x76, 0x2f, 0x31, 0x01]),
            "{name}.exr is not an EXR"
        );
    }
}

/// `render` lacked `reference`'s `--auto-view`, `--width`, `--height` and `--save-view`: now
/// it takes them, and frames an aggregate as `reference --auto-view` frames its mesh (the
/// aggregate records the asset's bounds).
#[test]
fn render_frames_as_reference_does() {
    let d = tempfile::tempdir().unwrap();
    let cwd = d.path();
    common::tiny_plane(cwd);
    let size = [
        "--width",
        "20",
        "--height",
        "10",
        "--spp",
        "2",
        "--auto-view",
    ];
    let mut a = vec![
        "reference",
        "plane45.glb",
        "-o",
        "r.exr",
        "--save-view",
        "r.json",
    ];
    a.extend(size);
    ok(&aggtool(&a, cwd));
    let mut b = vec![
        "render",
        "plane45.agg",
        "-o",
        "l.exr",
        "--save-view",
        "l.json",
    ];
    b.extend(size);
    ok(&aggtool(&b, cwd));
    let read = |f: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(cwd.join(f)).unwrap()).unwrap()
    };
    let (r, l) = (read("r.json"), read("l.json"));
    assert_eq!(r["camera"]["width"], 20);
    assert_eq!(l["camera"]["width"], 20);
    assert_eq!(l["camera"]["height"], 10);
    for key in ["eye", "target"] {
        for i in 0..3 {
            let (x, y) = (
                r["camera"][key][i].as_f64().unwrap(),
                l["camera"][key][i].as_f64().unwrap(),
            );
            assert!(
                (x - y).abs() <= 1e-4 * (1.0 + x.abs()),
                "{key}[{i}]: {x} vs {y}"
            );
        }
    }
    // Neither a view nor --auto-view: a clear error.
    let o = aggtool(&["render", "plane45.agg", "-o", "x.exr"], cwd);
    assert!(failed(&o, USAGE).contains("--auto-view"));
}

/// `gen city --instances 4` listed every asset of the kits (30 for the default ones) though it
/// placed a few, and `assemble` bakes every asset a manifest lists: now the manifest lists the
/// assets placed, and the report counts them.
#[test]
fn gen_city_lists_only_the_assets_it_places() {
    let d = tempfile::tempdir().unwrap();
    let cwd = d.path();
    ok(&aggtool(
        &["gen", "all", "-o", "kit", "--triangles", "300"],
        cwd,
    ));
    let kit_assets = std::fs::read_dir(cwd.join("kit")).unwrap().count();
    assert!(kit_assets >= 5, "{kit_assets}");
    let out = ok(&aggtool(
        &[
            "gen",
            "city",
            "-o",
            "town",
            "--instances",
            "2",
            "--kit",
            "kit",
        ],
        cwd,
    ));
    let m = aggtool::assembly::Manifest::load(&cwd.join("town/city.json")).unwrap();
    assert_eq!(m.instance_count(), 2);
    // Every listed asset is placed at least once.
    let per_asset = m.instances_per_asset();
    assert!(per_asset.iter().all(|&n| n > 0), "{per_asset:?}");
    assert!(m.assets.len() <= 2 && m.assets.len() < kit_assets);
    assert!(
        out.contains(&format!("of {} assets", m.assets.len())),
        "{out}"
    );
}

/// `eval --speed` without assets wrote an empty table (the hard cases, the default when no
/// asset is given, were ignored under `--speed`): now it studies every hard case.
#[test]
fn eval_speed_without_assets_studies_the_hard_cases() {
    let d = tempfile::tempdir().unwrap();
    let args = [
        "eval",
        "--speed",
        "8",
        "--triangles",
        "300",
        "--spp",
        "1",
        "--reference-spp",
        "2",
        "-o",
        "ev",
        "--json",
    ];
    let r: serde_json::Value = serde_json::from_str(&ok(&aggtool(&args, d.path()))).unwrap();
    let scenes: Vec<&str> = r["results"]
        .as_array()
        .unwrap()
        .iter()
        .map(|row| row["scene"].as_str().unwrap())
        .collect();
    assert_eq!(scenes, aggtool::gen::NAMES, "{r}");
    let table = std::fs::read_to_string(d.path().join("ev/speed.md")).unwrap();
    assert_eq!(
        table.lines().count(),
        2 + aggtool::gen::NAMES.len(),
        "{table}"
    );
}
