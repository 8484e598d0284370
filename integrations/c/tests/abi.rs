//! The C ABI's contract, called from Rust through the rlib: bad input gives an error code and
//! a message, never a panic or a crash; good input traces the same as the Rust API.

use std::ffi::{CStr, CString};

use aggtool_capi::*;

fn last_error() -> String {
    unsafe { CStr::from_ptr(agg_last_error()) }
        .to_string_lossy()
        .into_owned()
}

/// The library's cones for the ABI's.
fn lib_cones(cones: &[AggCone]) -> Vec<aggtool::runtime::Cone> {
    cones
        .iter()
        .map(|k| aggtool::runtime::Cone::new(k.origin.into(), k.dir.into(), k.aperture))
        .collect()
}

/// A small baked tree in a temporary folder.
fn baked() -> (tempfile::TempDir, CString) {
    let dir = tempfile::tempdir().unwrap();
    let scene = aggtool::gen::generate(
        "foliage",
        &aggtool::gen::GenSettings {
            triangles: 1500,
            ..Default::default()
        },
    )
    .unwrap()
    .to_scene();
    let p = dir.path().join("t.agg");
    let settings = aggtool::bake::BakeSettings {
        max_res: 16,
        min_res: 4,
        samples: 4,
        aiv_rays: 4,
        aiv_res: 8,
        abv_res: 8,
        ..Default::default()
    };
    aggtool::bake::bake_to_file(&scene, "t", &settings, &p, &aggtool::util::no_progress).unwrap();
    let c = CString::new(p.to_str().unwrap()).unwrap();
    (dir, c)
}

#[test]
fn bad_input_is_an_error_code_with_a_message() {
    unsafe {
        assert!(agg_open(std::ptr::null()).is_null());
        assert!(last_error().contains("path"));
        let missing = CString::new("/nonexistent/x.agg").unwrap();
        assert!(agg_open(missing.as_ptr()).is_null());
        assert!(
            last_error().contains("/nonexistent/x.agg"),
            "{}",
            last_error()
        );
        let (dir, path) = baked();
        // A truncated copy is refused when opened.
        let bytes = std::fs::read(path.to_str().unwrap()).unwrap();
        let cut = dir.path().join("cut.agg");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let cut = CString::new(cut.to_str().unwrap()).unwrap();
        assert!(agg_open(cut.as_ptr()).is_null());
        assert!(!last_error().is_empty());

        let scene = agg_open(path.as_ptr());
        assert!(!scene.is_null(), "{}", last_error());
        let lights = agg_lights_new();
        let (mut lo, mut hi) = ([0f32; 3], [0f32; 3]);
        assert_eq!(
            agg_bounds(std::ptr::null(), lo.as_mut_ptr(), hi.as_mut_ptr()),
            AGG_ERR_ARGUMENT
        );
        assert_eq!(
            agg_bounds(scene, std::ptr::null_mut(), hi.as_mut_ptr()),
            AGG_ERR_ARGUMENT
        );
        assert_eq!(agg_bounds(scene, lo.as_mut_ptr(), hi.as_mut_ptr()), AGG_OK);
        // The culling box: every level's holds the bounds, a narrow near cone's lies in it.
        let (mut wlo, mut whi) = ([0f32; 3], [0f32; 3]);
        let (mut nlo, mut nhi) = ([0f32; 3], [0f32; 3]);
        let walk = |a: f32, t: f32, l: &mut [f32; 3], h: &mut [f32; 3]| {
            agg_walk_bounds(scene, a, t, l.as_mut_ptr(), h.as_mut_ptr())
        };
        assert_eq!(walk(0.0, f32::INFINITY, &mut wlo, &mut whi), AGG_OK);
        assert_eq!(walk(0.001, 5.0, &mut nlo, &mut nhi), AGG_OK);
        for i in 0..3 {
            assert!(wlo[i] <= lo[i] && whi[i] >= hi[i]);
            assert!(nlo[i] >= wlo[i] && nhi[i] <= whi[i]);
        }
        assert_eq!(walk(-1.0, 5.0, &mut nlo, &mut nhi), AGG_ERR_VALUE);
        assert_eq!(walk(0.01, f32::NAN, &mut nlo, &mut nhi), AGG_ERR_VALUE);
        assert_eq!(
            agg_walk_bounds(scene, 0.01, 1.0, std::ptr::null_mut(), nhi.as_mut_ptr()),
            AGG_ERR_ARGUMENT
        );
        // A lights pointer passed as a scene is refused, not dereferenced as one.
        assert_eq!(
            agg_bounds(lights as *const AggScene, lo.as_mut_ptr(), hi.as_mut_ptr()),
            AGG_ERR_ARGUMENT
        );
        let nan = [f32::NAN; 3];
        assert_eq!(agg_lights_set_constant(lights, nan.as_ptr()), AGG_ERR_VALUE);
        assert_eq!(
            agg_lights_set_sun(lights, [0.0f32; 3].as_ptr(), [1.0f32; 3].as_ptr()),
            AGG_ERR_VALUE
        );
        assert_eq!(
            agg_lights_set_environment(lights, [1.0f32; 3].as_ptr(), 0, 1, 1.0, 0.0),
            AGG_ERR_VALUE
        );
        let centre = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let good = AggCone {
            origin: [centre[0], centre[1], centre[2] + 3.0 * (hi[2] - lo[2])],
            dir: [0.0, 0.0, -1.0],
            aperture: 0.01,
        };
        let bad = AggCone {
            dir: [f32::NAN, 0.0, 0.0],
            ..good
        };
        let mut out = [0f32; 8];
        assert_eq!(
            agg_trace_cones(scene, lights, [good, bad].as_ptr(), 2, 1, out.as_mut_ptr()),
            AGG_ERR_VALUE
        );
        assert!(last_error().contains("cone 1"), "{}", last_error());
        assert_eq!(
            agg_trace_cones(scene, lights, std::ptr::null(), 0, 1, std::ptr::null_mut()),
            AGG_OK
        );
        assert_eq!(
            agg_trace_cones(scene, lights, std::ptr::null(), 2, 1, out.as_mut_ptr()),
            AGG_ERR_ARGUMENT
        );
        assert_eq!(
            agg_voxel_eval(
                scene,
                0,
                u64::MAX,
                [0.0, 1.0, 0.0f32].as_ptr(),
                [0.0, 0.0, 1.0f32].as_ptr(),
                out.as_mut_ptr()
            ),
            AGG_ERR_NOT_FOUND
        );
        assert_eq!(
            agg_voxel_eval(
                scene,
                99,
                0,
                [0.0, 1.0, 0.0f32].as_ptr(),
                [0.0, 0.0, 1.0f32].as_ptr(),
                out.as_mut_ptr()
            ),
            AGG_ERR_NOT_FOUND
        );
        agg_lights_free(lights);
        agg_close(scene);
        agg_close(std::ptr::null_mut());
        agg_lights_free(std::ptr::null_mut());
    }
}

#[test]
fn cones_and_hits_agree_with_the_rust_api() {
    unsafe {
        let (_dir, path) = baked();
        let scene = agg_open(path.as_ptr());
        assert!(!scene.is_null(), "{}", last_error());
        let lights = agg_lights_new();
        let (mut lo, mut hi) = ([0f32; 3], [0f32; 3]);
        assert_eq!(agg_bounds(scene, lo.as_mut_ptr(), hi.as_mut_ptr()), AGG_OK);
        let c = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let cone = AggCone {
            origin: [c[0], c[1], c[2] + 3.0 * (hi[2] - lo[2])],
            dir: [0.0, 0.0, -1.0],
            aperture: 0.004,
        };
        // Radiance: the C call against the Rust API with the same cone and random stream.
        let mut out = [0f32; 4];
        assert_eq!(
            agg_trace_cones(scene, lights, &cone, 1, 5, out.as_mut_ptr()),
            AGG_OK
        );
        let rust =
            aggtool::runtime::LodScene::open(std::path::Path::new(path.to_str().unwrap())).unwrap();
        let r = rust.trace(
            &aggtool::runtime::Cone::new(cone.origin.into(), cone.dir.into(), cone.aperture),
            &aggtool::lights::Lights::constant(glam::Vec3::ONE),
            &Default::default(),
            &mut aggtool::math::rng::Pcg32::new(5, 0),
        );
        assert_eq!(
            out,
            [r.radiance.x, r.radiance.y, r.radiance.z, r.transmittance]
        );
        // Hits: the count, a second call with room for all, each voxel answering eval and
        // visibility, and coverage + transmittance ≈ 1 for a cone through the middle.
        let (mut n, mut t) = (0usize, 0f32);
        assert_eq!(
            agg_hits(scene, &cone, std::ptr::null_mut(), 0, &mut n, &mut t),
            AGG_OK
        );
        assert!(n > 0, "the centre cone met nothing");
        let mut hits = vec![AggHit::default(); n];
        let mut n2 = 0usize;
        assert_eq!(
            agg_hits(scene, &cone, hits.as_mut_ptr(), n, &mut n2, &mut t),
            AGG_OK
        );
        assert_eq!(n, n2);
        for h in &hits {
            let mut rgb = [0f32; 3];
            let (wi, wo) = ([0.0f32, 1.0, 0.0], [0.0f32, 0.0, 1.0]);
            assert_eq!(
                agg_voxel_eval(
                    scene,
                    h.level,
                    h.key,
                    wi.as_ptr(),
                    wo.as_ptr(),
                    rgb.as_mut_ptr()
                ),
                AGG_OK,
                "{}",
                last_error()
            );
            assert!(rgb.iter().all(|x| x.is_finite() && *x >= 0.0));
            let (mut aiv, mut inc) = (0f32, 0f32);
            assert_eq!(
                agg_voxel_visibility(scene, h.level, h.key, wi.as_ptr(), &mut aiv, &mut inc),
                AGG_OK
            );
            assert!((0.0..=1.0).contains(&aiv) && (0.0..=1.0).contains(&inc));
            let (mut wi2, mut val, mut pdf) = ([0f32; 3], [0f32; 3], 0f32);
            let code = agg_voxel_sample(
                scene,
                h.level,
                h.key,
                wo.as_ptr(),
                [0.3f32, 0.6, 0.2].as_ptr(),
                wi2.as_mut_ptr(),
                val.as_mut_ptr(),
                &mut pdf,
            );
            assert!(code == AGG_OK || code == AGG_ERR_NOT_FOUND);
        }
        assert!((0.0..=1.0).contains(&t));
        agg_lights_free(lights);
        agg_close(scene);
    }
}

/// `agg_open` takes an assembly manifest too: two instances of the tree trace through the C
/// ABI exactly as the library's `Opened` traces them, their bounds cover both instances, the
/// hit layer refuses the assembly with a message, and a manifest naming a missing aggregate
/// is refused at open with the asset's id.
#[test]
fn a_manifest_opens_and_traces_as_the_library_does() {
    unsafe {
        let (dir, path) = baked();
        let agg = std::path::Path::new(path.to_str().unwrap());
        let manifest = dir.path().join("pair.json");
        std::fs::write(
            &manifest,
            format!(
                r#"{{ "version": 1,
                     "assets": {{ "tree": {{ "source": "t.glb", "aggregate": "{}" }} }},
                     "instances": [ {{ "asset": "tree" }},
                                    {{ "asset": "tree", "translation": [40, 0, 0] }} ] }}"#,
                agg.file_name().unwrap().to_str().unwrap()
            ),
        )
        .unwrap();
        // The source need not exist to render from aggregates; give it anyway.
        std::fs::write(dir.path().join("t.glb"), b"").unwrap();
        let m = CString::new(manifest.to_str().unwrap()).unwrap();
        let s = agg_open(m.as_ptr());
        assert!(!s.is_null(), "{}", last_error());
        let (mut lo, mut hi) = ([0f32; 3], [0f32; 3]);
        assert_eq!(agg_bounds(s, lo.as_mut_ptr(), hi.as_mut_ptr()), AGG_OK);
        let (alo, ahi) = aggtool::format::Aggregate::open(agg).unwrap().bounds();
        assert!(
            hi[0] - lo[0] >= 40.0 + (ahi.x - alo.x) * 0.99,
            "{lo:?} {hi:?}"
        );
        let l = agg_lights_new();
        let c = 0.5 * (alo + ahi);
        let cones: Vec<AggCone> = (0..64)
            .map(|i| {
                let x = c.x + 20.0 + (i % 8) as f32 * 5.0 - 20.0;
                AggCone {
                    origin: [x, c.y + (i / 8) as f32 - 4.0, c.z + 200.0],
                    dir: [0.0, 0.0, -1.0],
                    aperture: 0.002,
                }
            })
            .collect();
        let mut out = vec![0f32; 4 * cones.len()];
        assert_eq!(
            agg_trace_cones(s, l, cones.as_ptr(), cones.len(), 9, out.as_mut_ptr()),
            AGG_OK,
            "{}",
            last_error()
        );
        let lib = aggtool::assembly::Opened::open(&manifest).unwrap();
        let rc = lib_cones(&cones);
        let mut want = vec![0f32; out.len()];
        lib.trace_batch(
            &rc,
            &aggtool::lights::Lights::constant(glam::Vec3::ONE),
            &aggtool::runtime::TraceSettings::default(),
            9,
            &mut want,
        );
        assert_eq!(out, want);
        assert!(out.chunks(4).any(|p| p[3] < 1.0), "some cone meets a tree");
        // A host's pass of stratified samples: the library's batch, the same bytes; pixel
        // ids are required.
        let pixels: Vec<u64> = (0..cones.len() as u64).map(|p| 40 + p).collect();
        assert_eq!(
            agg_trace_cones_stratified(
                s,
                l,
                cones.as_ptr(),
                pixels.as_ptr(),
                cones.len(),
                3,
                9,
                out.as_mut_ptr()
            ),
            AGG_OK,
            "{}",
            last_error()
        );
        let at = aggtool::runtime::PixelSamples {
            pixels: &pixels,
            sample: 3,
        };
        lib.trace_batch_stratified(
            &rc,
            at,
            &aggtool::lights::Lights::constant(glam::Vec3::ONE),
            &aggtool::runtime::TraceSettings::default(),
            9,
            &mut want,
        );
        assert_eq!(out, want);
        assert_eq!(
            agg_trace_cones_stratified(
                s,
                l,
                cones.as_ptr(),
                std::ptr::null(),
                cones.len(),
                3,
                9,
                out.as_mut_ptr()
            ),
            AGG_ERR_ARGUMENT
        );
        let (mut n, mut t) = (0usize, 0f32);
        assert_eq!(
            agg_hits(s, &cones[0], std::ptr::null_mut(), 0, &mut n, &mut t),
            AGG_ERR_VALUE
        );
        assert!(last_error().contains("assembly"), "{}", last_error());
        // One pick a cone through every instance: the library's picks; the picked voxels
        // shade by instance (a translated instance: the aggregate's own directions). Cones
        // alternate between the two trees.
        let cones: Vec<AggCone> = (0..64)
            .map(|i| AggCone {
                origin: [
                    c.x + 40.0 * (i % 2) as f32
                        + (ahi.x - alo.x) * (((i / 2) % 4) as f32 / 4.0 - 0.375),
                    c.y + (ahi.y - alo.y) * ((i / 8) as f32 / 8.0 - 0.44),
                    c.z + 200.0,
                ],
                dir: [0.0, 0.0, -1.0],
                aperture: 0.002,
            })
            .collect();
        let rc = lib_cones(&cones);
        let u: Vec<f32> = (0..cones.len()).map(|i| (i as f32 + 0.5) / 64.0).collect();
        let mut picks = vec![AggPick::default(); cones.len()];
        assert_eq!(
            agg_pick_cones(
                s,
                cones.as_ptr(),
                cones.len(),
                u.as_ptr(),
                std::ptr::null(),
                picks.as_mut_ptr()
            ),
            AGG_OK,
            "{}",
            last_error()
        );
        let want = lib.pick_batch(&rc, &u, &aggtool::runtime::TraceSettings::default());
        let single = aggtool::runtime::LodScene::open(agg).unwrap();
        let mut instances = [0; 2];
        for (p, w) in picks.iter().zip(&want) {
            assert_eq!(
                (p.weight, p.transmittance, p.entry),
                (w.weight, w.transmittance, w.entry)
            );
            let Some(h) = w.hit else {
                assert!(p.weight == 0.0 && p.t.is_infinite());
                continue;
            };
            assert_eq!(
                (p.instance, p.level, p.key, p.t),
                (h.instance, h.level, h.key, h.t)
            );
            instances[p.instance as usize] += 1;
            let (wi, wo) = ([0.0f32, 1.0, 0.0], [0.0f32, 0.0, 1.0]);
            let mut rgb = [0f32; 3];
            assert_eq!(
                agg_instance_voxel_eval(
                    s,
                    p.instance,
                    p.level,
                    p.key,
                    wi.as_ptr(),
                    wo.as_ptr(),
                    rgb.as_mut_ptr()
                ),
                AGG_OK,
                "{}",
                last_error()
            );
            let v = single.voxel(p.level as usize, p.key).unwrap();
            use aggtool::bsdf::Bsdf;
            assert_eq!(
                rgb,
                v.eval(glam::Vec3::from(wi), glam::Vec3::from(wo))
                    .to_array()
            );
            let (mut aiv, mut inc) = (0f32, 0f32);
            assert_eq!(
                agg_instance_voxel_visibility(
                    s,
                    p.instance,
                    p.level,
                    p.key,
                    wi.as_ptr(),
                    &mut aiv,
                    &mut inc
                ),
                AGG_OK
            );
            assert_eq!(
                (aiv, inc),
                (v.aiv(glam::Vec3::Y), v.incident_visibility(glam::Vec3::Y))
            );
            let (mut wi2, mut val, mut pdf) = ([0f32; 3], [0f32; 3], 0f32);
            let uu = [0.3f32, 0.6, 0.2];
            let code = agg_instance_voxel_sample(
                s,
                p.instance,
                p.level,
                p.key,
                wo.as_ptr(),
                uu.as_ptr(),
                wi2.as_mut_ptr(),
                val.as_mut_ptr(),
                &mut pdf,
            );
            assert!(
                code == AGG_OK || code == AGG_ERR_NOT_FOUND,
                "{}",
                last_error()
            );
            // The shading call: the same numbers as the calls above, in one look-up (with a
            // light sample, and without one: NULL).
            let shade = |wi_light: *const f32| {
                let mut out = AggShade::default();
                let code = agg_instance_voxel_shade(
                    s,
                    p.instance,
                    p.level,
                    p.key,
                    wo.as_ptr(),
                    wi_light,
                    uu.as_ptr(),
                    &mut out,
                );
                assert_eq!(code, AGG_OK, "{}", last_error());
                out
            };
            let sh = shade(wi.as_ptr());
            assert_eq!(sh.light_value, rgb);
            assert_eq!(sh.light_visibility, inc);
            if code == AGG_OK {
                assert_eq!((sh.wi, sh.value, sh.pdf), (wi2, val, pdf));
                let (mut a2, mut i2) = (0f32, 0f32);
                agg_instance_voxel_visibility(
                    s,
                    p.instance,
                    p.level,
                    p.key,
                    wi2.as_ptr(),
                    &mut a2,
                    &mut i2,
                );
                assert_eq!(sh.visibility, i2);
            } else {
                assert_eq!((sh.pdf, sh.visibility), (0.0, 0.0));
            }
            let dark = shade(std::ptr::null());
            assert_eq!((dark.light_value, dark.light_pdf), ([0.0; 3], 0.0));
            assert_eq!((dark.wi, dark.pdf), (sh.wi, sh.pdf));
        }
        assert!(instances[0] > 0 && instances[1] > 0, "{instances:?}");
        let mut rgb = [0f32; 3];
        let dir = [0.0f32, 1.0, 0.0];
        assert_eq!(
            agg_instance_voxel_eval(s, 2, 0, 0, dir.as_ptr(), dir.as_ptr(), rgb.as_mut_ptr()),
            AGG_ERR_VALUE
        );
        assert!(
            last_error().contains("instance 2 is out of range"),
            "{}",
            last_error()
        );
        let bad_u = [f32::NAN];
        assert_eq!(
            agg_pick_cones(
                s,
                cones.as_ptr(),
                1,
                bad_u.as_ptr(),
                std::ptr::null(),
                picks.as_mut_ptr()
            ),
            AGG_ERR_VALUE
        );
        assert_eq!(
            agg_pick_cones(
                s,
                cones.as_ptr(),
                1,
                std::ptr::null(),
                std::ptr::null(),
                picks.as_mut_ptr()
            ),
            AGG_ERR_ARGUMENT
        );
        agg_lights_free(l);
        agg_close(s);
        // A manifest naming a missing aggregate.
        std::fs::write(
            &manifest,
            r#"{ "version": 1, "assets": { "tree": { "source": "t.glb", "aggregate": "gone.agg" } },
                 "instances": [ { "asset": "tree" } ] }"#,
        )
        .unwrap();
        assert!(agg_open(m.as_ptr()).is_null());
        assert!(last_error().contains("tree"), "{}", last_error());
    }
}

/// The cache budget through the C ABI: 0 is refused with a message; under a 1 MiB budget the
/// same cones give the same bits as under the default, and the statistics count the blocks
/// prepared. The budget is the process's, so the test puts the default back.
#[test]
fn the_cache_budget_through_the_abi() {
    unsafe {
        let (_dir, path) = baked();
        assert_eq!(agg_set_cache_mib(0), AGG_ERR_VALUE);
        assert!(last_error().contains("at least 1 MiB"), "{}", last_error());
        assert_eq!(agg_cache_stats(std::ptr::null_mut()), AGG_ERR_ARGUMENT);
        let lights = agg_lights_new();
        let trace = || {
            let scene = agg_open(path.as_ptr());
            assert!(!scene.is_null(), "{}", last_error());
            let (mut lo, mut hi) = ([0f32; 3], [0f32; 3]);
            assert_eq!(agg_bounds(scene, lo.as_mut_ptr(), hi.as_mut_ptr()), AGG_OK);
            let cones: Vec<AggCone> = (0..64)
                .map(|i| AggCone {
                    origin: [
                        lo[0] + (hi[0] - lo[0]) * (i % 8) as f32 / 7.0,
                        lo[1] + (hi[1] - lo[1]) * (i / 8) as f32 / 7.0,
                        hi[2] + 0.5 * (hi[2] - lo[2]) * (1 + i % 3) as f32,
                    ],
                    dir: [0.0, 0.0, -1.0],
                    aperture: 0.004,
                })
                .collect();
            let mut out = vec![0f32; 4 * cones.len()];
            assert_eq!(
                agg_trace_cones(
                    scene,
                    lights,
                    cones.as_ptr(),
                    cones.len(),
                    5,
                    out.as_mut_ptr()
                ),
                AGG_OK
            );
            agg_close(scene);
            out
        };
        let roomy = trace();
        assert_eq!(agg_set_cache_mib(1), AGG_OK);
        let small = trace();
        let mut stats = AggCacheStats::default();
        assert_eq!(agg_cache_stats(&mut stats), AGG_OK);
        assert_eq!(stats.budget, 1 << 20);
        assert!(stats.loaded > 0 && stats.peak > 0, "{stats:?}");
        let default_mib = aggtool::runtime::default_budget() >> 20;
        assert_eq!(agg_set_cache_mib(default_mib), AGG_OK);
        agg_lights_free(lights);
        assert!(roomy
            .iter()
            .zip(&small)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(
            roomy.chunks(4).any(|c| c[3] < 1.0),
            "the cones miss the tree"
        );
    }
}
