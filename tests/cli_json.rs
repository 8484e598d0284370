//! `--json` and `--quiet` on every command that reports (issue 40): under `--json` stdout is
//! one JSON object, the report or the error (`{"error", "kind", ...}`), and the exit status is
//! the same as without it; `-q` prints nothing on success and the error on failure. Levels are
//! named by their resolution (`render --level 64`), as `inspect` names them.

mod common;

use std::process::Output;

use common::aggtool;

/// Exit statuses (documented in `aggtool --help`).
const USAGE: i32 = 2;
const INPUT: i32 = 3;
const OUTPUT: i32 = 4;

/// The one JSON object on stdout of `o`.
fn object(o: &Output) -> serde_json::Map<String, serde_json::Value> {
    let out = String::from_utf8_lossy(&o.stdout);
    match serde_json::from_str(&out) {
        Ok(serde_json::Value::Object(m)) => m,
        _ => panic!(
            "stdout is not one JSON object: {out}\nstderr: {}",
            String::from_utf8_lossy(&o.stderr)
        ),
    }
}

/// `command INPUT` framed automatically at 8×8, 1 spp, written to `out`.
fn tiny_view<'a>(command: &'a str, input: &'a str, out: &'a str) -> Vec<&'a str> {
    vec![
        command,
        input,
        "--auto-view",
        "--width",
        "8",
        "--height",
        "8",
        "--spp",
        "1",
        "-o",
        out,
    ]
}

#[test]
fn json_reports_are_one_object_and_errors_too() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    common::tiny_plane(p);
    let render = tiny_view("render", "plane45.agg", "lod.exr");
    let reference = tiny_view("reference", "plane45.glb", "ref.exr");
    let runs: &[&[&str]] = &[
        &["gen", "plane45", "-o", ".", "--triangles", "200"],
        &["info", "plane45.glb"],
        &["inspect", "plane45.agg"],
        &render,
        &reference,
        &["compare", "lod.exr", "ref.exr", "--diff", "d.png"],
        &["export", "plane45.glb", "-o", "exported"],
        &["flatten", "plane45.glb", "-o", "flat"],
        &["tables", "check", "--points", "2", "--mc-samples", "8"],
    ];
    for args in runs {
        let mut a = args.to_vec();
        a.push("--json");
        let o = aggtool(&a, p);
        assert!(
            o.status.success(),
            "{a:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let m = object(&o);
        assert!(!m.is_empty() && !m.contains_key("error"), "{a:?}: {m:?}");
    }
    // A few reports' fields.
    let m = object(&aggtool(&["inspect", "plane45.agg", "--json"], p));
    assert_eq!(m["levels"][0]["res"], 8);
    let m = object(&aggtool(&["compare", "lod.exr", "lod.exr", "--json"], p));
    assert_eq!(m["rmse"], 0.0);
    // Errors: one object with the kind, and the status of the run without --json.
    let errors: &[(&[&str], i32, &str)] = &[
        (&["info", "missing.glb"], INPUT, "input"),
        (&["inspect", "missing.agg"], INPUT, "input"),
        (&["convert", "plane45.glb", "--keep", "2"], USAGE, "usage"),
        (
            &["convert", "plane45.glb", "-o", "exported"],
            OUTPUT,
            "output",
        ),
        (&["render", "plane45.agg", "-o", "x.exr"], USAGE, "usage"),
        (&["render", "plane45.agg", "--bogus-flag"], USAGE, "usage"),
        // A forest whose folder cannot be made (a file is in its path): an output error.
        (
            &[
                "gen",
                "forest",
                "-o",
                "plane45.glb/forest",
                "--species",
                "1",
            ],
            OUTPUT,
            "output",
        ),
    ];
    for (args, code, kind) in errors {
        let plain = aggtool(args, p);
        assert_eq!(plain.status.code(), Some(*code), "{args:?}");
        assert!(plain.stdout.is_empty(), "{args:?}");
        let mut a = args.to_vec();
        a.push("--json");
        let o = aggtool(&a, p);
        assert_eq!(o.status.code(), Some(*code), "{a:?}");
        let m = object(&o);
        assert_eq!(m["kind"], *kind, "{a:?}: {m:?}");
        assert!(m["error"].as_str().is_some_and(|e| !e.is_empty()), "{m:?}");
        assert_eq!(m["exit_code"], *code, "{m:?}");
    }
}

#[test]
fn quiet_prints_nothing_on_success_and_the_error_on_failure() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    common::tiny_plane(p);
    for args in [
        &["-q", "gen", "plane45", "-o", ".", "--triangles", "200"][..],
        &["inspect", "plane45.agg", "--quiet"],
        &[tiny_view("render", "plane45.agg", "q.exr"), vec!["-q"]].concat(),
    ] {
        let o = aggtool(args, p);
        assert!(o.status.success(), "{args:?}");
        assert!(
            o.stdout.is_empty(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stdout)
        );
        assert!(
            o.stderr.is_empty(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    assert!(p.join("q.exr").is_file() && p.join("q.png").is_file());
    let o = aggtool(&["-q", "inspect", "missing.agg"], p);
    assert_eq!(o.status.code(), Some(INPUT));
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.agg"));
}

#[test]
fn render_level_is_a_resolution() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    common::tiny_plane(p);
    let render = |level: &str, out: &str| {
        let mut a = tiny_view("render", "plane45.agg", out);
        a.extend(["--level", level, "--json"]);
        aggtool(&a, p)
    };
    // The levels are 8³ and 4³: --level 4 draws the coarse one only.
    let m = object(&render("4", "l4.exr"));
    assert_eq!(m["assets"][0]["levels_used"], serde_json::json!([4]));
    let m = object(&render("8", "l8.exr"));
    assert_eq!(m["assets"][0]["levels_used"], serde_json::json!([8]));
    // An index (0) or a resolution the file lacks is an error listing those it has.
    for bad in ["0", "16"] {
        let o = render(bad, "bad.exr");
        assert_eq!(o.status.code(), Some(USAGE), "--level {bad}");
        let m = object(&o);
        let e = m["error"].as_str().unwrap();
        assert!(e.contains("8, 4") && e.contains(bad), "{e}");
    }
}
