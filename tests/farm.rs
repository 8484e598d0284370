//! Farm bakes: `aggtool convert --shard I/N` parts merged by `aggtool merge` are the bytes of
//! the one-machine bake, and the merge refuses incomplete or mixed sets of parts.

use std::path::{Path, PathBuf};

mod common;
use common::aggtool;

fn ok(args: &[&str], dir: &Path) -> String {
    let o = aggtool(args, dir);
    assert!(
        o.status.success(),
        "aggtool {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A merge that must fail: its error, and no output left behind.
fn refused(args: &[&str], dir: &Path, out: &str) -> String {
    let o = aggtool(args, dir);
    assert!(!o.status.success(), "aggtool {args:?} succeeded");
    assert!(!dir.join(out).exists(), "a refused merge wrote {out}");
    let leftovers: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn shards_merge_into_the_one_machine_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&["gen", "foliage", "--triangles", "2000", "-o", "."], d);
    // At 64³ the finest level has several voxel and face chunks, so that the shards interleave
    // blocks within a level, not only across levels; the last case has a visibility level
    // (format 1.7), whose shard holds no AIV.
    let cases: [(&str, u32, &[&str]); 3] = [
        ("16", 3, &[]),
        ("64", 4, &[]),
        ("16", 3, &["--visibility-levels", "1"]),
    ];
    for (max_res, n, extra) in cases {
        let mut t = common::tiny_bake_flags(max_res);
        t.extend(extra);
        let mut args = vec!["convert", "foliage.glb", "-o", "one.agg"];
        args.extend(&t);
        ok(&args, d);
        let parts: Vec<String> = (0..n).map(|i| format!("part{i}.aggpart")).collect();
        for (i, p) in parts.iter().enumerate() {
            let shard = format!("{i}/{n}");
            let mut args = vec!["convert", "foliage.glb", "--shard", &shard, "-o", p];
            args.extend(&t);
            ok(&args, d);
        }
        // Any order of the parts.
        let mut args = vec!["merge", "-o", "merged.agg"];
        args.extend(parts.iter().rev().map(|s| s.as_str()));
        ok(&args, d);
        let one = std::fs::read(d.join("one.agg")).unwrap();
        let merged = std::fs::read(d.join("merged.agg")).unwrap();
        assert!(
            one == merged,
            "max-res {max_res}, {n} shards: merged {} bytes differ from the single bake's {}",
            merged.len(),
            one.len()
        );
        // Every shard holds some blocks, none all of them (the share is real).
        for p in &parts {
            let len = std::fs::metadata(d.join(p)).unwrap().len() as usize;
            assert!(len < one.len(), "{p} holds {len} bytes of {}", one.len());
        }
        if max_res == "64" {
            let s = ok(&["inspect", "merged.agg"], d);
            assert!(s.contains("64"), "{s}");
        }
        if !extra.is_empty() {
            let s = ok(&["inspect", "merged.agg"], d);
            assert!(s.contains("visibility levels (1.7)"), "{s}");
        }
        std::fs::remove_file(d.join("merged.agg")).unwrap();
    }
}

#[test]
fn merge_refuses_missing_duplicate_and_mismatched_parts() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&["gen", "foliage", "--triangles", "2000", "-o", "."], d);
    let t = common::tiny_bake_flags("16");
    for i in 0..3 {
        let shard = format!("{i}/3");
        let out = format!("p{i}.aggpart");
        let mut args = vec!["convert", "foliage.glb", "--shard", &shard, "-o", &out];
        args.extend(&t);
        ok(&args, d);
    }
    // The same shard 2/3 with other settings, and shard 0/2.
    let mut args = vec![
        "convert",
        "foliage.glb",
        "--shard",
        "2/3",
        "-o",
        "other2.aggpart",
    ];
    args.extend(&t);
    args.extend(["--keep", "0.2"]);
    ok(&args, d);
    let mut args = vec![
        "convert",
        "foliage.glb",
        "--shard",
        "0/2",
        "-o",
        "half0.aggpart",
    ];
    args.extend(&t);
    ok(&args, d);
    ok(
        &["convert", "foliage.glb", "-o", "one.agg"]
            .into_iter()
            .chain(t.clone())
            .collect::<Vec<_>>(),
        d,
    );

    let e = refused(
        &["merge", "p0.aggpart", "p2.aggpart", "-o", "out.agg"],
        d,
        "out.agg",
    );
    assert!(e.contains("missing shard(s) 1/3"), "{e}");
    let e = refused(
        &[
            "merge",
            "p0.aggpart",
            "p1.aggpart",
            "p1.aggpart",
            "p2.aggpart",
            "-o",
            "out.agg",
        ],
        d,
        "out.agg",
    );
    assert!(e.contains("duplicate shard 1/3"), "{e}");
    let e = refused(
        &[
            "merge",
            "p0.aggpart",
            "p1.aggpart",
            "other2.aggpart",
            "-o",
            "out.agg",
        ],
        d,
        "out.agg",
    );
    assert!(
        e.contains("not shards of the same bake") && e.contains("settings"),
        "{e}"
    );
    let e = refused(
        &[
            "merge",
            "p0.aggpart",
            "p1.aggpart",
            "half0.aggpart",
            "-o",
            "out.agg",
        ],
        d,
        "out.agg",
    );
    assert!(e.contains("of 3 shards"), "{e}");
    let e = refused(
        &["merge", "p0.aggpart", "one.agg", "-o", "out.agg"],
        d,
        "out.agg",
    );
    assert!(
        e.contains("one.agg") && e.contains("not a part file"),
        "{e}"
    );
    // A damaged block (a byte flipped in the blob area): the checksum names the part.
    let mut bytes = std::fs::read(d.join("p1.aggpart")).unwrap();
    bytes[40] ^= 0xff;
    std::fs::write(d.join("bad1.aggpart"), &bytes).unwrap();
    let e = refused(
        &[
            "merge",
            "p0.aggpart",
            "bad1.aggpart",
            "p2.aggpart",
            "-o",
            "out.agg",
        ],
        d,
        "out.agg",
    );
    assert!(e.contains("bad1.aggpart") && e.contains("checksum"), "{e}");
    // An existing output is left as it was.
    std::fs::write(d.join("out.agg"), b"keep me").unwrap();
    let o = aggtool(&["merge", "p0.aggpart", "p2.aggpart", "-o", "out.agg"], d);
    assert!(!o.status.success());
    assert_eq!(std::fs::read(d.join("out.agg")).unwrap(), b"keep me");
    // Bad shard arguments.
    let o = aggtool(&["convert", "foliage.glb", "--shard", "3/3"], d);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("0 <= I < N"));
}

/// What the farm templates run without openjd: `assemble --list`, one asset per task
/// (`--asset-number`), then `--require-reuse`; `merge --parts-of` and `--remove-parts`.
#[test]
fn farm_commands_one_asset_per_task_then_assemble_reuses() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(
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
        d,
    );
    let ids = ok(&["assemble", "f/forest.json", "--list"], d);
    let ids: Vec<&str> = ids.lines().collect();
    assert_eq!(ids.len(), 3, "{ids:?}");
    let t = common::tiny_bake_flags("16");
    // Before the tasks, --require-reuse fails (it would bake).
    let mut args = vec!["assemble", "f/forest.json", "--require-reuse"];
    args.extend(&t);
    let o = aggtool(&args, d);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("had to be baked"));
    std::fs::remove_dir_all(d.join("f")).unwrap();
    ok(
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
        d,
    );
    for k in 1..=3 {
        let k = k.to_string();
        let mut args = vec!["assemble", "f/forest.json", "--asset-number", &k];
        args.extend(&t);
        let s = ok(&args, d);
        assert!(s.contains("1 assets: 1 baked, 0 reused"), "{s}");
    }
    let mut args = vec!["assemble", "f/forest.json", "--require-reuse"];
    args.extend(&t);
    let s = ok(&args, d);
    assert!(s.contains("3 assets: 0 baked, 3 reused"), "{s}");
    let o = aggtool(&["assemble", "f/forest.json", "--asset-number", "4"], d);
    assert!(String::from_utf8_lossy(&o.stderr).contains("no asset number 4"));
    let o = aggtool(&["assemble", "f/forest.json", "--asset", "nope"], d);
    assert!(String::from_utf8_lossy(&o.stderr).contains("no asset 'nope'"));

    // Sharded: parts named as the template names them, merged and removed.
    ok(&["gen", "foliage", "--triangles", "1000", "-o", "."], d);
    let mut args = vec!["convert", "foliage.glb", "-o", "one.agg"];
    args.extend(&t);
    ok(&args, d);
    for i in 0..2 {
        let shard = format!("{i}/2");
        let mut args = vec!["convert", "foliage.glb", "--shard", &shard, "-o"];
        let out = format!("out/x.agg.{i}-of-2.aggpart");
        args.push(&out);
        args.extend(&t);
        ok(&args, d);
    }
    ok(
        &[
            "merge",
            "--parts-of",
            "out/x.agg",
            "--shards",
            "2",
            "--remove-parts",
            "-o",
            "out/x.agg",
        ],
        d,
    );
    assert_eq!(
        std::fs::read(d.join("one.agg")).unwrap(),
        std::fs::read(d.join("out/x.agg")).unwrap()
    );
    let left: Vec<_> = std::fs::read_dir(d.join("out")).unwrap().collect();
    assert_eq!(left.len(), 1, "parts left after --remove-parts");
}
