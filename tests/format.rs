//! The bake and the `.agg` format: golden statistics, round trip, rejection of bad files,
//! determinism, and effect detection (what is dropped changes nothing measurable).

mod common;

use std::path::Path;

use aggtool::absdf::Absdf;
use aggtool::bake::level::bake_level;
use aggtool::bake::{bake_to_file, BakeSettings};
use aggtool::bsdf::Bsdf;
use aggtool::format::{Aggregate, FormatError, Header, HEADER_SIZE, MAJOR, MINOR};
use aggtool::gen::{generate, GenSettings};
use aggtool::scene::Scene;
use aggtool::spatial::Grid;
use aggtool::trace::Accel;
use glam::Vec3;

/// Small settings for test bakes (seconds, not minutes).
fn small() -> BakeSettings {
    BakeSettings {
        max_res: 8,
        min_res: 2,
        samples: 8,
        max_samples: 64,
        aiv_res: 8,
        aiv_rays: 4,
        abv_res: 8,
        abv_rays: 1,
        // Each map truncated on its own, as `bake_level` bakes a level in memory, so that
        // files compare with it (the block allocation has its test in tests/rate.rs).
        block_allocation: false,
        ..Default::default()
    }
}

fn scene(name: &str, triangles: usize, lambertian: bool) -> Scene {
    generate(
        name,
        &GenSettings {
            triangles,
            lambertian,
            seed: 1,
        },
    )
    .unwrap()
    .to_scene()
}

fn bake(
    scene: &Scene,
    s: &BakeSettings,
    dir: &Path,
    name: &str,
) -> (Vec<u8>, aggtool::bake::BakeReport) {
    let path = dir.join(name);
    let r = bake_to_file(scene, "test.glb", s, &path, &aggtool::util::no_progress).unwrap();
    (std::fs::read(&path).unwrap(), r)
}

/// The bytes of `scene` baked with `s` on a pool of `threads` threads.
fn bake_on_threads(
    scene: &Scene,
    s: &BakeSettings,
    dir: &Path,
    name: &str,
    threads: usize,
) -> Vec<u8> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(|| bake(scene, s, dir, name).0)
}

/// Rewrites the header of `bytes` with another version (checksum fixed up).
fn with_version(bytes: &[u8], major: u16, minor: u16) -> Vec<u8> {
    let mut h = Header::parse(bytes).unwrap();
    h.major = major;
    h.minor = minor;
    let mut out = bytes.to_vec();
    out[..HEADER_SIZE].copy_from_slice(&h.to_bytes());
    out
}

/// Every truncated prefix, trailing bytes, a wrong identifier, an unknown major version and a
/// flipped bit anywhere are refused; a newer minor version is read.
fn check_rejection(bytes: &[u8], agg: &Aggregate) {
    // Every truncated prefix fails cleanly.
    for n in 0..bytes.len() {
        match Aggregate::from_bytes(bytes[..n].to_vec()) {
            Err(FormatError::Truncated { .. }) => {}
            Err(e) => panic!("prefix {n}: unexpected error {e}"),
            Ok(_) => panic!("prefix {n} accepted"),
        }
    }
    // Trailing bytes.
    let mut t = bytes.to_vec();
    t.extend_from_slice(b"xx");
    assert!(matches!(
        Aggregate::from_bytes(t),
        Err(FormatError::Trailing { extra: 2, .. })
    ));
    // Wrong identifier.
    let mut w = bytes.to_vec();
    w[1] = b'X';
    assert!(matches!(
        Aggregate::from_bytes(w),
        Err(FormatError::NotAggregate)
    ));
    assert!(matches!(
        Aggregate::from_bytes(b"glTF....".to_vec()),
        Err(FormatError::NotAggregate)
    ));
    // An unknown major version is refused; a newer minor version is read.
    let e = Aggregate::from_bytes(with_version(bytes, MAJOR + 1, 0))
        .err()
        .unwrap();
    assert!(matches!(e, FormatError::UnsupportedMajor { found } if found == MAJOR + 1));
    assert!(e.to_string().contains("not supported"));
    let newer = Aggregate::from_bytes(with_version(bytes, MAJOR, MINOR + 3)).unwrap();
    assert_eq!(newer.header().minor, MINOR + 3);
    assert_eq!(newer.read_level(0), agg.read_level(0));
    // A flipped bit anywhere after the header is caught (checksums), and so is one in the
    // header; stepping through the file in strides keeps this quick.
    let step = (bytes.len() / 997).max(1);
    for i in (0..bytes.len()).step_by(step) {
        let mut c = bytes.to_vec();
        c[i] ^= 0x10;
        assert!(Aggregate::from_bytes(c).is_err(), "flip at {i} accepted");
    }
}

/// The largest error quantization may add to a visibility value of an `n`² map: half a step
/// of 1/254 per detail, three details per level (math::haar::QNode), plus f32 rounding.
fn tree_tolerance(n: u32) -> f32 {
    3.0 * n.trailing_zeros() as f32 / (2.0 * aggtool::math::haar::Q_DETAIL) + 1e-6
}

/// A quantized level read back against the float level baked in memory: records, keys,
/// ellipsoids, exposures and faces exact; every AIV and ABV cell within [`tree_tolerance`];
/// lobes' SGGX matrices within 1e-3 of their largest entry, α and moments within binary16's
/// relative 2^-11, weights within 1e-5.
fn assert_quantized_close(read: &aggtool::format::LevelData, mem: &aggtool::format::LevelData) {
    assert_eq!(read.grid, mem.grid);
    assert_eq!(read.voxels.len(), mem.voxels.len());
    assert_eq!(read.faces.len(), mem.faces.len());
    let close = |a: f32, b: f32, rel: f32| (a - b).abs() <= rel * a.abs().max(b.abs()) + 6e-8;
    let trees = |a: &aggtool::math::haar::SparseHaar, b: &aggtool::math::haar::SparseHaar| {
        assert_eq!(
            (a.n, a.scaling, a.nodes.len()),
            (b.n, b.scaling, b.nodes.len())
        );
        let tol = tree_tolerance(a.n);
        for y in 0..a.n {
            for x in 0..a.n {
                let (u, v) = (a.eval(x, y), b.eval(x, y));
                assert!(
                    u.is_finite() && (u - v).abs() <= tol,
                    "({x}, {y}): {u} vs {v}"
                );
            }
        }
    };
    for (a, b) in read.voxels.iter().zip(&mem.voxels) {
        assert_eq!(
            (a.key, a.area, a.coverage, a.ellipsoid, a.exposure),
            (b.key, b.area, b.coverage, b.ellipsoid, b.exposure)
        );
        let (pa, pb) = (&a.appearance, &b.appearance);
        assert_eq!(
            (pa.roughness_mean, pa.roughness_variance, pa.lobes.len()),
            (pb.roughness_mean, pb.roughness_variance, pb.lobes.len())
        );
        for (la, lb) in pa.lobes.iter().zip(&pb.lobes) {
            assert!((la.weight - lb.weight).abs() <= 1e-5);
            assert!(close(la.alpha.x, lb.alpha.x, 4.9e-4) && close(la.alpha.y, lb.alpha.y, 4.9e-4));
            let (sa, sb) = (
                aggtool::math::sggx::Sggx::from_frame_roughness(la.frame, la.alpha),
                aggtool::math::sggx::Sggx::from_frame_roughness(lb.frame, lb.alpha),
            );
            let big = sb.xx.max(sb.yy).max(sb.zz);
            for (u, v) in [
                (sa.xx, sb.xx),
                (sa.yy, sb.yy),
                (sa.zz, sb.zz),
                (sa.xy, sb.xy),
                (sa.xz, sb.xz),
                (sa.yz, sb.yz),
            ] {
                assert!((u - v).abs() <= 1e-3 * big, "SGGX {u} vs {v}");
            }
        }
        let sets = |m: &aggtool::absdf::Moments| -> Vec<aggtool::absdf::MaterialMoments> {
            match m {
                aggtool::absdf::Moments::Constant(c) => vec![*c],
                aggtool::absdf::Moments::Directional {
                    diffuse, specular, ..
                } => diffuse.iter().chain(specular).copied().collect(),
            }
        };
        let (ma, mb) = (sets(&pa.moments), sets(&pb.moments));
        assert_eq!(ma.len(), mb.len());
        for (x, y) in ma.iter().zip(&mb) {
            let (u, v) = (
                [
                    x.c.to_array(),
                    x.mc.to_array(),
                    [x.s, x.ms, x.m],
                    [x.f90, x.mf90, 0.0],
                ],
                [
                    y.c.to_array(),
                    y.mc.to_array(),
                    [y.s, y.ms, y.m],
                    [y.f90, y.mf90, 0.0],
                ],
            );
            for (p, q) in u.iter().flatten().zip(v.iter().flatten()) {
                assert!(close(*p, *q, 4.9e-4), "moment {p} vs {q}");
            }
        }
        trees(&a.aiv, &b.aiv);
    }
    for (a, b) in read.faces.iter().zip(&mem.faces) {
        assert_eq!(a.face, b.face);
        trees(&a.abv, &b.abv);
    }
}

#[test]
fn round_trip_and_rejection() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene("foliage", 400, false);
    // The float layout reads back exactly; the quantized one within its tolerances.
    let s = BakeSettings {
        lossless: true,
        compression: 0,
        ..small()
    };
    let (bytes, report) = bake(&sc, &s, dir.path(), "a.agg");
    assert_eq!(report.bytes as usize, bytes.len());
    let agg = Aggregate::open(&dir.path().join("a.agg")).unwrap();
    assert_eq!(agg.level_count(), 3);
    // The finest level read back equals the level baked in memory (areas pass through f32).
    let accel = Accel::build(&sc);
    let (lo, hi) = sc.bounds();
    let mut mem = bake_level(&sc, &accel, Grid::around(lo, hi, 8), &s.level(8));
    let read = agg.read_level(0);
    mem.voxels
        .iter_mut()
        .for_each(|v| v.area = v.area as f32 as f64);
    mem.rays = 0;
    assert_eq!(read.grid, mem.grid);
    assert_eq!(read.faces, mem.faces);
    assert_eq!(read.voxels.len(), mem.voxels.len());
    for (a, b) in read.voxels.iter().zip(&mem.voxels) {
        assert_eq!(a, b);
    }
    // Zero-copy lookups agree with the decoded trees.
    for v in &mem.voxels {
        let r = agg.find_voxel(0, v.key).expect("voxel found by key");
        for d in [Vec3::X, Vec3::NEG_Y, Vec3::new(0.3, 0.5, -0.8).normalize()] {
            let cell = aggtool::math::sphere_maps::grid_cell(
                aggtool::math::sphere_maps::equal_area_sphere_to_square(d),
                s.aiv_res,
            );
            let want = v
                .aiv
                .eval(cell % s.aiv_res, cell / s.aiv_res)
                .clamp(0.0, 1.0);
            assert!((r.aiv(d) - want).abs() < 1e-6);
        }
    }
    assert!(agg.find_voxel(0, u64::MAX >> 2).is_none());
    assert!(agg.settings().lossless && !agg.component_bytes(0).1);
    check_rejection(&bytes, &agg);

    // Format 1.4's quantized layout, blocks uncompressed: within its tolerances at every
    // level, smaller, and refused by the rejection checks alike.
    let uncompressed = BakeSettings {
        compression: 0,
        ..small()
    };
    let (qbytes, _) = bake(&sc, &uncompressed, dir.path(), "q.agg");
    let q = Aggregate::from_bytes(qbytes.clone()).unwrap();
    assert_eq!(q.header().minor, MINOR);
    assert_eq!(q.settings().compression, 0);
    assert!(!q.settings().lossless);
    for l in 0..q.level_count() {
        assert!(q.component_bytes(l).1, "level {l} not quantized");
        assert_quantized_close(&q.read_level(l), &agg.read_level(l));
        // The zero-copy look-ups agree with the decoded quantized trees.
        let lv = q.read_level(l);
        for (v, r) in lv.voxels.iter().zip(q.voxels(l)) {
            for d in [Vec3::X, Vec3::NEG_Y, Vec3::new(0.3, 0.5, -0.8).normalize()] {
                let cell = aggtool::math::sphere_maps::grid_cell(
                    aggtool::math::sphere_maps::equal_area_sphere_to_square(d),
                    s.aiv_res,
                );
                let want = v
                    .aiv
                    .eval(cell % s.aiv_res, cell / s.aiv_res)
                    .clamp(0.0, 1.0);
                assert!((r.aiv(d) - want).abs() < 1e-6);
            }
        }
    }
    assert!(
        qbytes.len() * 10 < bytes.len() * 7,
        "{} vs {}",
        qbytes.len(),
        bytes.len()
    );
    check_rejection(&qbytes, &q);
    // A file claiming an older minor version may not hold quantized arrays.
    let e = Aggregate::from_bytes(with_version(&qbytes, MAJOR, 3))
        .err()
        .expect("1.3 with quantized arrays refused");
    assert!(e.to_string().contains("older than 1.4"), "{e}");

    // Format 1.5's compressed blocks (the default): the same content as the uncompressed
    // file, fewer bytes, every block compressed, refused by the rejection checks alike, and
    // refused in a file that claims 1.4.
    let (zbytes, _) = bake(&sc, &small(), dir.path(), "z.agg");
    let z = Aggregate::from_bytes(zbytes.clone()).unwrap();
    assert_eq!(
        z.settings().compression,
        aggtool::format::DEFAULT_COMPRESSION
    );
    assert!(
        zbytes.len() < qbytes.len(),
        "{} vs {}",
        zbytes.len(),
        qbytes.len()
    );
    for l in 0..z.level_count() {
        assert_eq!(z.read_level(l), q.read_level(l), "level {l}");
        assert_eq!(z.component_bytes(l), q.component_bytes(l), "level {l}");
        let (stored, inflated) = z.stored_and_inflated_bytes(l);
        let (plain, same) = q.stored_and_inflated_bytes(l);
        assert_eq!((inflated, plain), (same, same), "level {l}");
        assert!(stored < inflated, "level {l}: {stored} of {inflated} bytes");
    }
    check_rejection(&zbytes, &z);
    let e = Aggregate::from_bytes(with_version(&zbytes, MAJOR, 4))
        .err()
        .expect("1.4 with compressed blocks refused");
    assert!(e.to_string().contains("older than 1.5"), "{e}");
    // From 1.8 the compressed blocks are in byte planes with derived fields left out, which
    // no older file can hold.
    for minor in [5, 7] {
        let e = Aggregate::from_bytes(with_version(&zbytes, MAJOR, minor))
            .err()
            .expect("1.5 and 1.7 with derived planar blocks refused");
        assert!(e.to_string().contains("older than 1.8"), "{e}");
    }
    // The 1.6 file's blocks are in byte planes, which a 1.5 file cannot hold.
    let p = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/foliage-1.6.agg"))
        .unwrap();
    let e = Aggregate::from_bytes(with_version(&p, MAJOR, 5))
        .err()
        .expect("1.5 with planar blocks refused");
    assert!(e.to_string().contains("older than 1.6"), "{e}");
}

#[test]
fn bytes_are_deterministic_across_runs_and_threads() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene("displaced-sphere", 600, false);
    let s = small();
    let run = |threads: usize, name: &str| bake_on_threads(&sc, &s, dir.path(), name, threads);
    let a = run(1, "a.agg");
    let b = run(2, "b.agg");
    let c = run(2, "c.agg");
    assert!(a == b, "1 and 2 threads differ");
    assert!(b == c, "two runs differ");
}

/// Evaluates every voxel's ABSDF and AIV of level `l` in a few direction pairs.
fn evaluations(agg: &Aggregate, l: usize) -> Vec<f32> {
    let t = aggtool::tables::Tables::embedded();
    let dirs = [
        Vec3::Z,
        Vec3::new(0.6, 0.0, 0.8),
        Vec3::new(-0.3, 0.9, 0.3).normalize(),
        Vec3::new(0.1, -0.2, -0.97).normalize(),
    ];
    let mut out = Vec::new();
    for v in agg.voxels(l) {
        let app = v.appearance();
        let a = Absdf::new(&app, t);
        for wi in dirs {
            out.push(v.aiv(wi));
            for wo in dirs {
                out.extend(a.eval(wi, wo).to_array());
            }
        }
    }
    out
}

/// Effect detection stores less and renders the same: a Lambertian scene of uniform
/// materials drops directional and metallic moments; the ABSDF and visibility of every voxel
/// are unchanged against a bake that keeps every effect.
#[test]
fn dropped_effects_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene("plane45", 300, true);
    let s = small();
    let (lean, r1) = bake(&sc, &s, dir.path(), "lean.agg");
    let (full, _) = bake(
        &sc,
        &BakeSettings {
            keep_all_effects: true,
            ..s.clone()
        },
        dir.path(),
        "full.agg",
    );
    assert!(lean.len() < full.len(), "{} vs {}", lean.len(), full.len());
    let dropped: Vec<&str> = r1
        .effects
        .iter()
        .filter(|e| !e.kept)
        .map(|e| e.name)
        .collect();
    assert!(
        dropped.iter().any(|n| n.contains("metallic")),
        "{dropped:?}"
    );
    assert!(
        dropped.iter().any(|n| n.contains("directional")),
        "{dropped:?}"
    );
    let (a, b) = (
        Aggregate::from_bytes(lean).unwrap(),
        Aggregate::from_bytes(full).unwrap(),
    );
    for l in 0..a.level_count() {
        let (x, y) = (evaluations(&a, l), evaluations(&b, l));
        assert_eq!(x.len(), y.len());
        assert!(!x.is_empty());
        let scale = y.iter().fold(0f32, |m, v| m.max(v.abs()));
        for (p, q) in x.iter().zip(&y) {
            assert!(p.is_finite() && q.is_finite());
            assert!((p - q).abs() <= 1e-4 * scale, "level {l}: {p} vs {q}");
        }
    }
    // A scene with metal keeps the metallic moments.
    let metal = scene("rings", 600, false);
    let (_, r2) = bake(&metal, &s, dir.path(), "metal.agg");
    let m = r2
        .effects
        .iter()
        .find(|e| e.name.contains("metallic"))
        .unwrap();
    assert!(m.kept, "{m:?}");
}

/// The runtime builds a voxel's ABSDF reading its directional moments in place from the
/// quantized block (`VoxelRef::absdf`): the same function, bit for bit, as the ABSDF
/// of the decoded appearance, for metal and dielectric sets, every direction pair tried
/// (ω_i = −ω_o among them, where the ABSDF reads the moments' means), its density and its
/// samples; and it holds no copy of the moments.
#[test]
fn moments_read_in_place_are_the_decoded_ones() {
    let dir = tempfile::tempdir().unwrap();
    let t = aggtool::tables::Tables::embedded();
    let dirs = [
        Vec3::Z,
        -Vec3::Z,
        Vec3::new(0.6, 0.0, 0.8),
        Vec3::new(-0.3, 0.9, 0.3).normalize(),
        Vec3::new(0.1, -0.2, -0.97).normalize(),
        Vec3::new(0.99, 0.1, 0.0).normalize(),
    ];
    let (mut metal, mut dielectric) = (0, 0);
    // Every effect kept: metal sets; the effects the scene needs: dielectric ones.
    for (name, keep_all_effects) in [("rings", true), ("buildings", false)] {
        let s = BakeSettings {
            keep_all_effects,
            ..small()
        };
        let (bytes, _) = bake(&scene(name, 600, false), &s, dir.path(), "m.agg");
        let agg = Aggregate::from_bytes(bytes).unwrap();
        for l in 0..agg.level_count() {
            for v in agg.voxels(l) {
                let Some(h) = v.moment_halves() else {
                    continue;
                };
                assert!(h.is_valid());
                if h.metal {
                    metal += 1;
                } else {
                    dielectric += 1;
                }
                let (a, b) = (Absdf::new(&v.appearance(), t), v.absdf(t));
                assert!(b.memory_bytes() < a.memory_bytes());
                for wi in dirs {
                    for wo in dirs {
                        let (x, y) = (a.eval(wi, wo), b.eval(wi, wo));
                        assert_eq!(
                            x.to_array().map(f32::to_bits),
                            y.to_array().map(f32::to_bits)
                        );
                        assert_eq!(a.pdf(wi, wo).to_bits(), b.pdf(wi, wo).to_bits());
                        let u = glam::Vec2::new(0.3, 0.7);
                        let (p, q) = (a.sample(wo, 0.2, u), b.sample(wo, 0.2, u));
                        assert_eq!(format!("{p:?}"), format!("{q:?}"));
                    }
                }
            }
        }
    }
    assert!(
        metal > 0 && dielectric > 0,
        "{metal} metal, {dielectric} dielectric"
    );
}

/// Committed statistics of a small bake: a change of these numbers is a change of the bake,
/// to be made on purpose (regenerate with AGGTOOL_BLESS=1 and say why in the commit).
#[test]
fn golden_bake() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene("lattice", 500, false);
    let (bytes, _) = bake(&sc, &small(), dir.path(), "g.agg");
    let agg = Aggregate::from_bytes(bytes).unwrap();
    let mut got = Vec::new();
    for l in 0..agg.level_count() {
        let lv = agg.read_level(l);
        let n = lv.voxels.len() as f64;
        let area: f64 = lv.voxels.iter().map(|v| v.area).sum();
        let cov = lv.voxels.iter().map(|v| v.coverage as f64).sum::<f64>() / n;
        let rough = lv
            .voxels
            .iter()
            .map(|v| v.appearance.roughness_mean as f64)
            .sum::<f64>()
            / n;
        let lobes = lv
            .voxels
            .iter()
            .map(|v| v.appearance.lobes.len())
            .sum::<usize>();
        let aiv = lv
            .voxels
            .iter()
            .map(|v| (v.aiv.scaling / v.aiv.n as f32) as f64)
            .sum::<f64>()
            / n;
        let abv = lv
            .faces
            .iter()
            .map(|f| (f.abv.scaling / f.abv.n as f32) as f64)
            .sum::<f64>()
            / lv.faces.len().max(1) as f64;
        got.push(serde_json::json!({
            "res": lv.grid.res,
            "voxels": lv.voxels.len(),
            "faces": lv.faces.len(),
            "area": area,
            "coverage": cov,
            "roughness": rough,
            "lobes": lobes,
            "aiv_mean": aiv,
            "abv_mean": abv,
        }));
    }
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/lattice-8.json");
    if std::env::var_os("AGGTOOL_BLESS").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, serde_json::to_string_pretty(&got).unwrap()).unwrap();
    }
    let want: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    assert_eq!(want.len(), got.len());
    for (w, g) in want.iter().zip(&got) {
        for key in ["res", "voxels", "faces", "lobes"] {
            assert_eq!(w[key], g[key], "{key} at level {}", w["res"]);
        }
        for key in ["area", "coverage", "roughness", "aiv_mean", "abv_mean"] {
            let (a, b) = (w[key].as_f64().unwrap(), g[key].as_f64().unwrap());
            assert!(
                (a - b).abs() <= 1e-4 * a.abs().max(1e-3),
                "{key} at level {}: {a} vs {b}",
                w["res"]
            );
        }
    }
}

/// A failed or abandoned write leaves the previous file untouched and no temporary behind.
#[test]
fn writer_is_atomic() {
    let dir = tempfile::tempdir().unwrap();
    let dest = dir.path().join("x.agg");
    std::fs::write(&dest, b"previous").unwrap();
    {
        let mut w = aggtool::format::Writer::create(&dest).unwrap();
        w.write_blob(&[1, 2, 3], 0, 0, 0).unwrap();
        // Dropped without finish.
    }
    assert_eq!(std::fs::read(&dest).unwrap(), b"previous");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    // Bad settings fail before anything is written.
    let sc = scene("plane45", 50, true);
    let bad = BakeSettings {
        max_res: 12,
        ..small()
    };
    let e = bake_to_file(&sc, "s", &bad, &dest, &aggtool::util::no_progress)
        .err()
        .unwrap();
    assert!(e.to_string().contains("--max-res"), "{e}");
    assert_eq!(std::fs::read(&dest).unwrap(), b"previous");
}

/// Random damage with the checksums switched off (so it reaches the structural checks): every
/// file is refused cleanly or reads without a panic, the property the fuzz target
/// (fuzz/fuzz_targets/read_agg.rs) explores at length.
#[test]
fn damaged_files_never_panic() {
    let dir = tempfile::tempdir().unwrap();
    let (bytes, _) = bake(&scene("foliage", 300, false), &small(), dir.path(), "f.agg");
    // The default bake (quantized, blocks compressed), then the committed files of each layout
    // (1.3 floats, 1.4 quantized, 1.5 compressed, 1.6 in byte planes, 1.7 a visibility level,
    // 1.8 derived fields left out).
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let files = [
        (bytes, 3000),
        (std::fs::read(data.join("foliage-1.3.agg")).unwrap(), 1000),
        (std::fs::read(data.join("foliage-1.4.agg")).unwrap(), 1000),
        (std::fs::read(data.join("foliage-1.5.agg")).unwrap(), 1000),
        (std::fs::read(data.join("foliage-1.6.agg")).unwrap(), 1000),
        (std::fs::read(data.join("foliage-1.7.agg")).unwrap(), 1000),
        (std::fs::read(data.join("foliage-1.8.agg")).unwrap(), 1000),
    ];
    for (bytes, runs) in files {
        damage(&bytes, runs);
    }
}

/// `runs` copies of `bytes` with one to four random bytes damaged, read without checksums.
fn damage(bytes: &[u8], runs: usize) {
    let good = Aggregate::from_bytes(bytes.to_vec()).unwrap();
    assert!(aggtool::format::exercise(&good) > 0);
    let mut rng = aggtool::math::rng::Pcg32::new(7, 1);
    let (mut refused, mut read, mut lazy_read) = (0, 0, 0u32);
    for _ in 0..runs {
        let mut b = bytes.to_vec();
        for _ in 0..1 + rng.next_u32() % 4 {
            let i = HEADER_SIZE + (rng.next_u32() as usize % (b.len() - HEADER_SIZE));
            b[i] = match rng.next_u32() % 3 {
                0 => b[i] ^ (1 << (rng.next_u32() % 8)),
                1 => 0xff,
                _ => rng.next_u32() as u8,
            };
        }
        // Read lazily (tree shapes not walked), the damage reaches the tree look-ups, which
        // must stay in bounds; a non-finite coefficient is counted there, not asserted on.
        if let Ok(a) = Aggregate::from_bytes_lazy_ignoring_checksums(b.clone()) {
            let (n, _) = aggtool::math::numerics::counting(|| aggtool::format::exercise(&a));
            lazy_read += (n > 0) as u32;
        }
        match Aggregate::from_bytes_ignoring_checksums(b) {
            Ok(a) => {
                aggtool::format::exercise(&a);
                read += 1;
            }
            Err(_) => refused += 1,
        }
    }
    assert!(
        lazy_read >= read,
        "lazy reads {lazy_read}, full reads {read}"
    );
    // Both outcomes happen (damage to a float is often harmless; to an offset, fatal).
    assert!(refused > 0 && read > 0, "refused {refused}, read {read}");
}

/// Inputs the fuzzer (fuzz/fuzz_targets/read_agg.rs) once made the reader panic on, kept in
/// tests/fuzz-regressions/: each must be refused or read, never panic.
/// - `read_agg-short-block.bin`: a block reference of fewer than 8 bytes (flatbuffers'
///   identifier check asserts on such a buffer).
#[test]
fn fuzz_regressions_never_panic() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-regressions");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let bytes = std::fs::read(entry.unwrap().path()).unwrap();
        assert!(Aggregate::from_bytes(bytes.clone()).is_err());
        if let Ok(a) = Aggregate::from_bytes_ignoring_checksums(bytes) {
            aggtool::format::exercise(&a);
        }
        n += 1;
    }
    assert!(n >= 1);
}

/// Hard cases of quantization, each baked in both layouts and compared within the stated
/// tolerances ([`assert_quantized_close`]): single-sample voxels (one surface sample each: one
/// lobe at its narrowest), flat voxels and rank-deficient lobes (the 45° plane: one normal per
/// voxel, α at its floor across it), all-visible and all-occluded maps beside trees (the
/// buildings' closed walls and open roofs), and foliage's cut-outs. Every zero-copy visibility
/// is finite and in [0, 1] and every decoded lobe is a unit frame with α in (0, 1].
#[test]
fn hard_cases_round_trip_quantized() {
    let dir = tempfile::tempdir().unwrap();
    let single = BakeSettings {
        samples: 1,
        max_samples: 1,
        ..small()
    };
    let cases = [
        ("plane45", 50, single.clone()),
        ("plane45", 50, small()),
        ("buildings", 600, single),
        ("buildings", 600, small()),
        ("foliage", 300, small()),
    ];
    let mut seen = aggtool::format::encode::Counts::default();
    for (i, (name, tris, s)) in cases.into_iter().enumerate() {
        let sc = scene(name, tris, false);
        let lossless = BakeSettings {
            lossless: true,
            ..s.clone()
        };
        let (fb, _) = bake(&sc, &lossless, dir.path(), &format!("f{i}.agg"));
        let (qb, _) = bake(&sc, &s, dir.path(), &format!("q{i}.agg"));
        let (f, q) = (
            Aggregate::from_bytes(fb).unwrap(),
            Aggregate::from_bytes(qb).unwrap(),
        );
        let dirs = [
            Vec3::X,
            Vec3::NEG_Z,
            Vec3::new(0.3, -0.5, 0.8).normalize(),
            Vec3::new(-0.7, 0.7, 0.1).normalize(),
        ];
        for l in 0..q.level_count() {
            seen.add(&q.counts(l));
            assert_quantized_close(&q.read_level(l), &f.read_level(l));
            for v in q.voxels(l) {
                for d in dirs {
                    let a = v.aiv(d);
                    assert!((0.0..=1.0).contains(&a), "{name}: AIV {a}");
                }
                for lb in v.lobes() {
                    assert!((lb.frame.determinant() - 1.0).abs() < 1e-3, "{name}");
                    assert!(lb.alpha.min_element() > 0.0 && lb.alpha.max_element() <= 1.0);
                }
            }
            for fc in q.faces(l) {
                for d in dirs {
                    let a = fc.abv(d);
                    assert!((0.0..=1.0).contains(&a), "{name}: ABV {a}");
                }
            }
        }
    }
    // The cases do hold what they are meant to.
    assert!(
        seen.aiv_all_visible > 0 && seen.aiv_all_occluded > 0,
        "{seen:?}"
    );
    assert!(seen.aiv_trees > 0 && seen.cut_out > 0, "{seen:?}");
    assert!(seen.abv_trees > 0 && seen.abv_trees < seen.faces);
}

/// A bake with visibility levels (`BakeSettings::visibility_levels`, format 1.7) is the same bytes on
/// one thread as on two; a file whose `shading_res` names no level of it is refused with an
/// error that says so; and with `shading_res` cleared (what a 1.6 reader sees, which does not
/// know the field) the visibility level is an ordinary level that renders finite values.
#[test]
fn visibility_levels_are_deterministic_and_checked() {
    use aggtool::format::fb;
    let dir = tempfile::tempdir().unwrap();
    let sc = scene("foliage", 1500, false);
    let s = BakeSettings {
        visibility_levels: 1,
        ..small()
    };
    let a = bake_on_threads(&sc, &s, dir.path(), "a.agg", 1);
    assert!(
        a == bake_on_threads(&sc, &s, dir.path(), "b.agg", 2),
        "1 and 2 threads differ"
    );
    let agg = Aggregate::from_bytes(a.clone()).unwrap();
    assert_eq!(agg.header().minor, MINOR);
    assert_eq!(agg.shading_level(0), 1);
    // Rewrites the recorded shading_res in place (the index's checksum fixed up).
    let with_shading_res = |r: u32| {
        let mut b = a.clone();
        let h = Header::parse(&b).unwrap();
        let (o, n) = (h.index_offset as usize, h.index_size as usize);
        let pos = {
            let index = flatbuffers::root::<fb::Index>(&b[o..o + n]).unwrap();
            let st = index.settings().unwrap();
            let field = st._tab.vtable().get(fb::BakeSettings::VT_SHADING_RES) as usize;
            assert!(field > 0, "shading_res is stored");
            o + st._tab.loc() + field
        };
        b[pos..pos + 4].copy_from_slice(&r.to_le_bytes());
        let mut h = h;
        h.index_crc32 = crc32fast::hash(&b[o..o + n]);
        b[..HEADER_SIZE].copy_from_slice(&h.to_bytes());
        b
    };
    assert_eq!(
        Aggregate::from_bytes(with_shading_res(4)).unwrap().bytes(),
        agg.bytes()
    );
    let Err(e) = Aggregate::from_bytes(with_shading_res(3)) else {
        panic!("a shading_res naming no level was read");
    };
    assert!(
        matches!(e, FormatError::Corrupt(_)) && e.to_string().contains("shading_res 3"),
        "{e}"
    );
    let plain = Aggregate::from_bytes(with_shading_res(0)).unwrap();
    assert_eq!(plain.shading_level(0), 0);
    let lod = aggtool::runtime::LodScene::new(plain);
    let (c, r) = sc.bounding_sphere();
    let view = aggtool::render::View::framing(c, r, 16, 16, 4);
    let lights = view.lights().unwrap();
    let ts = aggtool::runtime::TraceSettings {
        level: Some(0),
        ..Default::default()
    };
    let (img, stats) = aggtool::runtime::render(
        &lod,
        &view.camera(),
        &lights,
        4,
        1,
        &ts,
        &aggtool::util::no_progress,
    );
    common::assert_clean_render(&img, &stats, "a visibility level read as a plain one");
}
