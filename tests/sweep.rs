//! `aggtool sweep`: the table files hold the planned rows, the Pareto plots are PNGs, a second
//! sweep into the same folder bakes only what is new or changed, and bad `--vary` names and
//! values are refused before anything is written. Tiny bakes (8³/4³, 8² maps, a few samples)
//! on a 200-triangle plane, 8² pixels: each sweep takes about a second.

use std::path::Path;
use std::process::Output;

mod common;
use common::{aggtool, ok};

/// `aggtool sweep plane45.glb` with tiny bakes and renders, `extra` flags, into `out`.
fn tiny_sweep(dir: &Path, extra: &[&str], out: &str) -> Output {
    let mut args = vec![
        "sweep",
        "plane45.glb",
        "--res",
        "8",
        "--spp",
        "4",
        "--reference-spp",
        "16",
        "--min-res",
        "4",
        "--samples",
        "4",
        "--aiv-res",
        "8",
        "--aiv-rays",
        "4",
        "--abv-res",
        "8",
        "--abv-full-res",
        "8",
        "-o",
        out,
    ];
    args.extend_from_slice(extra);
    aggtool(&args, dir)
}

/// The labels of the lines of `stdout` that start with `what: ` (e.g. `baked`), up to the
/// colon or the parenthesis that follows the label.
fn labels(stdout: &str, what: &str) -> Vec<String> {
    stdout
        .lines()
        .filter_map(|l| l.strip_prefix(&format!("{what}: ")))
        .map(|l| l.split([':', ' ']).next().unwrap_or_default().to_string())
        .collect()
}

fn gen_plane(dir: &Path) {
    ok(&aggtool(
        &["gen", "plane45", "-o", ".", "--triangles", "200"],
        dir,
    ));
}

#[test]
fn sweep_writes_tables_and_plots_and_resumes() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    gen_plane(p);
    // First sweep: four presets, one varied lobe count, and keep=15%, which is the default
    // preset's value: baked once, reported as the same settings.
    let out = ok(&tiny_sweep(
        p,
        &["--vary", "ndf_lobes=1", "--vary", "keep=15%"],
        "s",
    ));
    let s = p.join("s");
    let rows_of = |file: &str| -> Vec<serde_json::Value> {
        let t: serde_json::Value =
            serde_json::from_slice(&std::fs::read(s.join(file)).unwrap()).unwrap();
        t["rows"].as_array().unwrap().clone()
    };
    let rows = rows_of("table.json");
    let names: Vec<&str> = rows.iter().map(|r| r["label"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "preset=draft",
            "preset=default",
            "preset=high",
            "preset=max",
            "ndf_lobes=1",
            "keep=15%"
        ]
    );
    for r in &rows {
        let rmse = r["rmse"].as_f64().unwrap();
        assert!(rmse.is_finite() && rmse > 0.0, "{r}");
        assert!(r["bytes"].as_u64().unwrap() > 0 && r["bake_seconds"].as_f64().unwrap() > 0.0);
        // The table's costs are CPU seconds, recorded beside the wall seconds.
        let cpu = |k: &str| r[k].as_f64().unwrap();
        assert!(
            cpu("bake_cpu_seconds") > 0.0 && cpu("render_cpu_seconds") >= 0.0,
            "{r}"
        );
        assert!(r["components"]["voxels"].as_u64().unwrap() > 0, "{r}");
        assert!(s.join(r["image"].as_str().unwrap()).exists());
        // The meshopt mesh of the row's bytes, rendered and compared beside it.
        let m = &r["mesh"];
        assert!(m["rmse"].as_f64().unwrap().is_finite(), "{r}");
        assert!(m["triangles"].as_u64().unwrap() >= 1, "{r}");
    }
    // The varied row has the base's settings with one field changed; max is the paper's
    // control; the default row is the base.
    assert_eq!(rows[4]["settings"]["ndf_lobes"], 1);
    assert_eq!(rows[3]["settings"]["keep"], 1.0);
    assert_eq!(rows[1]["base"], true);
    let mut same = rows[4]["settings"].clone();
    same["ndf_lobes"] = rows[1]["settings"]["ndf_lobes"].clone();
    assert_eq!(same, rows[1]["settings"], "only ndf_lobes differs");
    assert_eq!(rows[5]["rmse"], rows[1]["rmse"]);
    assert_eq!(labels(&out, "baked").len(), 5, "{out}");
    assert!(
        out.contains("reused: keep=15% (same settings as preset=default)"),
        "{out}"
    );
    let md = std::fs::read_to_string(s.join("table.md")).unwrap();
    assert!(md.contains("mesh of equal bytes"), "{md}");
    for n in &names {
        assert!(md.contains(&format!("| {n}")), "{n} missing from {md}");
    }
    for plot in [
        "pareto-bake-seconds.png",
        "pareto-mib.png",
        "pareto-render-seconds.png",
    ] {
        let b = std::fs::read(s.join(plot)).unwrap();
        assert_eq!(&b[..8], b"\x89PNG\r\n\x1a\n", "{plot} is a PNG");
    }
    // Second sweep with one more value: only that one is baked; the other rows, and the
    // reference, are reused untouched.
    let row1 = s.join("rows").join("ndf_lobes=1.json");
    let before = std::fs::read(&row1).unwrap();
    let mtime = std::fs::metadata(&row1).unwrap().modified().unwrap();
    let out = ok(&tiny_sweep(
        p,
        &["--vary", "ndf_lobes=1,2", "--vary", "keep=15%"],
        "s",
    ));
    assert_eq!(labels(&out, "baked"), ["ndf_lobes=2"], "{out}");
    assert!(out.contains("reused: reference"), "{out}");
    assert_eq!(labels(&out, "reused").len(), 7, "{out}");
    assert_eq!(std::fs::read(&row1).unwrap(), before);
    assert_eq!(std::fs::metadata(&row1).unwrap().modified().unwrap(), mtime);
    assert_eq!(rows_of("table.json").len(), 7);
    // An interrupted sweep (a row never written) bakes that row alone.
    std::fs::remove_file(s.join("rows").join("preset=max.json")).unwrap();
    let out = ok(&tiny_sweep(p, &["--vary", "ndf_lobes=1,2"], "s"));
    assert_eq!(labels(&out, "baked"), ["preset=max"], "{out}");
    // Other bake flags are other settings: nothing is reused but the reference.
    let out = ok(&tiny_sweep(
        p,
        &["--moment-res", "2", "--vary", "ndf_lobes=1"],
        "s",
    ));
    assert_eq!(labels(&out, "baked").len(), 5, "{out}");
    assert!(out.contains("reused: reference"), "{out}");
}

#[test]
fn bad_vary_is_refused_naming_the_settings() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    gen_plane(p);
    for (vary, needles) in [
        (
            "lobes=1,2",
            &[
                "unknown bake setting 'lobes'",
                "ndf_lobes",
                "keep",
                "aiv_rays",
            ][..],
        ),
        ("ndf_lobes=1.5", &["ndf_lobes=1.5"][..]),
        ("ndf_lobes=9", &["--ndf-lobes must be 1 to 4"][..]),
        ("ndf_lobes", &["NAME=V1,V2"][..]),
    ] {
        let o = tiny_sweep(p, &["--vary", vary], "bad");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{vary} accepted");
        for n in needles {
            assert!(err.contains(n), "{vary}: '{err}' should name '{n}'");
        }
        assert!(!err.contains("panicked"), "{err}");
        assert!(!p.join("bad").exists(), "{vary}: nothing written");
    }
}
