//! The beta distribution of a voxel's roughness (paper §5.1, supplemental Eq. 2): shape
//! parameters from the mean μ and variance σ² of α,
//!
//! ```text
//! a = −μ (σ² + μ² − μ) / σ²,   b = (σ² + μ² − μ)(μ − 1) / σ².
//! ```
//!
//! A beta distribution needs 0 < σ² < μ(1 − μ): larger variances are clamped to 99% of that
//! bound, and a variance below [`MIN_VARIANCE`] (uniform roughness, one sample) is a point
//! mass, reported as [`RoughnessDistribution::Constant`].

/// ln B(a, b) = ln Γ(a) + ln Γ(b) − ln Γ(a + b).
fn ln_beta(a: f64, b: f64) -> f64 {
    use super::special::ln_gamma;
    ln_gamma(a) + ln_gamma(b) - ln_gamma(a + b)
}

/// Variances below this are treated as zero (a single roughness).
pub const MIN_VARIANCE: f32 = 1e-6;

/// The roughness distribution of a voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RoughnessDistribution {
    /// All surfaces have this α.
    Constant(f32),
    /// Beta(a, b) on [0, 1].
    Beta {
        /// Shape parameter a (> 0).
        a: f32,
        /// Shape parameter b (> 0).
        b: f32,
    },
}

impl RoughnessDistribution {
    /// From mean and variance (supplemental Eq. 2), clamped to a valid distribution.
    pub fn from_moments(mean: f32, variance: f32) -> Self {
        let mu = if mean.is_finite() {
            mean.clamp(1e-4, 1.0 - 1e-4)
        } else {
            0.5
        };
        let var = if variance.is_finite() { variance } else { 0.0 };
        if var < MIN_VARIANCE {
            return RoughnessDistribution::Constant(mu);
        }
        let var = var.min(0.99 * mu * (1.0 - mu));
        let k = var + mu * mu - mu; // negative
        RoughnessDistribution::Beta {
            a: -mu * k / var,
            b: k * (mu - 1.0) / var,
        }
    }

    /// Mean roughness μ.
    pub fn mean(&self) -> f32 {
        match *self {
            RoughnessDistribution::Constant(m) => m,
            RoughnessDistribution::Beta { a, b } => a / (a + b),
        }
    }

    /// Variance of the roughness.
    pub fn variance(&self) -> f32 {
        match *self {
            RoughnessDistribution::Constant(_) => 0.0,
            RoughnessDistribution::Beta { a, b } => a * b / ((a + b) * (a + b) * (a + b + 1.0)),
        }
    }

    /// Density at x in (0, 1) (0 for a point mass).
    pub fn pdf(&self, x: f32) -> f32 {
        match *self {
            RoughnessDistribution::Constant(_) => 0.0,
            RoughnessDistribution::Beta { a, b } => {
                if !(x > 0.0 && x < 1.0) {
                    return 0.0;
                }
                let (a, b, x) = (a as f64, b as f64, x as f64);
                let l = (a - 1.0) * x.ln() + (b - 1.0) * (1.0 - x).ln() - ln_beta(a, b);
                super::finite_or_zero(l.exp() as f32)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moments_round_trip() {
        for (m, v) in [(0.3f32, 0.01f32), (0.5, 0.05), (0.9, 0.002), (0.1, 0.0005)] {
            let d = RoughnessDistribution::from_moments(m, v);
            assert!(matches!(d, RoughnessDistribution::Beta { .. }));
            assert!(
                (d.mean() - m).abs() < 1e-5 && (d.variance() - v).abs() < 1e-5 * v.max(1e-3),
                "{d:?}"
            );
            // The pdf integrates to one (midpoint rule, 100k cells).
            let n = 100_000;
            let s: f64 = (0..n)
                .map(|i| d.pdf((i as f32 + 0.5) / n as f32) as f64)
                .sum::<f64>()
                / n as f64;
            assert!((s - 1.0).abs() < 0.01, "{d:?}: {s}");
        }
    }

    #[test]
    fn degenerate_moments() {
        assert_eq!(
            RoughnessDistribution::from_moments(0.4, 0.0),
            RoughnessDistribution::Constant(0.4)
        );
        assert!(matches!(
            RoughnessDistribution::from_moments(f32::NAN, f32::NAN),
            RoughnessDistribution::Constant(_)
        ));
        // Variance above μ(1−μ) is clamped to a valid beta.
        let d = RoughnessDistribution::from_moments(0.5, 1.0);
        match d {
            RoughnessDistribution::Beta { a, b } => assert!(a > 0.0 && b > 0.0),
            _ => panic!(),
        }
        // Roughness 0 and 1 means are clamped inside (0, 1).
        for m in [0.0, 1.0] {
            let d = RoughnessDistribution::from_moments(m, 1e-3);
            assert!(d.mean().is_finite() && d.pdf(0.5).is_finite());
        }
    }
}
