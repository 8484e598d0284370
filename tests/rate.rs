//! Rate control (issue 42): a size budget is met within 3%, an error bound holds on the maps
//! as decoded, re-rating a file needs no bake, and the bytes do not depend on the threads.

mod common;

use aggtool::bake::rate::{map_weights, RateTarget, TOLERANCE};
use aggtool::bake::{bake_to_file, rate_file, BakeReport, BakeSettings};
use aggtool::format::{Aggregate, VoxelData};
use aggtool::math::haar::SparseHaar;
use aggtool::scene::Scene;
use std::path::Path;

const MIB: f64 = 1024.0 * 1024.0;

fn scene() -> Scene {
    common::gen_scene("foliage", 3000)
}

/// Small settings whose candidates still outweigh the rest of the file.
fn settings() -> BakeSettings {
    BakeSettings {
        aiv_res: 16,
        abv_res: 16,
        ..common::small_bake(16)
    }
}

fn bake(sc: &Scene, s: &BakeSettings, path: &Path) -> BakeReport {
    bake_to_file(sc, "test.glb", s, path, &aggtool::util::no_progress).unwrap()
}

/// A bake of `base` that keeps every candidate (`--keep 1 --energy 1`) at `path`.
fn bake_candidates(sc: &Scene, base: &BakeSettings, path: &Path) -> BakeReport {
    let s = BakeSettings {
        keep: 1.0,
        energy: 1.0,
        ..base.clone()
    };
    bake(sc, &s, path)
}

/// `base` baked with the per-map rule (`block_allocation` off) and as it is (the block
/// allocation) into `dir`: the two files' paths, maps first.
fn bake_maps_and_blocks(
    sc: &Scene,
    base: &BakeSettings,
    dir: &Path,
) -> (std::path::PathBuf, std::path::PathBuf) {
    let maps = dir.join("maps.agg");
    let s = BakeSettings {
        block_allocation: false,
        ..base.clone()
    };
    bake(sc, &s, &maps);
    let blocks = dir.join("blocks.agg");
    bake(sc, base, &blocks);
    (maps, blocks)
}

/// Every candidate kept, the smallest file, and a budget between them is met within 3% under
/// it, by the bake and by re-rating the candidates' file; a budget below the smallest file
/// says so and writes the smallest; one above everything keeps every candidate.
#[test]
fn size_budgets_are_met_within_three_percent() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene();
    let all_path = dir.path().join("all.agg");
    let all = bake_candidates(&sc, &settings(), &all_path);
    let agg = Aggregate::open(&all_path).unwrap();
    // The smallest file: a budget of one byte cannot be met.
    let (least, r) = rate_file(
        &agg,
        RateTarget::FileBytes(1),
        &dir.path().join("least.agg"),
    )
    .unwrap();
    assert!(
        !r.met && r.message.contains("without any visibility detail"),
        "{r:?}"
    );
    assert!(least < all.bytes, "{least} vs {}", all.bytes);
    for share in [0.3, 0.6, 0.9] {
        let budget = least as f64 + share * (all.bytes - least) as f64;
        let s = BakeSettings {
            size_mib: budget / MIB,
            ..settings()
        };
        let path = dir.path().join(format!("b{share}.agg"));
        let r = bake(&sc, &s, &path);
        let size = std::fs::metadata(&path).unwrap().len() as f64;
        let rate = r.rate.as_ref().unwrap();
        assert!(rate.met, "{}", rate.line());
        assert_eq!(rate.bytes as f64, size);
        let budget = (budget / MIB * MIB).round();
        assert!(
            size <= budget && size >= (1.0 - TOLERANCE) * budget,
            "{size} for a budget of {budget}: {}",
            rate.line()
        );
        // Re-rating the candidates' file lands in the same band.
        let (size2, r2) = rate_file(
            &agg,
            RateTarget::FileBytes(budget as u64),
            &dir.path().join("re.agg"),
        )
        .unwrap();
        assert!(r2.met && size2 as f64 <= budget, "{} {size2}", r2.line());
        Aggregate::open(&path).unwrap().verify_all().unwrap();
    }
    // A budget above everything keeps every candidate: the levels decode as the input's
    // (trees compared as maps: the input may hold nodes whose details quantized to zero,
    // which the rate control prunes).
    let big = dir.path().join("big.agg");
    let (_, r) = rate_file(&agg, RateTarget::FileBytes(all.bytes * 2), &big).unwrap();
    assert!(r.met && r.kept == r.candidates, "{}", r.line());
    let big = Aggregate::open(&big).unwrap();
    for l in 0..agg.level_count() {
        let (x, y) = (big.read_level(l), agg.read_level(l));
        assert_eq!(x.voxels.len(), y.voxels.len());
        assert_eq!(x.faces.len(), y.faces.len());
        for (a, b) in x.voxels.iter().zip(&y.voxels) {
            // Lobe frames are quantized again, which moves them by less than a step.
            for (p, q) in a.appearance.lobes.iter().zip(&b.appearance.lobes) {
                assert!(
                    p.frame.abs_diff_eq(q.frame, 1e-4),
                    "level {l}: voxel {}",
                    a.key
                );
            }
            let mut same = VoxelData {
                aiv: b.aiv.clone(),
                ..a.clone()
            };
            for (p, q) in same.appearance.lobes.iter_mut().zip(&b.appearance.lobes) {
                p.frame = q.frame;
            }
            assert_eq!(same, *b, "level {l}: voxel {} changed", a.key);
            assert_eq!(cells(&a.aiv), cells(&b.aiv), "level {l}: AIV of {}", a.key);
        }
        for (a, b) in x.faces.iter().zip(&y.faces) {
            assert_eq!(a.face, b.face);
            assert_eq!(
                cells(&a.abv),
                cells(&b.abv),
                "level {l}: ABV of {:?}",
                a.face
            );
        }
    }
}

/// A map's cells, as decoded.
fn cells(t: &SparseHaar) -> Vec<f32> {
    (0..t.n * t.n).map(|i| t.eval(i % t.n, i / t.n)).collect()
}

/// The error estimate is what the maps lose, as decoded: for each level, the weighted sum
/// over maps of the squared differences between the candidate and the truncated map, cell by
/// cell (Parseval says it equals the dropped details' energy), and `--error` bounds it.
#[test]
fn error_bound_holds_on_the_decoded_maps() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene();
    // Float trees, so that the comparison sees the truncation alone.
    let base = BakeSettings {
        lossless: true,
        ..settings()
    };
    let all_path = dir.path().join("all.agg");
    bake_candidates(&sc, &base, &all_path);
    let all = Aggregate::open(&all_path).unwrap();
    let mut sizes = Vec::new();
    let mut flattened_total = 0;
    for bound in [0.005, 0.02, 0.08] {
        let path = dir.path().join(format!("e{bound}.agg"));
        let r = bake(
            &sc,
            &BakeSettings {
                error: bound,
                ..base.clone()
            },
            &path,
        );
        let rate = r.rate.unwrap();
        let cut = Aggregate::open(&path).unwrap();
        for l in 0..all.level_count() {
            let (d, flattened) = level_error(&all.read_level(l), &cut.read_level(l));
            flattened_total += flattened;
            let measured = d.sqrt();
            let estimate = rate.level_errors[l];
            assert!(
                (measured - estimate).abs() <= 1e-3 * bound + 1e-4 * estimate,
                "level {l}: decoded {measured} vs estimate {estimate}"
            );
            assert!(
                measured <= bound * (1.0 + 1e-4),
                "level {l}: {measured} > {bound}"
            );
        }
        sizes.push(std::fs::metadata(&path).unwrap().len());
    }
    assert!(sizes[0] > sizes[1] && sizes[1] > sizes[2], "{sizes:?}");
    // Some voxel lost its directional moments to a bound (else the test checks nothing of
    // them).
    assert!(flattened_total > 0);
}

/// The block allocation (the default) keeps, in every level, at most the weighted squared
/// error of the per-map truncation (`--block-allocation false`) against the candidates, as
/// decoded, in fewer bytes; its bytes do not depend on the threads.
#[test]
fn block_allocation_keeps_the_per_map_error_in_fewer_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene();
    let base = BakeSettings {
        lossless: true,
        ..settings()
    };
    assert!(base.block_allocation, "the default");
    let all_path = dir.path().join("all.agg");
    bake_candidates(&sc, &base, &all_path);
    let all = Aggregate::open(&all_path).unwrap();
    let (maps_path, blocks_path) = bake_maps_and_blocks(&sc, &base, dir.path());
    let (maps, blocks) = (
        Aggregate::open(&maps_path).unwrap(),
        Aggregate::open(&blocks_path).unwrap(),
    );
    assert!(blocks.settings().block_allocation && !maps.settings().block_allocation);
    let mut flattened_total = 0;
    for l in 0..all.level_count() {
        let a = all.read_level(l);
        let (dm, _) = level_error(&a, &maps.read_level(l));
        let (db, flattened) = level_error(&a, &blocks.read_level(l));
        flattened_total += flattened;
        assert!(db <= dm * (1.0 + 1e-4) + 1e-12, "level {l}: {db} > {dm}");
    }
    let bytes = |p: &Path| std::fs::metadata(p).unwrap().len();
    assert!(
        bytes(&blocks_path) < bytes(&maps_path),
        "{} >= {}",
        bytes(&blocks_path),
        bytes(&maps_path)
    );
    assert!(
        flattened_total > 0,
        "no moments flattened: the test sees none"
    );
    // The same bytes on one thread.
    let one = dir.path().join("one.agg");
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| bake(&sc, &base, &one));
    assert_eq!(
        std::fs::read(&one).unwrap(),
        std::fs::read(&blocks_path).unwrap()
    );
}

/// Black voxels (albedo 0: a black material with its specular reflection switched off) still
/// have their maps truncated by the block allocation: with weights a·ρ² of 0 a block had no
/// error to spend and kept every candidate, several times the bytes of the per-map rule
/// (their maps weigh the cone share's contrast, [`aggtool::bake::rate::SHARE_CONTRAST`]).
#[test]
fn black_voxels_are_truncated() {
    let dir = tempfile::tempdir().unwrap();
    let mut sc = scene();
    for m in &mut sc.materials {
        m.base_color = glam::Vec4::new(0.0, 0.0, 0.0, m.base_color.w);
        m.specular_factor = 0.0;
        m.metallic = 0.0;
    }
    let base = settings();
    assert!(base.block_allocation, "the default");
    let (maps, blocks) = bake_maps_and_blocks(&sc, &base, dir.path());
    let all = dir.path().join("all.agg");
    bake_candidates(&sc, &base, &all);
    let bytes = |p: &Path| std::fs::metadata(p).unwrap().len();
    let (m, b, a) = (bytes(&maps), bytes(&blocks), bytes(&all));
    assert!(
        a > m + m / 4,
        "the candidates ({a}) barely outweigh the per-map rule ({m})"
    );
    assert!(b <= m, "block allocation {b} bytes > per-map rule {m}");
}

/// A level's weighted squared error against its candidates, as decoded (the rate control's
/// estimate, [`error_bound_holds_on_the_decoded_maps`]), and how many voxels lost their
/// directional moments.
fn level_error(a: &aggtool::format::LevelData, c: &aggtool::format::LevelData) -> (f64, usize) {
    let (w, wf) = map_weights(a.voxels.iter(), a.faces.iter(), a.grid.voxel_size());
    let sq = |x: &SparseHaar, y: &SparseHaar| {
        let (x, y) = (cells(x), cells(y));
        x.iter()
            .zip(&y)
            .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
            .sum::<f64>()
    };
    let surface = |v: &VoxelData| v.area * v.coverage as f64;
    let s2 = (a.grid.voxel_size() as f64).powi(2);
    let total = a.voxels.iter().map(surface).sum::<f64>() + a.faces.len() as f64 * s2;
    let rho = |m: &aggtool::absdf::MaterialMoments| m.diffuse() + m.reflectance();
    let (mut d, mut flattened) = (0f64, 0);
    assert_eq!(a.voxels.len(), c.voxels.len());
    for ((va, vc), w) in a.voxels.iter().zip(&c.voxels).zip(&w) {
        d += w * sq(&va.aiv, &vc.aiv);
        use aggtool::absdf::Moments;
        if let (
            Moments::Directional {
                diffuse, specular, ..
            },
            Moments::Constant(flat),
        ) = (&va.appearance.moments, &vc.appearance.moments)
        {
            let mean_v = va.aiv.scaling as f64 / va.aiv.n as f64;
            let cells = diffuse.iter().chain(specular);
            let n = (diffuse.len() + specular.len()) as f64;
            let e = cells
                .map(|m| (rho(m) - rho(flat)).length_squared() as f64 / 3.0)
                .sum::<f64>()
                / n;
            d += surface(va) / total * mean_v * mean_v * e;
            flattened += 1;
        }
    }
    for (fa, fc) in a.faces.iter().zip(&c.faces) {
        d += wf * sq(&fa.abv, &fc.abv);
    }
    (d, flattened)
}

/// The same settings with a budget give the same bytes on one thread and on two.
#[test]
fn budgeted_bytes_do_not_depend_on_threads() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene();
    let s = BakeSettings {
        size_mib: 0.05,
        ..settings()
    };
    let run = |threads: usize, name: &str| {
        let path = dir.path().join(name);
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| bake(&sc, &s, &path));
        std::fs::read(&path).unwrap()
    };
    assert!(run(1, "a.agg") == run(2, "b.agg"), "1 and 2 threads differ");
}

/// Two targets at once, a negative one, and a sharded bake with a target are refused with a
/// message naming the flags.
#[test]
fn bad_targets_are_refused() {
    let s = settings();
    let two = BakeSettings {
        size_mib: 1.0,
        error: 0.01,
        ..s.clone()
    };
    let e = two.validate().unwrap_err();
    assert!(e.contains("--size-mib") && e.contains("--error"), "{e}");
    let neg = s.with_field("level_mib", "-2").unwrap_err();
    assert!(neg.contains("--level-mib"), "{neg}");
    let nan = BakeSettings {
        size_mib: f64::NAN,
        ..s.clone()
    };
    assert!(nan.validate().is_err());
    let dir = tempfile::tempdir().unwrap();
    let e = aggtool::bake::bake_shard_to_file(
        &scene(),
        "t",
        &BakeSettings { size_mib: 1.0, ..s },
        aggtool::format::part::Shard { index: 0, count: 2 },
        &dir.path().join("p.aggpart"),
        &aggtool::util::no_progress,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("shards") && e.contains("--size-mib"), "{e}");
}

/// `aggtool convert --size-mib` and `aggtool rate` from the command line: the JSON report
/// says what was met, a missing input is an input error (3), a folder as the output an output
/// error (4), and no target a usage error (2); a failed run leaves no file.
#[test]
fn rate_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::ok(&common::aggtool(
        &["gen", "foliage", "-o", ".", "--triangles", "800"],
        d,
    ));
    let mut args = vec![
        "convert",
        "foliage.glb",
        "-q",
        "-o",
        "all.agg",
        "--keep",
        "1",
        "--energy",
        "1",
    ];
    args.extend(common::tiny_bake_flags("8"));
    common::ok(&common::aggtool(&args, d));
    let all = std::fs::metadata(d.join("all.agg")).unwrap().len() as f64;
    let budget = format!("{}", 0.95 * all / MIB);
    let out = common::ok(&common::aggtool(
        &[
            "rate",
            "all.agg",
            "--size-mib",
            &budget,
            "-o",
            "r.agg",
            "--json",
        ],
        d,
    ));
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(j["rate"]["met"], true, "{j}");
    assert_eq!(
        j["bytes"].as_u64().unwrap(),
        std::fs::metadata(d.join("r.agg")).unwrap().len()
    );
    let mut args = vec![
        "convert",
        "foliage.glb",
        "-o",
        "c.agg",
        "--size-mib",
        &budget,
    ];
    args.extend(common::tiny_bake_flags("8"));
    let out = common::ok(&common::aggtool(&args, d));
    assert!(out.contains("stats: rate: met a"), "{out}");
    let code = |args: &[&str]| common::aggtool(args, d).status.code();
    assert_eq!(
        code(&["rate", "none.agg", "--error", "0.01", "-o", "x.agg"]),
        Some(3)
    );
    assert_eq!(
        code(&["rate", "all.agg", "--error", "0.01", "-o", "."]),
        Some(4)
    );
    assert_eq!(code(&["rate", "all.agg", "-o", "x.agg"]), Some(2));
    assert!(!d.join("x.agg").exists());
}

/// `--level-mib` budgets the finest level alone: its blocks land within 3% under the budget
/// (each blob counted with the alignment padding before it), and coarser levels follow the
/// same multiplier.
#[test]
fn level_budget_counts_the_finest_level() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene();
    let all_path = dir.path().join("all.agg");
    bake_candidates(&sc, &settings(), &all_path);
    let all = Aggregate::open(&all_path).unwrap();
    let (v, f) = all.level_bytes(0);
    let budget = 0.7 * (v + f) as f64;
    let path = dir.path().join("l.agg");
    let r = bake(
        &sc,
        &BakeSettings {
            level_mib: budget / MIB,
            ..settings()
        },
        &path,
    );
    let rate = r.rate.unwrap();
    assert!(rate.met, "{}", rate.line());
    let budget = (budget / MIB * MIB).round();
    let agg = Aggregate::open(&path).unwrap();
    let (v, f) = agg.level_bytes(0);
    let (bv, bf) = agg.block_counts(0);
    let padded = rate.bytes as f64;
    assert!(
        padded <= budget && padded >= (1.0 - TOLERANCE) * budget,
        "{padded} for {budget}"
    );
    assert!(((v + f) as f64) <= padded && padded - ((v + f) as f64) < 64.0 * (bv + bf) as f64);
    // The coarser levels lost details too (one multiplier), so they are smaller than in the
    // file that keeps every candidate.
    let coarser = |a: &Aggregate| {
        (1..a.level_count())
            .map(|l| a.level_bytes(l).0 + a.level_bytes(l).1)
            .sum::<u64>()
    };
    assert!(coarser(&agg) < coarser(&all));
}

/// `assemble --size-mib` budgets every asset of a manifest alike: each aggregate whose
/// candidates exceed the budget lands within 3% under it, and one below it keeps everything.
#[test]
fn assemble_budgets_every_asset() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let gen = |out: &str| {
        common::ok(&common::aggtool(
            &[
                "gen",
                "forest",
                "-o",
                out,
                "--species",
                "2",
                "--instances",
                "6",
                "--triangles",
                "1500",
            ],
            d,
        ))
    };
    gen("all");
    gen("budget");
    let assemble = |manifest: &str, extra: &[&str]| {
        let mut args = vec!["assemble", manifest, "-q"];
        args.extend(common::tiny_bake_flags("8"));
        args.extend(extra);
        common::ok(&common::aggtool(&args, d))
    };
    assemble("all/forest.json", &["--keep", "1", "--energy", "1"]);
    let sizes = |sub: &str| -> Vec<(String, u64)> {
        let mut v: Vec<(String, u64)> = std::fs::read_dir(d.join(sub))
            .unwrap()
            .filter_map(|e| {
                let p = e.unwrap().path();
                (p.extension()? == "agg").then(|| {
                    let name = p.file_name().unwrap().to_string_lossy().into_owned();
                    (name, std::fs::metadata(&p).unwrap().len())
                })
            })
            .collect();
        v.sort();
        v
    };
    let all = sizes("all");
    assert!(all.len() >= 3, "{all:?}");
    // The budget: between the smallest and the largest candidates' file.
    let (lo, hi) = (
        all.iter().map(|a| a.1).min().unwrap(),
        all.iter().map(|a| a.1).max().unwrap(),
    );
    let budget = 0.5 * (lo + hi) as f64;
    let mib = format!("{}", budget / MIB);
    assemble(
        "budget/forest.json",
        &["--keep", "1", "--energy", "1", "--size-mib", &mib],
    );
    let budgeted = sizes("budget");
    assert_eq!(budgeted.len(), all.len());
    let mut met = 0;
    for ((name, full), (_, got)) in all.iter().zip(&budgeted) {
        let got = *got as f64;
        if (*full as f64) > budget {
            assert!(
                got <= budget && got >= (1.0 - TOLERANCE) * budget,
                "{name}: {got} bytes for a budget of {budget} ({full} with every candidate)"
            );
            met += 1;
        } else {
            // Everything kept: the same file but for the budget recorded in its settings.
            assert!(
                (got - *full as f64).abs() <= 64.0,
                "{name}: under the budget, everything kept: {got} against {full}"
            );
        }
    }
    assert!(met >= 1, "no asset was over the budget: {all:?}");
}
