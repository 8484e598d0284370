//! Files of earlier minor versions, committed under tests/data/, still open, verify and render
//! as they did when they were written (schema/CHANGES.md: a reader of 1.m reads any 1.x file).
//!
//! - `foliage-1.3.agg`: `aggtool gen foliage --triangles 400`, baked by the 1.3 build
//!   (21f8d27) with `aggtool convert foliage.glb --max-res 8 --min-res 2 --samples 8
//!   --max-samples 64 --aiv-res 8 --aiv-rays 4 --abv-res 8 --abv-rays 1`.
//! - `foliage-1.0.agg`, `foliage-1.1.agg`, `foliage-1.2.agg`: the same asset and command,
//!   baked by builds of the last commit writing each version (aa840f1, 8e562ba, bf5b976; each
//!   built in a temporary worktree). Their expected figures were printed by the 1.4 build,
//!   whose float path renders the 1.3 file as the 1.3 build did (the test below) and renders
//!   these three exactly as a 1.3 reader does (`aggtool render` on a 32² view: RMSE 0).
//!
//! - `foliage-1.4.agg`: the same voxels and faces in format 1.4's quantized layout, written
//!   from `foliage-1.3.agg` by `cargo run -p aggtool-tools --bin requantize -- tests/data/foliage-1.3.agg
//!   tests/data/foliage-1.4.agg` (the bytes a quantized bake of those settings writes). Both
//!   files also seed the fuzzer (fuzz/fuzz_targets/read_agg.rs).
//!
//! The expected figures were printed by this test on the 1.3 build (AGGTOOL_PRINT=1 prints
//! them again); the render is deterministic (fixed seed, per-pixel streams).

use std::path::Path;

use aggtool::format::Aggregate;
use aggtool::render::View;
use aggtool::runtime::{LodScene, Shading, TraceSettings};
use aggtool::util::no_progress;
use glam::Vec3;

/// A committed file, opened with full verification.
fn open(name: &str) -> Aggregate {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name);
    Aggregate::open(&p).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// The mean radiance of a 16×16, 4-spp render framing the file's bounds under a constant sky
/// and a sun, and three of its pixels.
fn render(agg: Aggregate) -> (Vec3, [Vec3; 3]) {
    let (lo, hi) = agg.bounds();
    let mut v = View::framing(0.5 * (lo + hi), 0.5 * (hi - lo).length(), 16, 16, 4);
    v.environment = Some(aggtool::render::EnvironmentDesc::Constant {
        constant: aggtool::render::Rgb::Rgb([0.4, 0.5, 0.7]),
    });
    v.sun = Some(aggtool::render::SunDesc {
        direction: [0.3, 1.0, 0.5],
        irradiance: aggtool::render::Rgb::Scalar(2.0),
    });
    let lights = v.lights().unwrap();
    let lod = LodScene::new(agg);
    let (img, stats) = aggtool::runtime::render(
        &lod,
        &v.camera(),
        &lights,
        4,
        1,
        // The shading of the builds that printed the pinned values below (these tests are of
        // the format): without the per-cone normalisation added since, and with the coverage
        // roulette that was on by default then, and the footprint's discrete level.
        &TraceSettings {
            normalize: false,
            continuous_lod: false,
            // Every sample walks its own cone, as the builds that printed the values did.
            samples_per_walk: 1,
            shading: Shading::Reservoir {
                picks: 1,
                roulette: true,
            },
            ..Default::default()
        },
        &no_progress,
    );
    assert_eq!((stats.invalid_samples, stats.non_finite), (0, 0));
    let mean = img.pixels.iter().copied().sum::<Vec3>() / img.pixels.len() as f32;
    let px = |x: usize, y: usize| img.pixels[y * 16 + x];
    (mean, [px(8, 8), px(5, 10), px(10, 4)])
}

/// Relative agreement within 1e-4 (the same code path reads the same floats; the margin is
/// for summation order only).
fn close(a: Vec3, b: [f32; 3]) -> bool {
    let b = Vec3::from_array(b);
    (a - b).abs().max_element() <= 1e-4 * b.abs().max_element().max(1e-3)
}

/// Renders `agg` ([`render`]) and checks its mean and three pixels against the pinned values
/// (AGGTOOL_PRINT=1 prints them, to pin them again on purpose).
fn assert_renders_as(agg: Aggregate, want_mean: [f32; 3], want_px: [[f32; 3]; 3]) {
    let (mean, px) = render(agg);
    if std::env::var_os("AGGTOOL_PRINT").is_some() {
        eprintln!(
            "mean {:?} pixels {:?}",
            mean.to_array(),
            px.map(|p| p.to_array())
        );
    }
    assert!(close(mean, want_mean), "mean {mean}");
    for (p, w) in px.iter().zip(want_px) {
        assert!(close(*p, w), "pixel {p} against {w:?}");
    }
}

#[test]
fn format_1_3_file_still_reads_and_renders_the_same() {
    let agg = open("foliage-1.3.agg");
    assert_eq!((agg.header().major, agg.header().minor), (1, 3));
    assert_eq!(agg.level_count(), 3);
    let counts: Vec<(u64, u64)> = (0..3)
        .map(|l| (agg.counts(l).voxels, agg.counts(l).faces))
        .collect();
    assert_eq!(counts, [(133, 220), (37, 80), (8, 24)]);
    assert!(aggtool::format::exercise(&agg) > 0);
    // Printed by the 1.3 build (21f8d27), again when the image loop's sampler became
    // stratified (the means moved by 0.4% at most, the pixels by the 4 spp's noise), and again
    // when the ABSDF read Eq. 21's S at the narrower lobe width (means +0.06%, pixels +0.4% at
    // most), and when the lobes took their own masses in the weight's E|n·ω| and the ABSDF's
    // mixture (means −0.1%, the third pixel's green −11%); the second pixel sees the sky past
    // the foliage.
    let want_mean = [0.36692527, 0.46882218, 0.638884];
    let want_px = [
        [0.23257966, 0.36944845, 0.3871688],
        [0.4, 0.5, 0.7],
        [0.22649914, 0.3731705, 0.3749212],
    ];
    assert_renders_as(agg, want_mean, want_px);
}

/// The committed 1.0, 1.1 and 1.2 files open, verify and render as they did (the values printed
/// again when the image loop's sampler became stratified, when the ABSDF read Eq. 21's S at
/// the narrower lobe width, and when the lobes took their own masses in the weight's E|n·ω|
/// and the ABSDF's mixture).
#[test]
fn format_1_0_to_1_2_files_still_read_and_render_the_same() {
    // (file, minor, voxels and faces per level, mean, three pixels)
    type Want = (&'static str, u16, [(u64, u64); 3], [f32; 3], [[f32; 3]; 3]);
    let files: [Want; 3] = [
        (
            "foliage-1.0.agg",
            0,
            [(133, 220), (37, 80), (8, 24)],
            [0.3638888, 0.46428075, 0.6340261],
            [
                [0.24630862, 0.42532218, 0.39871374],
                [0.4, 0.5, 0.7],
                [0.20890787, 0.29996324, 0.35633704],
            ],
        ),
        (
            "foliage-1.1.agg",
            1,
            [(133, 220), (37, 80), (8, 24)],
            [0.3644614, 0.465451, 0.63451964],
            [
                [0.25185832, 0.4482221, 0.40321606],
                [0.4, 0.5, 0.7],
                [0.20893082, 0.30005965, 0.356364],
            ],
        ),
        (
            "foliage-1.2.agg",
            2,
            [(133, 220), (37, 80), (8, 24)],
            [0.36457744, 0.4652735, 0.6344923],
            [
                [0.246137, 0.4242519, 0.39772072],
                [0.4, 0.5, 0.7],
                [0.19762078, 0.2664382, 0.34205383],
            ],
        ),
    ];
    let print = std::env::var_os("AGGTOOL_PRINT").is_some();
    for (name, minor, counts, want_mean, want_px) in files {
        let agg = open(name);
        assert_eq!(
            (agg.header().major, agg.header().minor),
            (1, minor),
            "{name}"
        );
        let got: Vec<(u64, u64)> = (0..agg.level_count())
            .map(|l| (agg.counts(l).voxels, agg.counts(l).faces))
            .collect();
        assert!(aggtool::format::exercise(&agg) > 0);
        let (mean, px) = render(agg);
        if print {
            eprintln!(
                "{name}: counts {got:?} mean {:?} pixels {:?}",
                mean.to_array(),
                px.map(|p| p.to_array())
            );
            continue;
        }
        assert_eq!(got, counts, "{name}");
        assert!(close(mean, want_mean), "{name}: mean {mean}");
        for (p, w) in px.iter().zip(want_px) {
            assert!(close(*p, w), "{name}: pixel {p} against {w:?}");
        }
    }
}

/// The committed 1.4 file opens and verifies, is quantized at every level, and renders as the
/// float file does within what quantization moves a render: the mean within 0.5%, the pixels
/// within 2% (visibility values move by 0.006 at most in this file, binary16 moments by 2^-11).
#[test]
fn format_1_4_quantized_file_renders_as_the_float_one() {
    let agg = open("foliage-1.4.agg");
    assert_eq!((agg.header().major, agg.header().minor), (1, 4));
    assert!(!agg.settings().lossless);
    for l in 0..agg.level_count() {
        assert!(agg.component_bytes(l).1, "level {l} is not quantized");
    }
    assert!(aggtool::format::exercise(&agg) > 0);
    let (mean, px) = render(agg);
    let (float_mean, float_px) = render(open("foliage-1.3.agg"));
    if std::env::var_os("AGGTOOL_PRINT").is_some() {
        eprintln!(
            "1.4 mean {:?} pixels {:?}",
            mean.to_array(),
            px.map(|p| p.to_array())
        );
    }
    let rel = |a: Vec3, b: Vec3| (a - b).abs().max_element() / b.max_element().max(1e-3);
    assert!(
        rel(mean, float_mean) <= 0.005,
        "mean {mean} vs {float_mean}"
    );
    for (p, f) in px.iter().zip(float_px) {
        assert!(rel(*p, f) <= 0.02, "pixel {p} vs {f}");
    }
}

/// The committed 1.8 file (`foliage-1.8.agg`: `cargo run -p aggtool-tools --bin requantize --
/// tests/data/foliage-1.3.agg tests/data/foliage-1.8.agg`, its blocks in byte planes with the
/// derived fields left out) holds exactly what the 1.6 file holds, inflated to the same
/// FlatBuffers, in fewer bytes, and renders exactly as it does.
#[test]
fn format_1_8_derived_file_renders_as_the_1_6_one() {
    let d = open("foliage-1.8.agg");
    let p = open("foliage-1.6.agg");
    assert_eq!((d.header().major, d.header().minor), (1, 8));
    assert!(d.bytes().len() < p.bytes().len());
    for l in 0..d.level_count() {
        assert_eq!(d.read_level(l), p.read_level(l), "level {l}");
        assert_eq!(
            d.stored_and_inflated_bytes(l).1,
            p.stored_and_inflated_bytes(l).1,
            "level {l}: the same FlatBuffers inflated"
        );
    }
    assert!(aggtool::format::exercise(&d) > 0);
    let (mean, px) = render(d);
    let (mean6, px6) = render(p);
    assert_eq!(mean, mean6);
    assert_eq!(px, px6);
}

/// The committed 1.7 file (`foliage-1.7.agg`: `aggtool gen foliage --triangles 400`, baked by
/// the build that added visibility levels with the 1.3 file's command and `--visibility-levels 1`):
/// its 8³ level holds no AIV trees and no directional moments, its voxels read the AIV of the
/// 4³ voxels that contain them, and it renders as it did when it was written (values printed
/// by that build, and again when the lobes took their own masses: the weight's E|n·ω| and the
/// ABSDF's mixture, mean −0.5% at most).
#[test]
fn format_1_7_visibility_level_file_reads_and_renders_the_same() {
    let agg = open("foliage-1.7.agg");
    assert_eq!((agg.header().major, agg.header().minor), (1, 7));
    assert_eq!(agg.settings().shading_res, 4);
    assert_eq!(
        (0..3).map(|l| agg.shading_level(l)).collect::<Vec<_>>(),
        [1, 1, 2]
    );
    let c = agg.counts(0);
    assert_eq!((c.voxels, c.faces), (133, 220));
    assert_eq!((c.aiv_trees, c.directional_moments), (0, 0));
    assert!(aggtool::format::exercise(&agg) > 0);
    assert_renders_as(
        agg,
        [0.35564217, 0.45440573, 0.61875206],
        [
            [0.21258226, 0.38188633, 0.343128],
            [0.4, 0.5, 0.7],
            [0.15289976, 0.22047704, 0.26157188],
        ],
    );
}

/// The committed 1.6 file (`foliage-1.6.agg`: `cargo run -p aggtool-tools --bin requantize --
/// tests/data/foliage-1.3.agg tests/data/foliage-1.6.agg`, its blocks compressed in byte planes)
/// opens, verifies, holds exactly what the 1.5 file holds in fewer bytes, and renders exactly
/// as it does: byte planes are lossless.
#[test]
fn format_1_6_planar_file_renders_as_the_1_5_one() {
    let p = open("foliage-1.6.agg");
    let z = open("foliage-1.5.agg");
    assert_eq!((p.header().major, p.header().minor), (1, 6));
    assert!(p.bytes().len() < z.bytes().len());
    for l in 0..p.level_count() {
        assert_eq!(p.read_level(l), z.read_level(l), "level {l}");
        assert_eq!(
            p.stored_and_inflated_bytes(l).1,
            z.stored_and_inflated_bytes(l).1,
            "level {l}: the same FlatBuffers inflated"
        );
    }
    assert!(aggtool::format::exercise(&p) > 0);
    let (mean, px) = render(p);
    let (mean5, px5) = render(z);
    assert_eq!(mean, mean5);
    assert_eq!(px, px5);
}

/// The committed 1.5 file (`foliage-1.5.agg`: `cargo run -p aggtool-tools --bin requantize --
/// tests/data/foliage-1.3.agg tests/data/foliage-1.5.agg`, the quantized layout with its blocks
/// compressed at the default level) opens, verifies, holds exactly what the 1.4 file holds, and
/// renders exactly as it does: compression is lossless.
#[test]
fn format_1_5_compressed_file_renders_as_the_1_4_one() {
    let z = open("foliage-1.5.agg");
    let q = open("foliage-1.4.agg");
    assert_eq!((z.header().major, z.header().minor), (1, 5));
    assert_eq!(
        z.settings().compression,
        aggtool::format::DEFAULT_COMPRESSION
    );
    assert!(z.bytes().len() < q.bytes().len());
    for l in 0..z.level_count() {
        assert_eq!(z.read_level(l), q.read_level(l), "level {l}");
        let (stored, inflated) = z.stored_and_inflated_bytes(l);
        assert!(stored < inflated, "level {l}: {stored} of {inflated} bytes");
    }
    assert!(aggtool::format::exercise(&z) > 0);
    let (mean, px) = render(z);
    let (mean4, px4) = render(q);
    assert_eq!(mean, mean4);
    assert_eq!(px, px4);
}
