//! Validation of the factorized ABSDF against the ground truth of Eq. 3 on the seven voxel
//! cases, energy (Eq. 4), reciprocity (Eq. 5), sampling against the pdf, and hard cases.

use aggtool::absdf::cases::{case_samples, compare_case, sphere_grid, CASES};
use aggtool::absdf::estimate::{estimate, EstimateSettings, SurfaceSample};
use aggtool::absdf::{Absdf, MaterialMoments, Moments, NdfLobe, VoxelAppearance};
use aggtool::bsdf::{BaseBsdf, Bsdf};
use aggtool::math::rng::Pcg32;
use aggtool::math::sampling::square_to_uniform_sphere;
use aggtool::math::unit_or_zero;
use aggtool::scene::SurfaceParams;
use aggtool::tables::Tables;
use aggtool::validation::chi2::{chi2_test, Chi2Settings};
use glam::{Mat3, Vec2, Vec3};

fn appearance(name: &str) -> VoxelAppearance {
    estimate(
        &case_samples(name, 2048).unwrap(),
        &EstimateSettings::default(),
    )
    .unwrap()
}

/// Relative RMSE (RMSE over direction pairs / RMS of the ground truth) per case, on a 6×6
/// equal-area grid of both directions with 2048 samples. The bounds are regression guards 25% above
/// the values measured, the flat voxel's 1% as in `flat_voxel_is_its_base_bsdf` (flat 0.003, curved
/// 0.644, foliage 0.094, anisotropic 0.095, orientation-color 0.186, mixed-roughness 0.388,
/// metal-dielectric 0.145, leaf-and-twig 0.157; with Eq. 21's S read at the microfacet roughness
/// alone flat was 0.022, anisotropic 0.106, mixed-roughness 0.371 and metal-dielectric 0.149; with
/// Eq. 14's SG diffuse term foliage was 0.174, orientation-color 0.248 and metal-dielectric 0.212;
/// with the lobes weighed by their area shares alone, not over their masses, leaf-and-twig was
/// 0.255); they are not goals. The curved voxel (normals uniform over a 60° cap) is the known weak
/// case: a mixture of GGX-shaped lobes cannot take a flat-topped, sharp-edged normal distribution.
/// `cargo test --release --test absdf -- --ignored --nocapture` prints the full-size figures.
#[test]
fn factored_absdf_tracks_ground_truth() {
    let t = Tables::embedded();
    let guard = [0.01, 0.81, 0.12, 0.12, 0.24, 0.49, 0.19, 0.2];
    for (&name, &g) in CASES.iter().zip(&guard) {
        let (r, _) = compare_case(name, t, 2048, 6).unwrap();
        let rel = r.rmse / r.gt_rms;
        eprintln!(
            "{name}: lobes {} rmse {:.4} gt rms {:.4} relative {:.3}",
            r.lobes, r.rmse, r.gt_rms, rel
        );
        assert!(
            rel.is_finite() && rel < g,
            "{name}: relative RMSE {rel} above its guard {g}"
        );
    }
}

/// Full-size figures for the closing note: 8192 samples, 12×12 grids.
#[test]
#[ignore]
fn report_absdf_rmse() {
    let t = Tables::embedded();
    for &name in CASES {
        let (r, _) = compare_case(name, t, 8192, 12).unwrap();
        println!(
            "{name:<18} lobes {} rmse {:.5} gt_rms {:.5} relative {:.4}",
            r.lobes,
            r.rmse,
            r.gt_rms,
            r.rmse / r.gt_rms
        );
    }
}

/// Eq. 5: σ_N(ω_o) f̂(ω_i, ω_o) = σ_N(ω_i) f̂(ω_o, ω_i); every factor of our model is symmetric,
/// so it holds to f32 rounding (1e-4 relative).
#[test]
fn reciprocity() {
    let t = Tables::embedded();
    let dirs = sphere_grid(6);
    for &name in CASES {
        let a = Absdf::new(&appearance(name), t);
        for &wo in &dirs {
            for &wi in &dirs {
                let l = a.eval(wi, wo) * a.projected_area(wo);
                let r = a.eval(wo, wi) * a.projected_area(wi);
                assert!(
                    (l - r).abs().max_element()
                        <= 1e-4 * l.max_element().max(r.max_element()).max(1e-3),
                    "{name}: {l} vs {r}"
                );
            }
        }
    }
}

/// Eq. 4 with white metal (no unattenuated diffuse): ∫ f̂ dω_i ≤ 1. Monte Carlo with 40k uniform
/// directions per ω_o (standard error ≲ 2% for these lobes): tolerance 10%, which also absorbs
/// the approximation of the factorization.
#[test]
fn energy() {
    let t = Tables::embedded();
    for &name in CASES {
        let mut s = case_samples(name, 1024).unwrap();
        for x in &mut s {
            x.params.base_color = Vec3::ONE;
            x.params.metallic = 1.0;
        }
        let a = Absdf::new(&estimate(&s, &EstimateSettings::default()).unwrap(), t);
        for wo in sphere_grid(4) {
            let mut rng = Pcg32::new(3, 9);
            let n = 40_000;
            let mut acc = 0f64;
            for _ in 0..n {
                let wi = square_to_uniform_sphere(rng.next_2d());
                acc += a.eval(wi, wo).max_element() as f64;
            }
            let e = acc / n as f64 * 4.0 * std::f64::consts::PI;
            assert!(e <= 1.1, "{name} ω_o={wo}: ∫f̂ = {e}");
        }
    }
}

/// A diffuse-only voxel reflects exactly its albedo: ∫ f̂ dω_i over the sphere (a 256² equal-area
/// quadrature), for a flat Lambertian voxel at views from 0° to 85° (all of it from the upper
/// hemisphere: nothing through the sheet) and for foliage-like normals spread over the sphere.
/// With Eq. 14's clamped-cosine SGs the flat voxel gave 0.81, 0.90, 0.83, 0.63 of the albedo
/// from above at 0°, 30°, 60°, 80° and passed 0.05 to 0.25 through from below.
#[test]
fn flat_lambertian_voxel_reflects_its_albedo() {
    let t = Tables::embedded();
    let albedo = 0.6;
    let lambert = |normal: Vec3| SurfaceSample {
        normal,
        params: SurfaceParams {
            base_color: Vec3::splat(albedo),
            metallic: 0.0,
            alpha: 1.0,
            specular: 0.0,
            f90: 0.0,
        },
        weight: 1.0,
    };
    let flat: Vec<SurfaceSample> = (0..256).map(|_| lambert(Vec3::Z)).collect();
    let spread: Vec<SurfaceSample> = case_samples("foliage", 2048)
        .unwrap()
        .iter()
        .map(|s| lambert(s.normal))
        .collect();
    let dirs = sphere_grid(256);
    let dw = 4.0 * std::f32::consts::PI / dirs.len() as f32;
    for (name, samples) in [("flat", flat), ("spread", spread)] {
        let a = Absdf::new(
            &estimate(&samples, &EstimateSettings::default()).unwrap(),
            t,
        );
        for deg in [0.0f32, 30.0, 60.0, 80.0, 85.0] {
            let th = deg.to_radians();
            let wo = Vec3::new(th.sin(), 0.0, th.cos());
            let (mut up, mut down) = (0f64, 0f64);
            for &wi in &dirs {
                let f = a.eval(wi, wo).x as f64 * dw as f64;
                if wi.z > 0.0 {
                    up += f;
                } else {
                    down += f;
                }
            }
            let total = (up + down) / albedo as f64;
            eprintln!(
                "{name} {deg}°: above {:.4} below {:.4}",
                up / albedo as f64,
                down / albedo as f64
            );
            // The flat voxel is exact; spread normals gain ~2% where the lobe integral's
            // approximation would go negative and is clamped to 0 (see `diffuse_numerator`).
            let tol = if name == "flat" { 0.01 } else { 0.03 };
            assert!(
                (total - 1.0).abs() < tol,
                "{name} at {deg}°: ∫f̂ = {total} of the albedo"
            );
            if name == "flat" {
                assert!(
                    down < 1e-3 * albedo as f64,
                    "{name} at {deg}°: {down} through the sheet"
                );
            }
        }
    }
}

/// A flat voxel of one material is its base BSDF: f̂(ω_i, ω_o) = f(ω_i, ω_o)·cos θ_i over the
/// upper hemisphere (a 64² equal-area grid), for dielectrics with the glTF default specular
/// (F0 0.04, F90 1) and metals, from mirror-like to α = 1, at views from 0° to 85°: relative
/// RMSE (over the base BSDF's RMS) below 1%. Reading Eq. 21's S at the microfacet roughness
/// alone failed this at grazing views: α = 1 at 72° reached 0.51 of the base BSDF towards an
/// ω_i at 80° on the far side (relative RMSE 0.1 and more); see `lune_alpha`.
#[test]
fn flat_voxel_is_its_base_bsdf() {
    let t = Tables::embedded();
    let dirs: Vec<Vec3> = sphere_grid(64).into_iter().filter(|w| w.z > 0.0).collect();
    for metallic in [0.0f32, 1.0] {
        for alpha in [0.05f32, 0.2, 0.5, 1.0] {
            let params = SurfaceParams {
                base_color: Vec3::splat(0.5),
                metallic,
                alpha,
                specular: 0.04,
                f90: 1.0,
            };
            let flat: Vec<SurfaceSample> = (0..256)
                .map(|_| SurfaceSample {
                    normal: Vec3::Z,
                    params,
                    weight: 1.0,
                })
                .collect();
            let a = Absdf::new(&estimate(&flat, &EstimateSettings::default()).unwrap(), t);
            let base = BaseBsdf::new(params);
            for deg in [0.0f32, 45.0, 72.0, 85.0] {
                let th = deg.to_radians();
                let wo = Vec3::new(th.sin(), 0.0, th.cos());
                let (mut se, mut ss) = (0f64, 0f64);
                for &wi in &dirs {
                    let f = a.eval(wi, wo).x as f64;
                    let g = (base.eval(wi, wo).x * wi.z) as f64;
                    se += (f - g).powi(2);
                    ss += g * g;
                }
                let rel = (se / ss).sqrt();
                assert!(
                    rel < 0.01,
                    "metallic {metallic}, α {alpha}, view at {deg}°: relative RMSE {rel}"
                );
            }
        }
    }
}

/// `sample` against `pdf` with the shared chi-square harness, and `eval_pdf` agrees.
#[test]
fn sampling_matches_pdf() {
    let t = Tables::embedded();
    for &name in CASES {
        let a = Absdf::new(&appearance(name), t);
        for wo in [
            Vec3::new(0.3, 0.2, 0.93).normalize(),
            Vec3::new(0.9, 0.1, 0.2).normalize(),
        ] {
            let mut rng = Pcg32::new(5, 5);
            let r = chi2_test(
                Chi2Settings {
                    samples: 100_000,
                    integration_res: 40,
                    ..Default::default()
                },
                |u| a.sample(wo, rng.next_f32(), u).map(|s| s.wi),
                |wi| a.pdf(wi, wo),
            );
            assert!(r.passed(0.01), "{name} {wo}: {r:?}");
            for wi in sphere_grid(4) {
                let (f, p) = a.eval_pdf(wi, wo);
                assert_eq!((f, p), (a.eval(wi, wo), a.pdf(wi, wo)));
            }
            // A sample's value and pdf are what evaluating its direction gives, to the bit,
            // for ω_o as given and as unit_or_zero gives it (the Python module's voxel_eval
            // re-checks sampled directions this way; the directional moments are looked up
            // by cell, so a re-normalisation that moved ω_i by one ulp once broke it).
            for wo in [wo, unit_or_zero(wo), 3.0 * wo] {
                for _ in 0..20_000 {
                    let u = Vec2::new(rng.next_f32(), rng.next_f32());
                    let Some(s) = a.sample(wo, rng.next_f32(), u) else {
                        continue;
                    };
                    assert_eq!(unit_or_zero(s.wi), s.wi);
                    assert_eq!(a.eval_pdf(s.wi, wo), (s.value, s.pdf), "{name} {wo} {s:?}");
                }
            }
        }
    }
}

fn flat_voxel(alpha: f32, metallic: f32, var: f32) -> VoxelAppearance {
    VoxelAppearance {
        lobes: vec![NdfLobe {
            weight: 1.0,
            frame: Mat3::IDENTITY,
            alpha: Vec2::ZERO,
        }],
        roughness_mean: alpha,
        roughness_variance: var,
        moments: Moments::Constant(MaterialMoments {
            c: Vec3::splat(0.7),
            mc: Vec3::splat(0.7 * metallic),
            s: 0.04,
            ms: 0.04 * metallic,
            m: metallic,
            f90: 1.0,
            mf90: metallic,
        }),
    }
}

/// Flat voxels, roughness 0 and 1, ω_i = ±ω_o, grazing, one sample, zero variance, metallic 0
/// and 1: everything finite, and the flat Lambertian voxel matches its BRDF × cos θ_i.
#[test]
fn hard_cases_are_finite() {
    let t = Tables::embedded();
    let dirs = [
        Vec3::Z,
        -Vec3::Z,
        Vec3::X,
        Vec3::new(1.0, 0.0, 1e-6).normalize(),
        Vec3::new(0.3, -0.4, 0.866).normalize(),
    ];
    for app in [
        flat_voxel(0.0, 0.0, 0.0),
        flat_voxel(1.0, 1.0, 0.0),
        flat_voxel(0.3, 0.5, 0.02),
        flat_voxel(0.5, 1.0, 0.25),
    ] {
        let a = Absdf::new(&app, t);
        for &wo in &dirs {
            for &wi in &dirs {
                let (f, p) = a.eval_pdf(wi, wo);
                assert!(f.is_finite() && p.is_finite() && f.min_element() >= 0.0 && p >= 0.0);
            }
            for k in 0..8 {
                if let Some(s) = a.sample(wo, k as f32 / 8.0, Vec2::new(0.37, k as f32 / 8.0)) {
                    assert!(s.wi.is_finite() && s.value.is_finite() && s.pdf > 0.0);
                }
            }
        }
    }
    // One sample.
    let one = [SurfaceSample {
        normal: Vec3::Z,
        params: SurfaceParams::lambertian(Vec3::ONE),
        weight: 1.0,
    }];
    let a = Absdf::new(&estimate(&one, &EstimateSettings::default()).unwrap(), t);
    assert!(a.eval(Vec3::Z, Vec3::Z).is_finite());
}

#[test]
fn embedded_tables_round_trip() {
    let t = Tables::embedded();
    assert_eq!(&Tables::from_bytes(&t.to_bytes()).unwrap(), t);
    assert!(
        aggtool::tables::EMBEDDED.len() < 5 << 20,
        "tables stay under 5 MB"
    );
    let b = t.to_bytes();
    for n in [0, 7, 12, 100, b.len() - 1] {
        assert!(Tables::from_bytes(&b[..n]).is_err());
    }
    let mut longer = b.clone();
    longer.push(0);
    assert!(Tables::from_bytes(&longer).is_err());
}
