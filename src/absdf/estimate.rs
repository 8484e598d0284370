//! Estimating a voxel's [`VoxelAppearance`] from surface samples (paper §7.1): roughness
//! moments, the SGGX mixture of the normals (k-means on double-sided normals with seeds spread
//! apart, k = 1..k_max, the highest likelihood wins), and material moments, constant or
//! directional (Eq. 23, splatted through low-discrepancy warps of the kernels).

use glam::{Mat3, Vec2, Vec3};

use super::{MaterialMoments, Moments, NdfLobe, VoxelAppearance};
use crate::math::frame::Frame;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::microfacet::{ggx_sample_vndf, ALPHA_MIN};
use crate::math::sg::COSINE_SHARPNESS;
use crate::math::sggx::Sggx;
use crate::math::sphere_maps::{equal_area_sphere_to_square, grid_cell};
use crate::scene::SurfaceParams;

/// One surface sample: unit normal, material parameters, area weight.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceSample {
    /// Unit shading normal n of the surface at the sample.
    pub normal: Vec3,
    /// The base material's parameters there (Eq. 11).
    pub params: SurfaceParams,
    /// Its share of the voxel's projected area: the sample's area weight in the estimates of Eq. 7–9.
    pub weight: f32,
}

/// Settings of the estimation.
#[derive(Clone, Copy, Debug)]
pub struct EstimateSettings {
    /// Largest number of SGGX lobes (the paper's k ≤ 4).
    pub max_lobes: usize,
    /// Resolution of the directional-moment grid (0 for constant moments).
    pub moment_res: u32,
    /// Kernel directions splatted per surface sample.
    pub splats: u32,
    /// Store constant moments when the material is uniform over the samples (the result is
    /// the same; off only to measure that).
    pub detect_constant: bool,
}

impl Default for EstimateSettings {
    fn default() -> Self {
        EstimateSettings {
            max_lobes: 4,
            moment_res: 3,
            splats: 32,
            detect_constant: true,
        }
    }
}

/// Normalising mass ∫D of a unit SGGX lobe, approximated by the isotropic closed form at the
/// geometric mean roughness (used only to compare likelihoods between mixtures). The exact
/// mass ([`crate::math::sggx::lobe_shape`]) was tried: it chose three lobes for the curved
/// validation voxel where this chooses two, and that ABSDF was further from Eq. 3 (relative
/// RMSE 0.729 against 0.675; the other cases kept their lobes and figures).
fn lobe_mass(alpha: Vec2) -> f32 {
    2.0 * crate::math::microfacet::m5_exact((alpha.x * alpha.y).sqrt())
}

/// k-means on double-sided normals (distance 1 − (n·c)²), centres by the principal axis of each
/// cluster, seeds by farthest-point selection from the area-weighted mean axis.
fn kmeans_axes(s: &[SurfaceSample], k: usize) -> Vec<usize> {
    let axis_of = |idx: &[usize]| -> Vec3 {
        let mut m = Mat3::ZERO;
        for &i in idx {
            let n = s[i].normal;
            m += Mat3::from_cols(n * n.x, n * n.y, n * n.z) * s[i].weight;
        }
        let (vals, vecs) = crate::math::sggx::symmetric_eigen(m);
        let j = (0..3).max_by(|&a, &b| vals[a].total_cmp(&vals[b])).unwrap();
        vecs.col(j)
    };
    let all: Vec<usize> = (0..s.len()).collect();
    let mut centres = vec![axis_of(&all)];
    while centres.len() < k {
        // The sample farthest from every centre.
        let far = (0..s.len())
            .max_by(|&a, &b| {
                let da = centres
                    .iter()
                    .map(|c| 1.0 - s[a].normal.dot(*c).powi(2))
                    .fold(f32::MAX, f32::min);
                let db = centres
                    .iter()
                    .map(|c| 1.0 - s[b].normal.dot(*c).powi(2))
                    .fold(f32::MAX, f32::min);
                da.total_cmp(&db)
            })
            .unwrap();
        centres.push(s[far].normal);
    }
    let mut assign = vec![0usize; s.len()];
    for _ in 0..20 {
        let mut changed = false;
        for (i, a) in assign.iter_mut().enumerate() {
            let best = (0..k)
                .max_by(|&x, &y| {
                    s[i].normal
                        .dot(centres[x])
                        .abs()
                        .total_cmp(&s[i].normal.dot(centres[y]).abs())
                })
                .unwrap();
            if best != *a {
                *a = best;
                changed = true;
            }
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            let idx: Vec<usize> = (0..s.len()).filter(|&i| assign[i] == c).collect();
            if !idx.is_empty() {
                *centre = axis_of(&idx);
            }
        }
        if !changed {
            break;
        }
    }
    assign
}

/// The SGGX mixture with k lobes and its log-likelihood.
fn mixture(s: &[SurfaceSample], k: usize) -> (Vec<NdfLobe>, f64) {
    let assign = if k == 1 {
        vec![0; s.len()]
    } else {
        kmeans_axes(s, k)
    };
    let total: f32 = s.iter().map(|x| x.weight).sum();
    let mut lobes = Vec::new();
    let mut dists = Vec::new();
    for c in 0..k {
        let idx: Vec<usize> = (0..s.len()).filter(|&i| assign[i] == c).collect();
        let w: f32 = idx.iter().map(|&i| s[i].weight).sum();
        if idx.is_empty() || !(w > 0.0) {
            continue;
        }
        let normals: Vec<Vec3> = idx.iter().map(|&i| s[i].normal).collect();
        let weights: Vec<f32> = idx.iter().map(|&i| s[i].weight).collect();
        let Some(sggx) = Sggx::estimate(&normals, &weights) else {
            continue;
        };
        let (frame, alpha) = sggx.frame_roughness();
        lobes.push(NdfLobe {
            weight: w / total,
            frame,
            alpha,
        });
        dists.push((
            w / total,
            Sggx::from_frame_roughness(frame, alpha),
            lobe_mass(alpha),
        ));
    }
    let ll = s
        .iter()
        .map(|x| {
            let p: f32 = dists.iter().map(|(w, d, m)| w * d.d(x.normal) / m).sum();
            x.weight as f64 * (p.max(1e-30) as f64).ln()
        })
        .sum::<f64>();
    (lobes, ll)
}

/// Whether [`estimate`] uses a sample: a positive finite weight and a finite non-zero normal.
pub fn usable(x: &SurfaceSample) -> bool {
    x.weight > 0.0
        && x.weight.is_finite()
        && x.normal.is_finite()
        && x.normal.length_squared() > 0.0
}

/// Estimates the appearance statistics of a set of surface samples. `None` without a
/// [`usable`] sample.
pub fn estimate(samples: &[SurfaceSample], settings: &EstimateSettings) -> Option<VoxelAppearance> {
    let s: Vec<SurfaceSample> = samples
        .iter()
        .filter(|x| usable(x))
        .map(|x| SurfaceSample {
            normal: x.normal.normalize(),
            ..*x
        })
        .collect();
    if s.is_empty() {
        return None;
    }
    let wsum: f32 = s.iter().map(|x| x.weight).sum();
    // Roughness moments.
    let mean = s.iter().map(|x| x.weight * x.params.alpha).sum::<f32>() / wsum;
    let var = (s
        .iter()
        .map(|x| x.weight * (x.params.alpha - mean).powi(2))
        .sum::<f32>()
        / wsum)
        .max(0.0);
    // Below this the roughness is uniform (one microfacet lobe): store exactly zero, not the
    // rounding noise of the sums.
    let var = if var < crate::math::beta::MIN_VARIANCE {
        0.0
    } else {
        var
    };
    // Normal distribution: k = 1..max, highest likelihood, ties (0.1%) to the fewer lobes.
    let mut best = mixture(&s, 1);
    for k in 2..=settings.max_lobes.min(s.len()) {
        let m = mixture(&s, k);
        if m.1 > best.1 + 1e-3 * best.1.abs() {
            best = m;
        }
    }
    // Material moments.
    let mut constant = MaterialMoments::default();
    for x in &s {
        let p = &x.params;
        constant.add(x.weight, p.base_color, p.metallic, p.specular, p.f90);
    }
    let constant = constant.normalized(wsum);
    let uniform = s.iter().all(|x| {
        let p = &x.params;
        let q = &s[0].params;
        (p.base_color - q.base_color).abs().max_element() < 1e-4
            && (p.metallic - q.metallic).abs() < 1e-4
            && (p.specular - q.specular).abs() < 1e-6
            && (p.f90 - q.f90).abs() < 1e-4
    });
    let moments = if (uniform && settings.detect_constant) || settings.moment_res == 0 {
        Moments::Constant(constant)
    } else {
        directional_moments(&s, settings, constant)
    };
    Some(VoxelAppearance {
        lobes: best.0,
        roughness_mean: mean,
        roughness_variance: var,
        moments,
    })
}

/// Eq. 23 by splatting: each sample's kernel (the clamped-cosine SG for the diffuse part, its
/// microfacet lobe for the specular part), on both sides of the surface, is sampled with a
/// scrambled Sobol sequence and the weights are accumulated per equal-area cell; empty cells
/// take the constant moments.
fn directional_moments(
    s: &[SurfaceSample],
    st: &EstimateSettings,
    fallback: MaterialMoments,
) -> Moments {
    let res = st.moment_res.max(1);
    let cells = (res * res) as usize;
    let mut num_d = vec![MaterialMoments::default(); cells];
    let mut den_d = vec![0f32; cells];
    let mut num_s = vec![MaterialMoments::default(); cells];
    let mut den_s = vec![0f32; cells];
    // The clamped-cosine SG's CDF normaliser 1 − e^(−2κ), the same for every splat (libm's
    // expm1 is an opaque call the compiler does not hoist: 2.4% of a maple bake).
    let kk = COSINE_SHARPNESS;
    let norm = -(-2.0 * kk).exp_m1();
    for (k, x) in s.iter().enumerate() {
        let p = &x.params;
        let w = x.weight / (2 * st.splats) as f32;
        for side in [1.0f32, -1.0] {
            let f = Frame::from_z(x.normal * side);
            for j in 0..st.splats {
                let u = sobol_2d(j, k as u32 * 2 + (side > 0.0) as u32);
                // Diffuse kernel: the clamped-cosine SG around the normal (exact inversion).
                let c = (1.0 + (1.0 - u.x * norm).ln() / kk).clamp(-1.0, 1.0);
                let sn = (1.0 - c * c).max(0.0).sqrt();
                let phi = 2.0 * std::f32::consts::PI * u.y;
                let d = f.to_world(Vec3::new(sn * phi.cos(), sn * phi.sin(), c));
                let cell = grid_cell(equal_area_sphere_to_square(d), res) as usize;
                num_d[cell].add(w, p.base_color, p.metallic, p.specular, p.f90);
                den_d[cell] += w;
                // Specular kernel: the microfacet distribution of the sample's roughness.
                let a = p.alpha.clamp(ALPHA_MIN, 1.0);
                let m = f.to_world(ggx_sample_vndf(Vec3::Z, a, a, u));
                let cell = grid_cell(equal_area_sphere_to_square(m), res) as usize;
                num_s[cell].add(w, p.base_color, p.metallic, p.specular, p.f90);
                den_s[cell] += w;
            }
        }
    }
    let finish = |num: Vec<MaterialMoments>, den: Vec<f32>| -> Vec<MaterialMoments> {
        num.iter()
            .zip(&den)
            .map(|(n, &d)| if d > 0.0 { n.normalized(d) } else { fallback })
            .collect()
    };
    Moments::Directional {
        res,
        diffuse: finish(num_d, den_d),
        specular: finish(num_s, den_s),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(n: Vec3, alpha: f32) -> SurfaceSample {
        SurfaceSample {
            normal: n,
            params: SurfaceParams {
                base_color: Vec3::splat(0.5),
                metallic: 0.0,
                alpha,
                specular: 0.04,
                f90: 1.0,
            },
            weight: 1.0,
        }
    }

    #[test]
    fn flat_voxel_is_one_lobe_with_constant_moments() {
        let s: Vec<_> = (0..50)
            .map(|_| sample(Vec3::new(0.0, 0.6, 0.8), 0.3))
            .collect();
        let v = estimate(&s, &Default::default()).unwrap();
        assert_eq!(v.lobes.len(), 1);
        assert!(matches!(v.moments, Moments::Constant(_)));
        assert!(v.roughness_variance < 1e-9 && (v.roughness_mean - 0.3).abs() < 1e-6);
        assert!(v.lobes[0].frame.col(2).dot(Vec3::new(0.0, 0.6, 0.8)).abs() > 0.999);
    }

    #[test]
    fn two_orientations_give_two_lobes() {
        let mut s: Vec<_> = (0..50).map(|_| sample(Vec3::Z, 0.3)).collect();
        s.extend((0..50).map(|_| sample(Vec3::X, 0.3)));
        let v = estimate(&s, &Default::default()).unwrap();
        assert!(v.lobes.len() >= 2, "{:?}", v.lobes);
        let one = estimate(&s[..1], &Default::default()).unwrap();
        assert_eq!(one.lobes.len(), 1, "a voxel with one sample");
        assert!(estimate(&[], &Default::default()).is_none());
    }
}
