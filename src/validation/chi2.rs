//! One chi-square goodness-of-fit harness for every direction sampler (after Mitsuba 3's
//! `chi2.py`): samples are binned on an equal-area grid over the sphere (cos θ × φ), expected
//! counts come from integrating the claimed pdf over each cell, cells with an expected count
//! under 5 are pooled, and the p-value of Pearson's statistic is compared with a significance
//! level. The harness fails outright on a negative or non-finite pdf, on a pdf integrating above
//! one, and on a sample drawn where the pdf is zero.

use std::f32::consts::PI;

use glam::{Vec2, Vec3};

use crate::math::rng::Pcg32;
use crate::math::special::gamma_q;

/// Outcome of a chi-square test.
#[derive(Clone, Debug)]
pub struct Chi2Result {
    /// Pearson statistic.
    pub statistic: f64,
    /// Degrees of freedom after pooling.
    pub dof: usize,
    /// Probability of a statistic at least this large if the sampler matches the pdf.
    pub p_value: f64,
    /// Integral of the pdf over the sphere (should be ≤ 1, = 1 when no sample can fail).
    pub pdf_integral: f64,
    /// Samples that returned `None`.
    pub failed_samples: usize,
    /// Why the test failed, if it did.
    pub failure: Option<String>,
}

impl Chi2Result {
    /// Passes when no hard failure happened and `p_value >= significance`.
    pub fn passed(&self, significance: f64) -> bool {
        self.failure.is_none() && self.p_value >= significance
    }
}

/// Settings of the test.
#[derive(Clone, Copy, Debug)]
pub struct Chi2Settings {
    /// Bins in cos θ.
    pub theta_bins: usize,
    /// Bins in φ.
    pub phi_bins: usize,
    /// Number of samples.
    pub samples: usize,
    /// Sub-cells per axis when integrating the pdf over a cell (midpoint rule). Smooth pdfs
    /// need ~12; pdfs with jumps inside cells (piecewise-constant maps) need ~100 or the
    /// integration error, not the sampler, fails the test at large sample counts.
    pub integration_res: usize,
    /// Seed of the uniform numbers fed to the sampler.
    pub seed: u64,
}

impl Default for Chi2Settings {
    fn default() -> Self {
        Chi2Settings {
            theta_bins: 20,
            phi_bins: 40,
            samples: 200_000,
            integration_res: 12,
            seed: 1,
        }
    }
}

fn cell_of(d: Vec3, s: &Chi2Settings) -> usize {
    let z = d.z.clamp(-1.0, 1.0);
    let t = (((1.0 - z) * 0.5 * s.theta_bins as f32) as usize).min(s.theta_bins - 1);
    let mut phi = d.y.atan2(d.x);
    if phi < 0.0 {
        phi += 2.0 * PI;
    }
    let p = ((phi / (2.0 * PI) * s.phi_bins as f32) as usize).min(s.phi_bins - 1);
    t * s.phi_bins + p
}

/// Runs the test. `sample` maps a uniform 2D point to a direction (or `None` for a failed
/// sample); `pdf` is the claimed solid-angle density of that sampler.
pub fn chi2_test(
    settings: Chi2Settings,
    mut sample: impl FnMut(Vec2) -> Option<Vec3>,
    pdf: impl Fn(Vec3) -> f32,
) -> Chi2Result {
    let s = settings;
    let ncells = s.theta_bins * s.phi_bins;
    let mut observed = vec![0f64; ncells];
    let mut failed = 0usize;
    let mut failure = None;
    let mut rng = Pcg32::new(s.seed, 0xC412);
    for _ in 0..s.samples {
        match sample(rng.next_2d()) {
            Some(d) if d.is_finite() => {
                let d = d.normalize_or_zero();
                let p = pdf(d);
                if !(p > 0.0) && failure.is_none() {
                    failure = Some(format!("sample {d} drawn where the pdf is {p}"));
                }
                observed[cell_of(d, &s)] += 1.0;
            }
            Some(d) => {
                if failure.is_none() {
                    failure = Some(format!("sampler returned a non-finite direction {d}"));
                }
            }
            None => failed += 1,
        }
    }
    // Integrate the pdf over each equal-area cell (area 4π / ncells) with the midpoint rule in
    // (cos θ, φ), where dω = d(cos θ) dφ.
    let mut expected = vec![0f64; ncells];
    let r = s.integration_res;
    let dz = 2.0 / s.theta_bins as f64;
    let dphi = 2.0 * std::f64::consts::PI / s.phi_bins as f64;
    let mut integral = 0f64;
    for t in 0..s.theta_bins {
        for p in 0..s.phi_bins {
            let mut acc = 0f64;
            for a in 0..r {
                for b in 0..r {
                    let z = 1.0 - (t as f64 + (a as f64 + 0.5) / r as f64) * dz;
                    let phi = (p as f64 + (b as f64 + 0.5) / r as f64) * dphi;
                    let st = (1.0 - z * z).max(0.0).sqrt();
                    let d = Vec3::new((st * phi.cos()) as f32, (st * phi.sin()) as f32, z as f32);
                    let v = pdf(d) as f64;
                    if (!v.is_finite() || v < 0.0) && failure.is_none() {
                        failure = Some(format!("pdf({d}) = {v}"));
                    }
                    acc += v.max(0.0);
                }
            }
            let mass = acc * dz * dphi / (r * r) as f64;
            integral += mass;
            expected[t * s.phi_bins + p] = mass * s.samples as f64;
        }
    }
    if integral > 1.0 + 1e-2 && failure.is_none() {
        failure = Some(format!("pdf integrates to {integral} > 1"));
    }
    // Pool cells with small expectation.
    let mut stat = 0f64;
    let mut dof = 0usize;
    let (mut pool_o, mut pool_e) = (0f64, 0f64);
    for i in 0..ncells {
        if expected[i] < 5.0 {
            pool_o += observed[i];
            pool_e += expected[i];
        } else {
            stat += (observed[i] - expected[i]).powi(2) / expected[i];
            dof += 1;
        }
    }
    // Failed samples are the complement of the pdf's mass.
    pool_o += failed as f64;
    pool_e += (1.0 - integral).max(0.0) * s.samples as f64;
    if pool_e >= 5.0 {
        stat += (pool_o - pool_e).powi(2) / pool_e;
        dof += 1;
    } else if pool_o > 10.0 + 3.0 * pool_e && failure.is_none() {
        failure = Some(format!(
            "{pool_o} samples fell where the pdf expects only {pool_e:.2}"
        ));
    }
    let dof = dof.saturating_sub(1).max(1);
    let p_value = gamma_q(dof as f64 / 2.0, stat / 2.0);
    Chi2Result {
        statistic: stat,
        dof,
        p_value,
        pdf_integral: integral,
        failed_samples: failed,
        failure,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::sampling::*;
    use crate::math::special::ln_gamma;

    #[test]
    fn gamma_q_known_values() {
        // Q(1, x) = e^-x; chi-square with 2 dof at 5.991 has p = 0.05.
        assert!((gamma_q(1.0, 2.0) - (-2.0f64).exp()).abs() < 1e-10);
        assert!((gamma_q(1.0, 5.991 / 2.0) - 0.05).abs() < 1e-3);
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-10);
    }

    #[test]
    fn cosine_hemisphere_passes() {
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(square_to_cosine_hemisphere(u)),
            cosine_hemisphere_pdf,
        );
        assert!(r.passed(0.01), "{r:?}");
    }

    #[test]
    fn uniform_sphere_passes() {
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(square_to_uniform_sphere(u)),
            |_| uniform_sphere_pdf(),
        );
        assert!(r.passed(0.01), "{r:?}");
    }

    /// The harness must reject a sampler whose pdf is wrong: cosine samples claimed uniform.
    #[test]
    fn wrong_pdf_is_rejected() {
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(square_to_cosine_hemisphere(u)),
            |d| if d.z > 0.0 { 1.0 / (2.0 * PI) } else { 0.0 },
        );
        assert!(!r.passed(0.01), "{r:?}");
        // A pdf integrating to 2 fails outright.
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(square_to_uniform_sphere(u)),
            |_| 2.0 * uniform_sphere_pdf(),
        );
        assert!(r.failure.is_some());
        // A sample where the pdf is zero fails outright.
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(square_to_uniform_sphere(u)),
            |d| {
                if d.z > 0.0 {
                    2.0 * uniform_sphere_pdf()
                } else {
                    0.0
                }
            },
        );
        assert!(r.failure.is_some());
    }
}
