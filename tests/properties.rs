//! Property tests: no NaN or infinity leaves the BSDF, the samplers or the lights, for any
//! input including degenerate ones, and none is produced inside and replaced on the way (the
//! count of `aggtool::math::numerics` stays zero, so a NaN that a function hides would still
//! fail these tests).

use aggtool::bsdf::{BaseBsdf, Bsdf};
use aggtool::film::Image;
use aggtool::lights::EnvMap;
use aggtool::math::distribution::Distribution1D;
use aggtool::math::microfacet::{ggx_g2, ggx_sample_vndf};
use aggtool::math::numerics::non_finite_count;
use aggtool::scene::SurfaceParams;
use glam::{Vec2, Vec3};
use proptest::prelude::*;

fn any_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        -2.0f32..2.0,
        Just(0.0f32),
        Just(1.0f32),
        Just(-1.0f32),
        Just(1e-8f32),
        Just(f32::NAN),
        Just(f32::INFINITY),
        Just(f32::MIN_POSITIVE),
    ]
}

fn any_dir() -> impl Strategy<Value = Vec3> {
    prop_oneof![
        (any_f32(), any_f32(), any_f32()).prop_map(|(x, y, z)| Vec3::new(x, y, z)),
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0)
            .prop_map(|(x, y, z)| Vec3::new(x, y, z).normalize_or(Vec3::Z)),
        Just(Vec3::Z),
        Just(-Vec3::Z),
        Just(Vec3::new(1.0, 0.0, 1e-7).normalize()),
    ]
}

fn any_params() -> impl Strategy<Value = SurfaceParams> {
    (any_f32(), any_f32(), any_f32(), any_f32(), any_f32()).prop_map(|(c, m, a, s, f)| {
        SurfaceParams {
            base_color: Vec3::splat(c.clamp(0.0, 1.0)),
            metallic: if m.is_nan() { 0.0 } else { m.clamp(0.0, 1.0) },
            alpha: a,
            specular: if s.is_nan() { 0.04 } else { s.clamp(0.0, 0.08) },
            f90: if f.is_nan() { 1.0 } else { f.clamp(0.0, 1.0) },
        }
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn bsdf_is_finite(p in any_params(), wo in any_dir(), wi in any_dir(), u in (0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0)) {
        let before = non_finite_count();
        let b = BaseBsdf::new(p);
        let f = b.eval(wi, wo);
        prop_assert!(f.is_finite() && f.min_element() >= 0.0);
        let pdf = b.pdf(wi, wo);
        prop_assert!(pdf.is_finite() && pdf >= 0.0);
        if let Some(s) = b.sample(wo, u.0, Vec2::new(u.1, u.2)) {
            prop_assert!(s.wi.is_finite() && s.value.is_finite() && s.pdf.is_finite() && s.pdf > 0.0);
        }
        prop_assert_eq!(non_finite_count(), before);
    }

    #[test]
    fn microfacet_is_finite(w in any_dir(), a in 1e-3f32..1.0, b in 1e-3f32..1.0, u in (0.0f32..1.0, 0.0f32..1.0)) {
        let w = w.normalize_or(Vec3::Z);
        if w.z > 0.0 {
            let m = ggx_sample_vndf(w, a, b, Vec2::new(u.0, u.1));
            prop_assert!(m.is_finite());
        }
        prop_assert!(ggx_g2(w, w, a, b).is_finite());
    }

    #[test]
    fn distribution_is_finite(w in proptest::collection::vec(any_f32(), 1..20), u in 0.0f32..1.0) {
        let before = non_finite_count();
        let d = Distribution1D::new(&w);
        let (x, pdf, _) = d.sample(u);
        prop_assert!(x.is_finite() && (0.0..1.0).contains(&x) && pdf.is_finite() && pdf > 0.0);
        prop_assert!(d.pdf(x).is_finite());
        prop_assert_eq!(non_finite_count(), before);
    }

    /// 80000:1 dynamic range, NaN and negative texels, tiny maps.
    #[test]
    fn environment_is_finite(vals in proptest::collection::vec(prop_oneof![Just(80000.0f32), Just(1.0f32), Just(0.0f32), Just(-1.0f32), Just(f32::NAN)], 1..24),
                             w in 1u32..6, d in any_dir(), u in (0.0f32..1.0, 0.0f32..1.0), rot in -720.0f32..720.0) {
        let h = (vals.len() as u32 / w).max(1);
        let mut img = Image::new(w, h);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            *p = Vec3::splat(vals[i % vals.len()]);
        }
        let before = non_finite_count();
        let env = EnvMap::from_image(&img, 1.0, rot);
        let d = d.normalize_or(Vec3::Y);
        prop_assert!(env.eval(d).is_finite());
        prop_assert!(env.pdf(d).is_finite());
        if let Some(s) = env.sample(Vec2::new(u.0, u.1)) {
            prop_assert!(s.wi.is_finite() && s.radiance.is_finite() && s.pdf.is_finite() && s.pdf > 0.0);
        }
        prop_assert_eq!(non_finite_count(), before);
    }
}

mod absdf_props {
    use aggtool::absdf::{Absdf, MaterialMoments, Moments, NdfLobe, VoxelAppearance};
    use aggtool::bsdf::Bsdf;
    use aggtool::math::numerics::non_finite_count;
    use aggtool::tables::Tables;
    use glam::{Mat3, Quat, Vec2, Vec3};
    use proptest::prelude::*;

    fn any_unit() -> impl Strategy<Value = f32> {
        prop_oneof![0.0f32..=1.0, Just(0.0f32), Just(1.0f32), Just(f32::NAN)]
    }

    fn any_lobe() -> impl Strategy<Value = NdfLobe> {
        (
            any_unit(),
            (-3.0f32..3.0, -3.0f32..3.0, -3.0f32..3.0),
            any_unit(),
            any_unit(),
        )
            .prop_map(|(w, (a, b, c), ax, ay)| NdfLobe {
                weight: w,
                frame: Mat3::from_quat(Quat::from_euler(glam::EulerRot::XYZ, a, b, c)),
                alpha: Vec2::new(ax, ay),
            })
    }

    fn any_appearance() -> impl Strategy<Value = VoxelAppearance> {
        (
            proptest::collection::vec(any_lobe(), 0..5),
            any_unit(),
            any_unit(),
            any_unit(),
            any_unit(),
        )
            .prop_map(|(lobes, mean, var, c, m)| VoxelAppearance {
                lobes,
                roughness_mean: mean,
                roughness_variance: var * 0.3,
                moments: Moments::Constant(MaterialMoments {
                    c: Vec3::splat(c),
                    mc: Vec3::splat(c * m),
                    s: 0.04,
                    ms: 0.04 * m,
                    m,
                    f90: 1.0,
                    mf90: m,
                }),
            })
    }

    fn any_dir() -> impl Strategy<Value = Vec3> {
        prop_oneof![
            (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0).prop_map(|(x, y, z)| Vec3::new(x, y, z)),
            Just(Vec3::Z),
            Just(-Vec3::Z),
            Just(Vec3::ZERO),
            Just(Vec3::new(1.0, 0.0, 1e-7)),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]

        /// Flat and fibre lobes (roughness 0), roughness 1, NaN parameters, zero weights,
        /// ω_i = ±ω_o, zero vectors: no NaN or infinity leaves eval, pdf or sample.
        #[test]
        fn absdf_is_finite(app in any_appearance(), wi in any_dir(), wo in any_dir(), u in (0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0)) {
            let before = non_finite_count();
            let a = Absdf::new(&app, Tables::embedded());
            let (f, p) = a.eval_pdf(wi, wo);
            prop_assert!(f.is_finite() && f.min_element() >= 0.0 && p.is_finite() && p >= 0.0);
            prop_assert!(a.eval(wo, wo).is_finite() && a.eval(-wo, wo).is_finite());
            if let Some(s) = a.sample(wo, u.0, Vec2::new(u.1, u.2)) {
                prop_assert!(s.wi.is_finite() && s.value.is_finite() && s.pdf.is_finite() && s.pdf > 0.0);
            }
            prop_assert_eq!(non_finite_count(), before);
        }
    }
}
