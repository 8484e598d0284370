//! Piecewise-constant distributions on [0, 1] and [0, 1]², sampled by inversion (pbrt-v4's
//! `PiecewiseConstant1D/2D`). Used for environment-map importance sampling.

use glam::Vec2;

/// A piecewise-constant density on [0, 1] with `n` equal cells.
#[derive(Clone, Debug)]
pub struct Distribution1D {
    func: Vec<f32>,
    cdf: Vec<f32>,
    integral: f32,
}

impl Distribution1D {
    /// Builds from non-negative cell weights; negative or non-finite weights count as zero. An
    /// all-zero function becomes uniform, so sampling never fails.
    pub fn new(weights: &[f32]) -> Self {
        let n = weights.len().max(1);
        let mut func: Vec<f32> = weights
            .iter()
            .map(|&w| if w.is_finite() && w > 0.0 { w } else { 0.0 })
            .collect();
        if func.is_empty() {
            func.push(0.0);
        }
        let mut cdf = vec![0.0f32; n + 1];
        let mut acc = 0.0f64;
        for i in 0..n {
            acc += func[i] as f64 / n as f64;
            cdf[i + 1] = acc as f32;
        }
        let mut integral = acc as f32;
        if !(integral > 0.0) {
            func.iter_mut().for_each(|f| *f = 1.0);
            for (i, c) in cdf.iter_mut().enumerate() {
                *c = i as f32 / n as f32;
            }
            integral = 1.0;
        } else {
            for c in cdf.iter_mut() {
                *c /= integral;
            }
        }
        cdf[n] = 1.0;
        Distribution1D {
            func,
            cdf,
            integral,
        }
    }

    /// Number of bins.
    pub fn len(&self) -> usize {
        self.func.len()
    }

    /// Whether it has no bin.
    pub fn is_empty(&self) -> bool {
        self.func.is_empty()
    }

    /// Integral of the (unnormalised) function over [0, 1].
    pub fn integral(&self) -> f32 {
        self.integral
    }

    /// Samples x in [0, 1); returns (x, pdf(x), cell index).
    pub fn sample(&self, u: f32) -> (f32, f32, usize) {
        let n = self.func.len();
        // Largest i with cdf[i] <= u.
        let i = match self.cdf.partition_point(|&c| c <= u) {
            0 => 0,
            k => (k - 1).min(n - 1),
        };
        let width = self.cdf[i + 1] - self.cdf[i];
        let du = if width > 0.0 {
            (u - self.cdf[i]) / width
        } else {
            0.5
        };
        let x = ((i as f32 + du.clamp(0.0, 1.0)) / n as f32).min(1.0 - f32::EPSILON);
        (x, self.func[i] / self.integral, i)
    }

    /// Density at x.
    pub fn pdf(&self, x: f32) -> f32 {
        let n = self.func.len();
        let i = ((x * n as f32) as usize).min(n - 1);
        self.func[i] / self.integral
    }

    /// The `u` that [`Self::sample`] maps to x (where the density is non-zero).
    pub fn invert(&self, x: f32) -> f32 {
        let n = self.func.len();
        let xf = x.clamp(0.0, 1.0) * n as f32;
        let i = (xf as usize).min(n - 1);
        let t = xf - i as f32;
        self.cdf[i] + t * (self.cdf[i + 1] - self.cdf[i])
    }
}

/// A piecewise-constant density on [0, 1]² from a row-major `width × height` grid of weights:
/// a marginal over rows and one conditional per row.
#[derive(Clone, Debug)]
pub struct Distribution2D {
    conditional: Vec<Distribution1D>,
    marginal: Distribution1D,
}

impl Distribution2D {
    /// The density of the `width × height` grid of non-negative `weights` (row-major).
    pub fn new(weights: &[f32], width: usize, height: usize) -> Self {
        assert_eq!(weights.len(), width * height, "weight grid size");
        let conditional: Vec<Distribution1D> = (0..height)
            .map(|y| Distribution1D::new(&weights[y * width..(y + 1) * width]))
            .collect();
        let row_mass: Vec<f32> = (0..height)
            .map(|y| {
                weights[y * width..(y + 1) * width]
                    .iter()
                    .map(|&w| if w.is_finite() && w > 0.0 { w } else { 0.0 })
                    .sum::<f32>()
                    / width as f32
            })
            .collect();
        Distribution2D {
            conditional,
            marginal: Distribution1D::new(&row_mass),
        }
    }

    /// Samples (x, y) in [0, 1)²; returns the point and its density.
    pub fn sample(&self, u: Vec2) -> (Vec2, f32) {
        let (y, pdf_y, row) = self.marginal.sample(u.y);
        let (x, pdf_x, _) = self.conditional[row].sample(u.x);
        (Vec2::new(x, y), pdf_x * pdf_y)
    }

    /// Density at p.
    pub fn pdf(&self, p: Vec2) -> f32 {
        let h = self.conditional.len();
        let row = ((p.y * h as f32) as usize).min(h - 1);
        self.marginal.pdf(p.y) * self.conditional[row].pdf(p.x)
    }

    /// The `u` that [`Self::sample`] maps to p.
    pub fn invert(&self, p: Vec2) -> Vec2 {
        let h = self.conditional.len();
        let row = ((p.y * h as f32) as usize).min(h - 1);
        Vec2::new(self.conditional[row].invert(p.x), self.marginal.invert(p.y))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_d_sample_pdf_invert() {
        let d = Distribution1D::new(&[1.0, 0.0, 3.0, 4.0]);
        assert!((d.integral() - 2.0).abs() < 1e-6);
        for k in 0..100 {
            let u = (k as f32 + 0.5) / 100.0;
            let (x, pdf, i) = d.sample(u);
            assert!(i != 1, "zero cell sampled");
            assert!((pdf - d.pdf(x)).abs() < 1e-5);
            assert!((d.invert(x) - u).abs() < 1e-4, "{u} {x}");
        }
        // Empirical histogram against the pdf.
        let mut counts = [0usize; 4];
        for k in 0..10_000 {
            counts[d.sample((k as f32 + 0.5) / 10_000.0).2] += 1;
        }
        assert_eq!(counts, [1250, 0, 3750, 5000]);
    }

    #[test]
    fn all_zero_becomes_uniform() {
        let d = Distribution1D::new(&[0.0, f32::NAN, -1.0]);
        let (x, pdf, _) = d.sample(0.5);
        assert!((x - 0.5).abs() < 1e-5 && (pdf - 1.0).abs() < 1e-6);
    }

    #[test]
    fn two_d_round_trip() {
        let w: Vec<f32> = (0..12).map(|i| (i % 5) as f32).collect();
        let d = Distribution2D::new(&w, 4, 3);
        for i in 0..20 {
            for j in 0..20 {
                let u = Vec2::new((i as f32 + 0.5) / 20.0, (j as f32 + 0.5) / 20.0);
                let (p, pdf) = d.sample(u);
                assert!(pdf > 0.0);
                assert!((d.pdf(p) - pdf).abs() < 1e-4);
                assert!((d.invert(p) - u).length() < 1e-3, "{u} {p} {}", d.invert(p));
            }
        }
    }
}
