//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Runs the `aggtool` binary of this build with `args` in `cwd`.
pub fn aggtool(args: &[&str], cwd: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_aggtool"))
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("run aggtool")
}

/// The stdout of a run that must have succeeded (its stderr in the message otherwise).
pub fn ok(o: &Output) -> String {
    assert!(
        o.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// `convert`'s flags for a tiny bake, `max_res`³ down to 4³ with few samples and rays (seconds
/// on any test asset): the one bake setting of the command-line tests.
pub fn tiny_bake_flags(max_res: &str) -> Vec<&str> {
    vec![
        "--max-res",
        max_res,
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
    ]
}

/// The 200-triangle `plane45.glb` and its tiny bake `plane45.agg` (8³ and 4³) in `dir`.
pub fn tiny_plane(dir: &Path) {
    ok(&aggtool(
        &["gen", "plane45", "-o", ".", "--triangles", "200"],
        dir,
    ));
    let mut args = vec!["convert", "plane45.glb", "-q"];
    args.extend(tiny_bake_flags("8"));
    ok(&aggtool(&args, dir));
}

/// What a test that skips for want of `../shared/assets` prints, before its name. `.ci/run`
/// fails when a test's output holds it while the folder is present.
pub const SKIPPED_NO_ASSETS: &str = "SKIPPED (no ../shared/assets)";

/// Says that `test` skipped (all or part of it) because `../shared/assets` is absent: one line
/// on stderr, written past libtest's capture (which hides a passing test's `eprintln!`), so
/// that a skip shows in `cargo test`'s output.
pub fn skipped_no_assets(test: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "{SKIPPED_NO_ASSETS}: {test}");
}

/// `../shared/assets` beside the checkout, or `None` when it is absent, after saying that
/// `test` skipped ([`skipped_no_assets`]): tests that need it skip, they never fail for its
/// absence, and never silently.
pub fn shared_assets(test: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets");
    if p.is_dir() {
        Some(p)
    } else {
        skipped_no_assets(test);
        None
    }
}

/// Asserts that a render is sound: every pixel finite, and no sample dropped as non-finite nor
/// value replaced on the way. The image loop leaves non-finite samples out of their pixels and
/// counts them, so finite pixels alone cannot show a NaN: the counters can.
pub fn assert_clean_render(
    img: &aggtool::film::Image,
    stats: &aggtool::film::ImageStats,
    what: &str,
) {
    assert_eq!(
        (stats.invalid_samples, stats.non_finite),
        (0, 0),
        "{what}: (invalid samples, non-finite values)"
    );
    assert!(
        img.pixels.iter().all(|p| p.is_finite()),
        "{what}: a non-finite pixel"
    );
}

/// Generates a scene into a temporary folder and imports it.
pub fn generated(
    name: &str,
    triangles: usize,
    lambertian: bool,
) -> (tempfile::TempDir, aggtool::scene::Scene) {
    let dir = tempfile::tempdir().unwrap();
    let settings = aggtool::gen::GenSettings {
        triangles,
        lambertian,
        seed: 1,
    };
    let (path, _) = aggtool::gen::write(name, &settings, dir.path(), false).unwrap();
    let scene = aggtool::import::load(&path, Default::default()).unwrap();
    (dir, scene)
}

/// Generated hard case `name` of about `triangles` triangles, in memory (no file).
pub fn gen_scene(name: &str, triangles: usize) -> aggtool::scene::Scene {
    aggtool::gen::generate(
        name,
        &aggtool::gen::GenSettings {
            triangles,
            ..Default::default()
        },
    )
    .unwrap()
    .to_scene()
}

/// Bake settings small enough for a test: `max_res` down to 2, few samples and rays.
pub fn small_bake(max_res: u32) -> aggtool::bake::BakeSettings {
    aggtool::bake::BakeSettings {
        max_res,
        min_res: 2,
        samples: 16,
        max_samples: 256,
        aiv_res: 16,
        aiv_rays: 16,
        abv_res: 16,
        abv_rays: 2,
        ..Default::default()
    }
}

/// Shared walks (`TraceSettings::samples_per_walk`) against a walk a sample, with
/// `render(samples_per_walk, seed)`: 4 samples a walk give the same image mean as 1 (within
/// 1%), differ per pixel by less than twice two one-walk renders with other seeds do, and give
/// the same bits on one thread as on the pool's.
#[allow(dead_code)]
pub fn assert_shared_walks_agree(render: impl Fn(u32, u64) -> aggtool::film::Image + Sync) {
    use aggtool::render::compare::compare;
    let mean = |img: &aggtool::film::Image| {
        img.pixels
            .iter()
            .map(|p| p.element_sum() as f64)
            .sum::<f64>()
            / img.pixels.len() as f64
    };
    let (each, shared, other) = (render(1, 3), render(4, 5), render(1, 11));
    let (me, ms) = (mean(&each), mean(&shared));
    assert!(
        (ms / me - 1.0).abs() < 0.01,
        "image mean {ms} shared, {me} each"
    );
    let noise = compare(&each, &other).unwrap().rmse;
    let d = compare(&each, &shared).unwrap().rmse;
    assert!(d < 2.0 * noise, "shared vs each {d}, noise {noise}");
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| render(4, 5));
    assert!(
        one.pixels
            .iter()
            .zip(&shared.pixels)
            .all(|(a, b)| a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits)),
        "thread count changed the bits"
    );
}
