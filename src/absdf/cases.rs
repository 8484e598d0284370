//! The validation voxels of the ABSDF (issue: flat, curved, foliage, anisotropic,
//! orientation-varying colour, mixed roughness, metal–dielectric mixture; and a flat leaf
//! beside a twig, whose two lobes differ in mass): synthetic surface
//! samples with known structure, their ground-truth ABSDF (direct integration of Eq. 3 over the
//! samples) and the factored one, compared on grids of directions (plotted as paper Fig. 4's 8×8 lat-long
//! outgoing slices by `eval::plot::plot_slices`).

use std::f32::consts::PI;

use glam::{Vec2, Vec3};

use super::estimate::{estimate, EstimateSettings, SurfaceSample};
use super::{ground_truth, Absdf, VoxelAppearance};
use crate::bsdf::Bsdf;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::sphere_maps::equal_area_square_to_sphere;
use crate::scene::SurfaceParams;
use crate::tables::Tables;

/// Names of the validation cases.
pub const CASES: &[&str] = &[
    "flat",
    "curved",
    "foliage",
    "anisotropic",
    "orientation-color",
    "mixed-roughness",
    "metal-dielectric",
    "leaf-and-twig",
];

fn params(c: Vec3, metallic: f32, alpha: f32) -> SurfaceParams {
    SurfaceParams {
        base_color: c,
        metallic,
        alpha,
        specular: 0.04,
        f90: 1.0,
    }
}

/// A direction in the cap of half-angle `theta_max` around +z from a 2D point (uniform in solid
/// angle).
fn cap(u: Vec2, theta_max: f32) -> Vec3 {
    let z = 1.0 - u.x * (1.0 - theta_max.cos());
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Surface samples of a named case (`n` samples, deterministic).
pub fn case_samples(name: &str, n: u32) -> Option<Vec<SurfaceSample>> {
    let gold = Vec3::new(1.0, 0.78, 0.34);
    let s = |normal: Vec3, p: SurfaceParams| SurfaceSample {
        normal,
        params: p,
        weight: 1.0,
    };
    let v: Vec<SurfaceSample> = (0..n)
        .map(|i| {
            let u = sobol_2d(i, 17);
            match name {
                "flat" => s(Vec3::new(0.0, 0.0, 1.0), params(gold, 1.0, 0.1)),
                "curved" => s(cap(u, 60f32.to_radians()), params(gold, 1.0, 0.05)),
                "foliage" => s(
                    crate::math::sampling::square_to_uniform_sphere(u),
                    params(Vec3::new(0.2, 0.45, 0.1), 0.0, 0.5),
                ),
                "anisotropic" => {
                    let phi = 2.0 * PI * u.x;
                    s(
                        Vec3::new(phi.cos(), phi.sin(), 0.0),
                        params(Vec3::splat(0.9), 1.0, 0.1),
                    )
                }
                "orientation-color" => {
                    let n = cap(u, 70f32.to_radians());
                    let c = if n.x > 0.0 {
                        Vec3::new(0.9, 0.45, 0.05)
                    } else {
                        Vec3::new(0.05, 0.2, 0.9)
                    };
                    s(n, params(c, 0.0, 0.3))
                }
                "mixed-roughness" => {
                    let a = if i % 2 == 0 { 0.05 } else { 0.5 };
                    s(cap(u, 20f32.to_radians()), params(Vec3::splat(0.8), 1.0, a))
                }
                "metal-dielectric" => {
                    let p = if i % 2 == 0 {
                        params(gold, 1.0, 0.2)
                    } else {
                        params(Vec3::splat(0.8), 0.0, 0.2)
                    };
                    s(cap(u, 30f32.to_radians()), p)
                }
                // Half the area a flat green leaf, half a brown twig (normals around a
                // circle): a flat lobe and one rough along one axis, of masses 2 and about π.
                "leaf-and-twig" => {
                    if i % 2 == 0 {
                        s(Vec3::Z, params(Vec3::new(0.2, 0.5, 0.1), 0.0, 0.5))
                    } else {
                        let phi = 2.0 * PI * u.x;
                        s(
                            Vec3::new(phi.cos(), phi.sin(), 0.0),
                            params(Vec3::new(0.4, 0.25, 0.1), 0.0, 0.8),
                        )
                    }
                }
                _ => s(Vec3::Z, params(Vec3::ONE, 0.0, 1.0)),
            }
        })
        .collect();
    CASES.contains(&name).then_some(v)
}

/// Directions on an equal-area grid over the sphere (`res × res`, cell centres), turned by a
/// fixed generic rotation so that no direction lies exactly in a validation voxel's symmetry
/// planes (at exactly grazing ω_o, Eq. 3 is 0/0).
pub fn sphere_grid(res: u32) -> Vec<Vec3> {
    let rot = glam::Quat::from_euler(glam::EulerRot::XYZ, 0.21, 0.37, 0.13);
    (0..res * res)
        .map(|k| {
            rot * equal_area_square_to_sphere(Vec2::new(
                ((k % res) as f32 + 0.5) / res as f32,
                ((k / res) as f32 + 0.5) / res as f32,
            ))
        })
        .collect()
}

/// Comparison of the factored ABSDF with the ground truth on a case.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CaseReport {
    /// The case's name (one of [`CASES`]).
    pub case: String,
    /// SGGX lobes the estimate fitted (Eq. 8).
    pub lobes: usize,
    /// RMSE over (ω_i, ω_o) pairs of an equal-area grid, luminance.
    pub rmse: f32,
    /// RMS of the ground truth on the same pairs (for scale).
    pub gt_rms: f32,
}

/// Estimates the case's appearance, and compares on `res² × res²` direction pairs.
pub fn compare_case(
    name: &str,
    tables: &Tables,
    samples: u32,
    res: u32,
) -> Option<(CaseReport, VoxelAppearance)> {
    let s = case_samples(name, samples)?;
    let app = estimate(&s, &EstimateSettings::default())?;
    let absdf = Absdf::new(&app, tables);
    let gt_samples: Vec<(Vec3, SurfaceParams, f32)> =
        s.iter().map(|x| (x.normal, x.params, x.weight)).collect();
    let dirs = sphere_grid(res);
    let (mut se, mut gs, mut n) = (0f64, 0f64, 0f64);
    for &wo in &dirs {
        for &wi in &dirs {
            let g = crate::math::color::luminance(ground_truth(&gt_samples, wi, wo)) as f64;
            let f = crate::math::color::luminance(absdf.eval(wi, wo)) as f64;
            se += (f - g).powi(2);
            gs += g * g;
            n += 1.0;
        }
    }
    Some((
        CaseReport {
            case: name.into(),
            lobes: app.lobes.len(),
            rmse: (se / n).sqrt() as f32,
            gt_rms: (gs / n).sqrt() as f32,
        },
        app,
    ))
}
