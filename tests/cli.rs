//! The command line: outputs exist, errors are clear and never panics.

use std::path::Path;
use std::process::{Command, Output};

mod common;
use common::{aggtool, ok};

/// `aggtool convert foliage.glb` in `dir` with a tiny 8³/4³ bake (`--samples 8`, 8² maps) and
/// `extra` flags into `out`; returns the child (stderr kept) after checking it succeeded.
fn tiny_convert(dir: &Path, extra: &[&str], out: &str) -> Output {
    let mut args = vec![
        "convert",
        "foliage.glb",
        "--max-res",
        "8",
        "--min-res",
        "4",
        "--samples",
        "8",
        "--aiv-res",
        "8",
        "--abv-res",
        "8",
        "-o",
        out,
    ];
    args.extend_from_slice(extra);
    let o = aggtool(&args, dir);
    ok(&o);
    o
}

/// `aggtool inspect FILE --json` in `dir`, parsed.
fn inspect_json(dir: &Path, file: &str) -> serde_json::Value {
    serde_json::from_str(&ok(&aggtool(&["inspect", file, "--json"], dir))).unwrap()
}

fn fails_with(o: &Output, needle: &str) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "expected failure");
    assert!(
        err.contains(needle),
        "stderr '{err}' should contain '{needle}'"
    );
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn gen_reference_compare_round_trip() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    ok(&aggtool(
        &["gen", "displaced-sphere", "-o", ".", "--triangles", "2000"],
        p,
    ));
    let view = r#"{"version": 1, "camera": {"eye": [0, 0.3, 2.2], "target": [0, 0, 0], "fov_y_deg": 35, "width": 24, "height": 16},
        "environment": {"constant": [0.8, 0.9, 1.0]}, "sun": {"direction": [1, 1, 0.5], "irradiance": 2}, "spp": 4, "seed": 7}"#;
    std::fs::write(p.join("view.json"), view).unwrap();
    let out = ok(&aggtool(
        &[
            "reference",
            "displaced-sphere.glb",
            "--view",
            "view.json",
            "-o",
            "a.exr",
        ],
        p,
    ));
    assert!(out.contains("stats:") && out.contains("output:"), "{out}");
    assert!(p.join("a.exr").exists() && p.join("a.png").exists());
    ok(&aggtool(
        &[
            "reference",
            "displaced-sphere.glb",
            "--view",
            "view.json",
            "-o",
            "b.exr",
        ],
        p,
    ));
    let json = ok(&aggtool(
        &["compare", "a.exr", "b.exr", "--json", "--diff", "d.png"],
        p,
    ));
    let v: serde_json::Value = serde_json::from_str(json.trim()).unwrap();
    assert_eq!(v["rmse"], 0.0, "same seed, same image");
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(24), Some(16))
    );
    assert!(p.join("d.png").exists());
    // A different seed gives a different image, compared with a positive RMSE.
    ok(&aggtool(
        &[
            "reference",
            "displaced-sphere.glb",
            "--view",
            "view.json",
            "--seed",
            "8",
            "-o",
            "c.exr",
        ],
        p,
    ));
    let v: serde_json::Value =
        serde_json::from_str(ok(&aggtool(&["compare", "a.exr", "c.exr", "--json"], p)).trim())
            .unwrap();
    assert!(v["rmse"].as_f64().unwrap() > 0.0);
    // Different sizes are a clear error.
    ok(&aggtool(
        &[
            "reference",
            "displaced-sphere.glb",
            "--auto-view",
            "--width",
            "8",
            "--height",
            "8",
            "--spp",
            "1",
            "-o",
            "small.exr",
        ],
        p,
    ));
    fails_with(
        &aggtool(&["compare", "a.exr", "small.exr"], p),
        "sizes differ",
    );
}

#[test]
fn bad_inputs_fail_cleanly() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    fails_with(&aggtool(&["gen", "teapot", "-o", "."], p), "unknown scene");
    fails_with(
        &aggtool(
            &["reference", "missing.glb", "--auto-view", "-o", "x.exr"],
            p,
        ),
        "missing.glb",
    );
    std::fs::write(p.join("bad.obj"), "v 0 0 0\nv 1 0 0\nf 1 2 9\n").unwrap();
    fails_with(&aggtool(&["info", "bad.obj"], p), "bad.obj");
    ok(&aggtool(
        &["gen", "plane45", "-o", ".", "--triangles", "100"],
        p,
    ));
    std::fs::write(
        p.join("v2.json"),
        r#"{"version": 2, "camera": {"eye": [0,0,1], "target": [0,0,0]}}"#,
    )
    .unwrap();
    fails_with(
        &aggtool(
            &[
                "reference",
                "plane45.glb",
                "--view",
                "v2.json",
                "-o",
                "x.exr",
            ],
            p,
        ),
        "version 2",
    );
    std::fs::write(p.join("env.json"), r#"{"version": 1, "camera": {"eye": [0,0,1], "target": [0,0,0]}, "environment": {"path": "nope.exr"}}"#).unwrap();
    fails_with(
        &aggtool(
            &[
                "reference",
                "plane45.glb",
                "--view",
                "env.json",
                "-o",
                "x.exr",
            ],
            p,
        ),
        "nope.exr",
    );
    fails_with(&aggtool(&["compare", "nope.exr", "x.exr"], p), "nope.exr");
    fails_with(
        &aggtool(&["reference", "plane45.glb", "-o", "x.exr"], p),
        "--auto-view",
    );
    assert!(!p.join("x.exr").exists(), "no output after a failure");
}

/// A reader that goes away (`aggtool ... | head`) stops the command quietly: no panic.
#[test]
fn closed_stdout_is_not_a_panic() {
    let d = tempfile::tempdir().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_aggtool"))
        .args(["gen", "all", "-o", ".", "--triangles", "2000"])
        .current_dir(d.path())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run aggtool");
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked"), "{err}");
}

/// `aggtool export` writes every mesh once with views inside geometry.bin, every instance, and
/// the textures its materials name; a bad asset fails and leaves the folder empty.
#[test]
fn export_writes_views_instances_and_textures() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    ok(&aggtool(
        &["gen", "buildings", "-o", ".", "--triangles", "800"],
        p,
    ));
    ok(&aggtool(
        &["gen", "foliage", "-o", ".", "--triangles", "800"],
        p,
    ));
    for (asset, dir) in [("buildings.glb", "b"), ("foliage.glb", "f")] {
        let out = ok(&aggtool(&["export", asset, "-o", dir], p));
        assert!(out.contains("output:"), "{out}");
        let info: serde_json::Value =
            serde_json::from_str(&ok(&aggtool(&["info", asset, "--json"], p))).unwrap();
        let scene: serde_json::Value =
            serde_json::from_slice(&std::fs::read(p.join(dir).join("scene.json")).unwrap())
                .unwrap();
        let bin = std::fs::metadata(p.join(dir).join("geometry.bin"))
            .unwrap()
            .len();
        let meshes = scene["meshes"].as_array().unwrap();
        assert_eq!(meshes.len() as u64, info["meshes"].as_u64().unwrap());
        assert_eq!(
            scene["instances"].as_array().unwrap().len() as u64,
            info["instances"].as_u64().unwrap()
        );
        let mut triangles = 0;
        for m in meshes {
            for (key, per) in [
                ("positions", 12),
                ("normals", 12),
                ("uvs", 8),
                ("indices", 4),
            ] {
                if let Some(v) = m[key].as_object() {
                    let end = v["offset"].as_u64().unwrap() + per * v["count"].as_u64().unwrap();
                    assert!(end <= bin, "{key} view ends at {end}, past {bin} bytes");
                }
            }
            triangles += m["indices"]["count"].as_u64().unwrap() / 3;
        }
        assert_eq!(triangles, info["triangles"].as_u64().unwrap());
        for mat in scene["materials"].as_array().unwrap() {
            if let Some(t) = mat["base_color_texture"].as_object() {
                assert!(p.join(dir).join(t["file"].as_str().unwrap()).exists());
            }
        }
    }
    std::fs::write(p.join("bad.obj"), "v 0 0 0\nv 1 0 0\nf 1 2 9\n").unwrap();
    fails_with(&aggtool(&["export", "bad.obj", "-o", "x"], p), "bad.obj");
    assert!(!p.join("x").join("scene.json").exists());
}

/// `convert` writes format 1.4's quantized layout by default, its blocks compressed (1.5), and
/// the float layout with `--lossless`; `inspect --json`
/// gives each level's bytes per component and layout, and the quantized file is smaller in
/// every node, lobe and moment component.
#[test]
fn lossless_and_quantized_layouts() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    ok(&aggtool(
        &["gen", "foliage", "-o", ".", "--triangles", "400"],
        p,
    ));
    let bake = |extra: &[&str], out: &str| {
        tiny_convert(p, extra, out);
        inspect_json(p, out)
    };
    let q = bake(&[], "q.agg");
    let l = bake(&["--lossless"], "l.agg");
    assert_eq!(q["format"], format!("1.{}", aggtool::format::MINOR));
    assert_eq!(q["settings"]["lossless"], false);
    assert_eq!(q["settings"]["compression"], 19);
    // Blocks compressed by default (1.5), stored as they are with level 0: same content.
    let z = bake(&["--compression-level", "0"], "z.agg");
    assert_eq!(z["settings"]["compression"], 0);
    for (a, b) in q["levels"]
        .as_array()
        .unwrap()
        .iter()
        .zip(z["levels"].as_array().unwrap())
    {
        assert_eq!(a["components"], b["components"]);
        assert_eq!(a["inflated_bytes"], b["bytes"]);
        assert!(a["bytes"].as_u64() < b["bytes"].as_u64(), "{a} vs {b}");
        assert!(a["compression_ratio"].as_f64().unwrap() > 1.0);
    }
    let e = aggtool(&["convert", "foliage.glb", "--compression-level", "23"], p);
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("--compression-level"));
    assert_eq!(l["settings"]["lossless"], true);
    for (a, b) in q["levels"]
        .as_array()
        .unwrap()
        .iter()
        .zip(l["levels"].as_array().unwrap())
    {
        assert_eq!(
            (a["quantized"].as_bool(), b["quantized"].as_bool()),
            (Some(true), Some(false))
        );
        let (ca, cb) = (&a["components"], &b["components"]);
        for k in ["lobes", "dielectric_moments", "aiv_nodes", "abv_nodes"] {
            let (x, y) = (ca[k].as_u64().unwrap(), cb[k].as_u64().unwrap());
            assert!(x < y || y == 0, "{k}: {x} quantized vs {y} lossless");
        }
        assert_eq!(ca["voxels"], cb["voxels"]);
    }
    let text = ok(&aggtool(&["inspect", "q.agg"], p));
    assert!(
        text.contains("bytes per component") && text.contains("quantized"),
        "{text}"
    );
}

/// `convert --progress-json` (for programs that run the bake, e.g. the Blender extension):
/// stderr holds only JSON progress lines, each stage of every level from 0 to its total, and
/// the file is the same as without the flag.
#[test]
fn convert_progress_json() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    ok(&aggtool(
        &["gen", "foliage", "-o", ".", "--triangles", "400"],
        p,
    ));
    let bake = |extra: &[&str], out: &str| {
        String::from_utf8_lossy(&tiny_convert(p, extra, out).stderr).into_owned()
    };
    let err = bake(&["--progress-json"], "j.agg");
    let lines: Vec<serde_json::Value> = err
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect();
    for stage in ["8³ voxels", "8³ faces", "4³ voxels", "4³ faces"] {
        let s: Vec<_> = lines.iter().filter(|l| l["stage"] == stage).collect();
        assert!(!s.is_empty(), "no {stage} in {err}");
        assert_eq!(s.first().unwrap()["done"], 0, "{err}");
        assert_eq!(
            s.last().unwrap()["done"],
            s.last().unwrap()["total"],
            "{err}"
        );
    }
    bake(&[], "n.agg");
    assert_eq!(
        std::fs::read(p.join("j.agg")).unwrap(),
        std::fs::read(p.join("n.agg")).unwrap()
    );
}

/// `--preset` starts from the library's preset and flags beside it override it: the file
/// records the preset's values where no flag was given (draft: 2 lobes, 4 AIV rays, fast
/// compression; max: nothing truncated, quantized or compressed) and the flag's where one was.
#[test]
fn presets_and_overrides() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    ok(&aggtool(
        &["gen", "foliage", "-o", ".", "--triangles", "300"],
        p,
    ));
    let convert = |extra: &[&str], out: &str| {
        let mut args = vec![
            "convert",
            "foliage.glb",
            "--max-res",
            "8",
            "--samples",
            "4",
            "-o",
            out,
        ];
        args.extend_from_slice(extra);
        let o = aggtool(&args, p);
        ok(&o);
        o
    };
    let settings = |extra: &[&str], out: &str| {
        convert(extra, out);
        inspect_json(p, out)["settings"].clone()
    };
    let draft = settings(&["--preset", "draft", "--aiv-res", "8"], "d.agg");
    assert_eq!(
        (
            &draft["ndf_lobes"],
            &draft["aiv_rays"],
            &draft["compression"]
        ),
        (&2.into(), &4.into(), &3.into())
    );
    assert_eq!(
        (&draft["aiv_res"], &draft["max_res"]),
        (&8.into(), &8.into()),
        "flags win"
    );
    let max = settings(
        &["--preset", "max", "--aiv-res", "8", "--abv-res", "8"],
        "m.agg",
    );
    assert_eq!((&max["keep"], &max["energy"]), (&1.0.into(), &1.0.into()));
    assert_eq!(
        (&max["lossless"], &max["denoise"], &max["compression"]),
        (&true.into(), &false.into(), &0.into())
    );
    // The AIV bandwidth: chosen per voxel by default, the paper's per-cell average in max, a
    // flag over either; recorded in the file.
    assert_eq!(
        (&draft["aiv_min_rays"], &max["aiv_min_rays"]),
        (&0.into(), &1.into())
    );
    let pooled = settings(&["--aiv-min-rays", "4"], "k.agg");
    assert_eq!(pooled["aiv_min_rays"], 4);
    // The bake reports the bandwidth of every voxel kept: all at the flag's, or spread over
    // the candidates when chosen.
    for (flag, out) in [("4", "k4.agg"), ("0", "k0.agg")] {
        let o = convert(&["--aiv-min-rays", flag, "--report", "r.json"], out);
        let stdout = String::from_utf8_lossy(&o.stdout);
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(p.join("r.json")).unwrap()).unwrap();
        for l in report["levels"].as_array().unwrap() {
            let bw: Vec<u64> = l["aiv_bandwidth"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap())
                .collect();
            assert_eq!(bw.iter().sum::<u64>(), l["voxels"].as_u64().unwrap(), "{l}");
            if flag == "4" {
                assert_eq!(bw[2], l["voxels"].as_u64().unwrap(), "{l}");
            }
        }
        assert!(stdout.contains("AIV bandwidth"), "{stdout}");
        // Every boundary face's ABV bandwidth, chosen by cross-validation.
        for l in report["levels"].as_array().unwrap() {
            let bw: u64 = l["abv_bandwidth"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap())
                .sum();
            assert_eq!(bw, l["faces"].as_u64().unwrap(), "{l}");
        }
        assert!(stdout.contains("; ABV bandwidth "), "{stdout}");
        if flag == "4" {
            assert!(stdout.contains("AIV bandwidth 4 rays 100%"), "{stdout}");
        }
    }
    let e = aggtool(&["convert", "foliage.glb", "--preset", "fast"], p);
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("possible values"));
}
