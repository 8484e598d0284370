//! Generation and checking of the tables: ground truths by Monte Carlo or quadrature, and
//! non-linear least-squares fits of the tabulated parameters (Nelder–Mead on the squared error,
//! in an unconstrained parameterisation). Every node is fitted independently with fixed seeds,
//! in parallel, so the output is deterministic whatever the thread count.

use std::f32::consts::PI;

use glam::{Mat3, Vec2, Vec3};
use rayon::prelude::*;

use super::{Table, Tables};
use crate::math::beta::RoughnessDistribution;
use crate::math::frame::Frame;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::microfacet::{ggx_sample_vndf, m5_exact, ALPHA_MIN};
use crate::math::sggx::Sggx;

// ---------------------------------------------------------------------------------------
// Small numerical tools.

/// Minimises `f` with the Nelder–Mead simplex method from `x0` with initial step `step`.
pub fn nelder_mead(f: &dyn Fn(&[f64]) -> f64, x0: &[f64], step: f64, iters: usize) -> Vec<f64> {
    let n = x0.len();
    let mut pts: Vec<Vec<f64>> = vec![x0.to_vec()];
    for i in 0..n {
        let mut p = x0.to_vec();
        p[i] += step;
        pts.push(p);
    }
    let mut vals: Vec<f64> = pts.iter().map(|p| f(p)).collect();
    for _ in 0..iters {
        let mut idx: Vec<usize> = (0..=n).collect();
        idx.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
        pts = idx.iter().map(|&i| pts[i].clone()).collect();
        vals = idx.iter().map(|&i| vals[i]).collect();
        if (vals[n] - vals[0]).abs() <= 1e-12 * (vals[0].abs() + 1e-30) {
            break;
        }
        let centroid: Vec<f64> = (0..n)
            .map(|k| pts[..n].iter().map(|p| p[k]).sum::<f64>() / n as f64)
            .collect();
        let along = |t: f64| -> Vec<f64> {
            (0..n)
                .map(|k| centroid[k] + t * (pts[n][k] - centroid[k]))
                .collect()
        };
        let xr = along(-1.0);
        let fr = f(&xr);
        if fr < vals[0] {
            let xe = along(-2.0);
            let fe = f(&xe);
            if fe < fr {
                pts[n] = xe;
                vals[n] = fe;
            } else {
                pts[n] = xr;
                vals[n] = fr;
            }
        } else if fr < vals[n - 1] {
            pts[n] = xr;
            vals[n] = fr;
        } else {
            let xc = if fr < vals[n] {
                along(-0.5)
            } else {
                along(0.5)
            };
            let fc = f(&xc);
            if fc < vals[n].min(fr) {
                pts[n] = xc;
                vals[n] = fc;
            } else {
                for i in 1..=n {
                    pts[i] = (0..n)
                        .map(|k| pts[0][k] + 0.5 * (pts[i][k] - pts[0][k]))
                        .collect();
                    vals[i] = f(&pts[i]);
                }
            }
        }
    }
    let best = (0..=n)
        .min_by(|&a, &b| vals[a].total_cmp(&vals[b]))
        .unwrap();
    pts[best].clone()
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn logit(p: f64) -> f64 {
    let p = p.clamp(1e-9, 1.0 - 1e-9);
    (p / (1.0 - p)).ln()
}

// ---------------------------------------------------------------------------------------
// Kernels and ground truths.

/// Isotropic GGX lobe value at polar angle cosine `c` (zero below the horizon).
#[inline]
fn ggx_iso(c: f32, alpha: f32) -> f32 {
    if c <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let t = c * c * (a2 - 1.0) + 1.0;
    a2 / (PI * t * t)
}

/// The normalised SG kernel ĝ(ω; n, κ) = exp(κ(ω·n − 1)) / ∫exp(κ(·−1)).
#[inline]
fn sg_kernel(c: f32, kappa: f32) -> f32 {
    let k = kappa.max(1e-4);
    let norm = 2.0 * PI * (-(-2.0 * k).exp_m1()) / k;
    (k * (c - 1.0)).exp() / norm
}

/// Samples the normalised SG kernel around +z; returns (direction, pdf).
fn sample_sg(u: Vec2, kappa: f32) -> (Vec3, f32) {
    let k = kappa.max(1e-4);
    let c = (1.0 + (1.0 - u.x * (-(-2.0 * k).exp_m1())).ln() / k).clamp(-1.0, 1.0);
    let s = (1.0 - c * c).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    let d = Vec3::new(s * phi.cos(), s * phi.sin(), c);
    (d, sg_kernel(c, k))
}

/// The isotropic kernel convolved with the SGGX lobes.
#[derive(Clone, Copy, Debug)]
pub enum Kernel {
    /// Normalised SG of sharpness κ (M1).
    Sg(f32),
    /// Normalised GGX lobe of roughness α, D_mic / M5 (M3).
    Ggx(f32),
}

impl Kernel {
    #[inline]
    fn eval(&self, c: f32) -> f32 {
        match *self {
            Kernel::Sg(k) => sg_kernel(c, k),
            Kernel::Ggx(a) => ggx_iso(c, a.clamp(ALPHA_MIN, 1.0)) / m5_exact(a),
        }
    }

    /// Samples n around +z: (n, pdf of this strategy).
    fn sample(&self, u: Vec2) -> (Vec3, f32) {
        match *self {
            Kernel::Sg(k) => sample_sg(u, k),
            Kernel::Ggx(a) => {
                let a = a.clamp(ALPHA_MIN, 1.0);
                let m = ggx_sample_vndf(Vec3::Z, a, a, u);
                (m, ggx_iso(m.z, a) * m.z)
            }
        }
    }

    /// Rough width (GGX-equivalent roughness) of the kernel, for scaling fit grids.
    fn width(&self) -> f32 {
        match *self {
            Kernel::Sg(k) => (1.0 / k.max(0.05)).sqrt().min(1.0),
            Kernel::Ggx(a) => a,
        }
    }
}

/// The unit SGGX lobe (double-sided GGX) of roughness α in the canonical frame.
#[inline]
fn lobe(alpha: Vec2) -> Sggx {
    Sggx::from_frame_roughness(Mat3::IDENTITY, alpha)
}

/// Ground-truth convolution (kernel ⊛ D_sggx(·; I, α))(ω) by Monte Carlo with multiple
/// importance sampling (balance heuristic) between sampling the lobe and sampling the kernel,
/// `n` samples each, with a scrambled Sobol sequence for `seed`.
pub fn convolution_gt(alpha: Vec2, kernel: Kernel, w: Vec3, n: u32, seed: u32) -> f32 {
    let d = lobe(alpha);
    let frame = Frame::from_z(w);
    let pdf_lobe = |m: Vec3| 0.5 * m.z.abs() * d.d(m);
    let pdf_kernel = |m: Vec3| match kernel {
        Kernel::Sg(_) => kernel.eval(m.dot(w)),
        Kernel::Ggx(a) => {
            let a = a.clamp(ALPHA_MIN, 1.0);
            let c = m.dot(w);
            ggx_iso(c, a) * c.max(0.0)
        }
    };
    let f = |m: Vec3| kernel.eval(m.dot(w)) * d.d(m);
    let mut acc = 0f64;
    for i in 0..n {
        // Strategy A: the lobe (visible normals from +z give pdf z·D; flip half of them).
        let u = sobol_2d(i, seed);
        let mut m = d.sample_visible(Vec3::Z, Vec2::new(u.x, (u.y * 2.0).fract()));
        if u.y >= 0.5 {
            m = -m;
        }
        let p = pdf_lobe(m) + pdf_kernel(m);
        if p > 0.0 {
            acc += (f(m) / p) as f64;
        }
        // Strategy B: the kernel around ω.
        let (ml, _) = kernel.sample(sobol_2d(i, seed ^ 0x5bd1_e995));
        let m = frame.to_world(ml);
        let p = pdf_lobe(m) + pdf_kernel(m);
        if p > 0.0 {
            acc += (f(m) / p) as f64;
        }
    }
    (acc / n as f64) as f32
}

/// Fit directions for lobe widths (wx, wy): a slope grid scaled to the expected width, plus a
/// coarse grid out to the horizon; weights are solid angles (so the error is an L2 norm over
/// the sphere, concentrated where the lobe is).
fn fit_directions(wx: f32, wy: f32) -> Vec<(Vec3, f32)> {
    let mut out = Vec::new();
    let k = 8;
    let smax = 4.0f32;
    for i in 0..k {
        for j in 0..k {
            let sx = (i as f32 + 0.5) / k as f32 * smax;
            let sy = (j as f32 + 0.5) / k as f32 * smax;
            let v = Vec3::new(sx * wx, sy * wy, 1.0);
            let len = v.length();
            let cos = 1.0 / len;
            // dω = cos³θ dslope_x dslope_y with slope steps (smax/k)·(wx, wy).
            let dw = cos * cos * cos * (smax / k as f32).powi(2) * wx * wy;
            out.push((v / len, dw));
        }
    }
    // Coarse coverage of the whole octant (θ up to 88°).
    for i in 0..6 {
        for j in 0..4 {
            let th = (i as f32 + 0.5) / 6.0 * 1.535;
            let ph = (j as f32 + 0.5) / 4.0 * PI / 2.0;
            let dw = th.sin() * (1.535 / 6.0) * (PI / 8.0);
            out.push((
                Vec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()),
                dw,
            ));
        }
    }
    out
}

/// Fits `scale · D_sggx(·; α+)` to (αx, αy) ⊛ kernel: α+ by Nelder–Mead, the scale in closed
/// form (linear least squares) for each α+. Returns (α+, scale, weighted RMS error, RMS of the
/// ground truth).
///
/// The scale is a third channel the paper's two-channel tables do not have: a normalised kernel
/// preserves the lobe's mass ∫D, while a unit SGGX lobe's mass grows with its roughness (from 2
/// to 4), so α+ alone cannot match both shape and mass of wide convolutions (measured: 36%
/// relative error at α = 0.3, κ = 3 without it, 2% with it).
pub fn fit_convolution(
    alpha: Vec2,
    kernel: Kernel,
    samples: u32,
    seed: u32,
) -> (Vec2, f32, f32, f32) {
    let kw = kernel.width();
    let wx = (alpha.x * alpha.x + kw * kw).sqrt().min(1.0);
    let wy = (alpha.y * alpha.y + kw * kw).sqrt().min(1.0);
    let dirs = fit_directions(wx, wy);
    let gt: Vec<f32> = dirs
        .iter()
        .enumerate()
        .map(|(k, (w, _))| {
            convolution_gt(
                alpha,
                kernel,
                *w,
                samples,
                seed.wrapping_add(k as u32 * 7919),
            )
        })
        .collect();
    let wsum: f64 = dirs.iter().map(|d| d.1 as f64).sum();
    // Optimal scale and error for a given α+.
    let solve = |a: Vec2| -> (f64, f64) {
        let l = lobe(a);
        let (mut gd, mut dd) = (0f64, 0f64);
        let vals: Vec<f64> = dirs.iter().map(|(w, _)| l.d(*w) as f64).collect();
        for ((v, (_, dw)), g) in vals.iter().zip(&dirs).zip(&gt) {
            gd += *dw as f64 * v * *g as f64;
            dd += *dw as f64 * v * v;
        }
        let sc = if dd > 0.0 { (gd / dd).max(0.0) } else { 1.0 };
        let e = vals
            .iter()
            .zip(&dirs)
            .zip(&gt)
            .map(|((v, (_, dw)), g)| *dw as f64 * (sc * v - *g as f64).powi(2))
            .sum::<f64>()
            / wsum;
        (sc, e)
    };
    let to_alpha = |p: &[f64]| {
        Vec2::new(p[0].exp() as f32, p[1].exp() as f32).clamp(Vec2::splat(ALPHA_MIN), Vec2::ONE)
    };
    let best = nelder_mead(
        &|p| solve(to_alpha(p)).1,
        &[(wx as f64).ln(), (wy as f64).ln()],
        0.3,
        200,
    );
    let a = to_alpha(&best);
    let (sc, e) = solve(a);
    let gt_rms = (dirs
        .iter()
        .zip(&gt)
        .map(|((_, dw), g)| *dw as f64 * (*g as f64).powi(2))
        .sum::<f64>()
        / wsum)
        .sqrt();
    (a, sc as f32, e.sqrt() as f32, gt_rms as f32)
}

// ---------------------------------------------------------------------------------------
// M2: the aggregated microfacet distribution (Eq. 18, 19).

/// Maps M2's parameters (μ, ν) to a roughness distribution (ν = σ²/(μ(1−μ))).
pub fn m2_distribution(mu: f32, nu: f32) -> RoughnessDistribution {
    RoughnessDistribution::from_moments(mu, nu * mu * (1.0 - mu))
}

/// Cumulative distribution of the polar angle of GGX normals under projected-area measure
/// (D cos): P(θ_m < θ) = tan²θ / (α² + tan²θ), as a function of t = tan θ.
#[inline]
fn ggx_cdf(t: f32, alpha: f32) -> f32 {
    let t2 = t * t;
    t2 / (alpha * alpha + t2)
}

/// tan θ grid for M2, log-spaced over every roughness scale.
fn tan_grid() -> Vec<f32> {
    (0..64)
        .map(|i| 10f32.powf(-4.0 + 7.0 * (i as f32 + 0.5) / 64.0))
        .collect()
}

/// The aggregated distribution's CDF on `ts` (quadrature over 4096 roughness values).
pub fn aggregated_cdf(dist: &RoughnessDistribution, ts: &[f32]) -> Vec<f32> {
    match *dist {
        RoughnessDistribution::Constant(a) => ts
            .iter()
            .map(|&t| ggx_cdf(t, a.clamp(ALPHA_MIN, 1.0)))
            .collect(),
        RoughnessDistribution::Beta { .. } => {
            let n = 4096;
            let alphas: Vec<(f32, f32)> = (0..n)
                .map(|i| {
                    let a = (i as f32 + 0.5) / n as f32;
                    (a.max(ALPHA_MIN), dist.pdf(a))
                })
                .collect();
            let wsum: f64 = alphas.iter().map(|x| x.1 as f64).sum::<f64>().max(1e-30);
            ts.iter()
                .map(|&t| {
                    (alphas
                        .iter()
                        .map(|(a, w)| *w as f64 * ggx_cdf(t, *a) as f64)
                        .sum::<f64>()
                        / wsum) as f32
                })
                .collect()
        }
    }
}

/// Fits (m1, α1, α2) of Eq. 19 for (μ, ν). The fit matches the distribution of microfacet
/// angles (the CDF of D cos, closed form for GGX, on a log grid of slopes), which weighs every
/// roughness scale alike; an L2 fit of D itself is dominated by the peak of the sharpest lobes
/// (for U-shaped betas D̂(0) diverges). Returns the fit and its RMS CDF error.
pub fn fit_m2(mu: f32, nu: f32) -> ([f32; 3], f32) {
    let dist = m2_distribution(mu, nu);
    let sd = dist.variance().sqrt();
    let ts = tan_grid();
    let target = aggregated_cdf(&dist, &ts);
    let params = |p: &[f64]| -> [f32; 3] {
        let a1 = (ALPHA_MIN as f64 * (1.0 / ALPHA_MIN as f64).powf(sigmoid(p[1]))) as f32;
        let a2 = (ALPHA_MIN as f64 * (1.0 / ALPHA_MIN as f64).powf(sigmoid(p[2]))) as f32;
        let m1 = sigmoid(p[0]) as f32;
        if a1 <= a2 {
            [m1, a1, a2]
        } else {
            [1.0 - m1, a2, a1]
        }
    };
    let err = |q: [f32; 3]| -> f64 {
        ts.iter()
            .zip(&target)
            .map(|(&t, g)| {
                ((q[0] * ggx_cdf(t, q[1]) + (1.0 - q[0]) * ggx_cdf(t, q[2]) - g) as f64).powi(2)
            })
            .sum::<f64>()
            / ts.len() as f64
    };
    let inv =
        |a: f32| logit((a.clamp(ALPHA_MIN, 1.0) as f64).ln() / (1.0 / ALPHA_MIN as f64).ln() + 1.0);
    let x0 = [0.0, inv((mu - sd).max(ALPHA_MIN)), inv((mu + sd).min(1.0))];
    let best = nelder_mead(&|p| err(params(p)), &x0, 0.5, 600);
    let q = params(&best);
    (q, err(q).sqrt() as f32)
}

// ---------------------------------------------------------------------------------------
// M4: the LTC of the normalised GGX lobe.

/// The isotropic LTC of the clamped cosine with M⁻¹ = diag(1/s, 1/s, 1): its density at polar
/// cosine c is c · D_ggx(c; s).
#[inline]
pub fn ltc_density(c: f32, s: f32) -> f32 {
    c.max(0.0) * ggx_iso(c, s)
}

/// CDF in θ of the normalised GGX lobe D/M5 (no cosine), closed form: with k = α² − 1 = −q²,
/// ∫ dt/(1 + k t²)² = t/(2(1 + k t²)) + atanh(q t)/(2q), so P(θ < T) = 2α²[G(1) − G(cos T)]/M5.
pub fn ggx_lobe_cdf(tan_t: f32, alpha: f32) -> f32 {
    let a = alpha.clamp(ALPHA_MIN, 1.0) as f64;
    let q = (1.0 - a * a).max(0.0).sqrt();
    let k = a * a - 1.0;
    let g = |t: f64| {
        let at = if q < 1e-6 { t } else { (q * t).atanh() / q };
        t / (2.0 * (1.0 + k * t * t)) + 0.5 * at
    };
    let c = 1.0 / (1.0 + (tan_t as f64).powi(2)).sqrt();
    (2.0 * a * a * (g(1.0) - g(c)) / m5_exact(alpha) as f64) as f32
}

/// Fits the LTC scale s for roughness α by matching the CDF in θ of the LTC density
/// (tan²θ / (s² + tan²θ)) to that of D/M5 on a log grid of slopes (golden-section search on
/// ln s). Returns (1/s, RMS CDF error).
pub fn fit_m4(alpha: f32) -> (f32, f32) {
    let a = alpha.clamp(ALPHA_MIN, 1.0);
    let ts = tan_grid();
    let target: Vec<f32> = ts.iter().map(|&t| ggx_lobe_cdf(t, a)).collect();
    let err = |s: f32| -> f64 {
        ts.iter()
            .zip(&target)
            .map(|(&t, g)| ((ggx_cdf(t, s) - g) as f64).powi(2))
            .sum::<f64>()
            / ts.len() as f64
    };
    let (mut lo, mut hi) = ((a as f64 * 0.2).ln(), (a as f64 * 5.0).ln());
    let g = 0.618_033_988_75;
    for _ in 0..80 {
        let m1 = hi - g * (hi - lo);
        let m2 = lo + g * (hi - lo);
        if err(m1.exp() as f32) < err(m2.exp() as f32) {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let s = (0.5 * (lo + hi)).exp() as f32;
    (1.0 / s, err(s).sqrt() as f32)
}

// ---------------------------------------------------------------------------------------
// Building and checking.

/// Settings of the table build.
#[derive(Clone, Copy, Debug)]
pub struct BuildSettings {
    /// Monte Carlo samples per strategy for each ground-truth direction of M1 and M3.
    pub samples: u32,
    /// Resolution of M3 per axis (the paper's 50).
    pub m3_res: u32,
    /// Resolution of M1 per axis (the paper's 20).
    pub m1_res: u32,
}

impl Default for BuildSettings {
    fn default() -> Self {
        BuildSettings {
            samples: 128,
            m3_res: 50,
            m1_res: 20,
        }
    }
}

/// Domain of κ in M1: the product of two clamped-cosine SGs has κ = λ|ω_i + ω_o| ≤ 2λ.
pub const KAPPA_MAX: f32 = 2.0 * crate::math::sg::COSINE_SHARPNESS;

fn fill_convolution(
    t: &mut Table,
    kernel_of: impl Fn(f32) -> Kernel + Sync,
    samples: u32,
    progress: &crate::util::StageCounter,
) {
    let nodes: Vec<Vec<f32>> = (0..t.node_count()).map(|k| t.node_params(k)).collect();
    let fitted: Vec<(Vec2, f32)> = nodes
        .par_iter()
        .enumerate()
        .map(|(k, p)| {
            // Symmetry: (αx, αy) and (αy, αx) swap channels; fit only αx ≤ αy.
            let (ax, ay) = (p[0].min(p[1]), p[0].max(p[1]));
            let (a, sc, _, _) =
                fit_convolution(Vec2::new(ax, ay), kernel_of(p[2]), samples, k as u32);
            progress.add(1);
            if p[0] <= p[1] {
                (a, sc)
            } else {
                (Vec2::new(a.y, a.x), sc)
            }
        })
        .collect();
    for (k, (a, sc)) in fitted.into_iter().enumerate() {
        t.data[3 * k..3 * k + 3].copy_from_slice(&[a.x, a.y, sc]);
    }
}

/// Builds all five tables.
pub fn build(settings: BuildSettings, progress: crate::util::Progress) -> Tables {
    let ar = (ALPHA_MIN, 1.0);
    let mut m5 = Table::new("M5 integral of D_mic over the sphere", &[256], &[ar], 1);
    let mut m4 = Table::new("M4 inverse LTC scale of the GGX lobe", &[256], &[ar], 1);
    for i in 0..256 {
        let a = m5.node(0, i);
        m5.data[i as usize] = m5_exact(a);
        m4.data[i as usize] = fit_m4(a).0;
    }
    let mut m2 = Table::new(
        "M2 beta roughness (mu, nu) to two GGX lobes (m1, a1, a2)",
        &[32, 32],
        &[ar, (0.0, 0.95)],
        3,
    );
    let fits: Vec<[f32; 3]> = (0..m2.node_count())
        .into_par_iter()
        .map(|k| {
            let p = m2.node_params(k);
            fit_m2(p[0], p[1]).0
        })
        .collect();
    for (k, q) in fits.into_iter().enumerate() {
        m2.data[3 * k..3 * k + 3].copy_from_slice(&q);
    }
    let r1 = settings.m1_res;
    let mut m1 = Table::new(
        "M1 SGGX conv SG (ax, ay, kappa) to alpha+",
        &[r1, r1, r1],
        &[ar, ar, (0.0, KAPPA_MAX)],
        3,
    );
    let r3 = settings.m3_res;
    let mut m3 = Table::new(
        "M3 SGGX conv GGX (ax, ay, alpha) to alpha+",
        &[r3, r3, r3],
        &[ar, ar, ar],
        3,
    );
    let bar = crate::util::StageCounter::new(
        progress,
        "tables",
        (m1.node_count() + m3.node_count()) as u64,
    );
    fill_convolution(&mut m1, Kernel::Sg, settings.samples, &bar);
    fill_convolution(&mut m3, Kernel::Ggx, settings.samples, &bar);
    Tables::new(m1, m2, m3, m4, m5)
}

/// One table's fit error against fresh ground truth at random parameters (off the nodes, so
/// interpolation error is included).
#[derive(Clone, Debug, serde::Serialize)]
pub struct CheckResult {
    /// The table checked (M1–M5).
    pub table: String,
    /// What `rmse` measures (best 0).
    pub metric: String,
    /// Random parameter points checked.
    pub points: usize,
    /// RMS over the points of the per-point error.
    pub rmse: f32,
    /// Largest per-point error.
    pub worst: f32,
}

/// Checks every table against fresh ground truth (`points` random parameter points each).
pub fn check(tables: &Tables, points: usize, samples: u32) -> Vec<CheckResult> {
    let mut out = Vec::new();
    let rnd = |i: usize, d: u32| sobol_2d(i as u32, 1000 + d);
    // M5: against Monte Carlo ∫ D over the hemisphere (cosine-weighted importance sampling).
    let errs: Vec<f32> = (0..points)
        .into_par_iter()
        .map(|i| {
            let a = ALPHA_MIN + (1.0 - ALPHA_MIN) * rnd(i, 1).x;
            let n = 1 << 16;
            let mut acc = 0f64;
            for k in 0..n {
                let m = ggx_sample_vndf(Vec3::Z, a, a, sobol_2d(k, i as u32));
                acc += 1.0 / m.z.max(1e-6) as f64; // D / (D cos)
            }
            let mc = (acc / n as f64) as f32;
            (tables.m5.lookup1(&[a]) - mc).abs() / mc
        })
        .collect();
    out.push(summarise("M5", &errs));
    // M4: the LTC's CDF in θ against the normalised lobe's, by Monte Carlo (the lobe sampled
    // by inverting its closed-form CDF would be circular, so: cosine-weighted GGX samples
    // reweighted by 1/(cos M5)).
    let ts = tan_grid();
    let errs: Vec<f32> = (0..points)
        .into_par_iter()
        .map(|i| {
            let a = ALPHA_MIN + (1.0 - ALPHA_MIN) * rnd(i, 2).x;
            let s = 1.0 / tables.m4.lookup1(&[a]);
            let n = 1 << 15;
            let mut hist = vec![0f64; ts.len()];
            let mut total = 0f64;
            for k in 0..n {
                let m = ggx_sample_vndf(Vec3::Z, a, a, sobol_2d(k, 77 + i as u32));
                let w = 1.0 / m.z.max(1e-6) as f64;
                total += w;
                let tm = (1.0 - m.z * m.z).max(0.0).sqrt() / m.z.max(1e-6);
                let j = ts.partition_point(|&t| t < tm);
                if j < ts.len() {
                    hist[j] += w;
                }
            }
            let mut acc = 0f64;
            let mut e = 0f64;
            for (j, &t) in ts.iter().enumerate() {
                acc += hist[j];
                e += ((acc / total) as f32 - ggx_cdf(t, s)).powi(2) as f64;
            }
            (e / ts.len() as f64).sqrt() as f32
        })
        .collect();
    out.push(summarise("M4", &errs));
    // M2: the two-lobe mixture against the aggregated distribution (RMS error of the CDF of
    // microfacet angles, absolute, in [0, 1]).
    let ts = tan_grid();
    let errs: Vec<f32> = (0..points)
        .into_par_iter()
        .map(|i| {
            let p = rnd(i, 3);
            let (mu, nu) = (ALPHA_MIN + (1.0 - ALPHA_MIN) * p.x, 0.95 * p.y);
            let mut q = [0f32; 3];
            tables.m2.lookup_into(&[mu, nu], &mut q);
            let gt = aggregated_cdf(&m2_distribution(mu, nu), &ts);
            let e: f64 = ts
                .iter()
                .zip(&gt)
                .map(|(&t, g)| {
                    ((q[0] * ggx_cdf(t, q[1]) + (1.0 - q[0]) * ggx_cdf(t, q[2]) - g) as f64).powi(2)
                })
                .sum::<f64>()
                / ts.len() as f64;
            e.sqrt() as f32
        })
        .collect();
    out.push(summarise("M2", &errs));
    for (name, table, kernel_of) in [
        (
            "M1",
            &tables.m1,
            (|x: f32| Kernel::Sg(x * KAPPA_MAX)) as fn(f32) -> Kernel,
        ),
        (
            "M3",
            &tables.m3,
            (|x: f32| Kernel::Ggx(ALPHA_MIN + (1.0 - ALPHA_MIN) * x)) as fn(f32) -> Kernel,
        ),
    ] {
        let errs: Vec<f32> = (0..points)
            .into_par_iter()
            .map(|i| {
                let p = rnd(i, 4);
                let q = rnd(i, 5);
                let alpha = Vec2::new(
                    ALPHA_MIN + (1.0 - ALPHA_MIN) * p.x,
                    ALPHA_MIN + (1.0 - ALPHA_MIN) * p.y,
                );
                let kernel = kernel_of(q.x);
                let kp = match kernel {
                    Kernel::Sg(k) => k,
                    Kernel::Ggx(a) => a,
                };
                let mut o = [0f32; 3];
                table.lookup_into(&[alpha.x, alpha.y, kp], &mut o);
                let fitted = lobe(Vec2::new(o[0], o[1]));
                let sc = o[2];
                let kw = kernel.width();
                let dirs = fit_directions(
                    (alpha.x.powi(2) + kw * kw).sqrt().min(1.0),
                    (alpha.y.powi(2) + kw * kw).sqrt().min(1.0),
                );
                let (mut e, mut n) = (0f64, 0f64);
                for (k, (w, dw)) in dirs.iter().enumerate() {
                    let g =
                        convolution_gt(alpha, kernel, *w, samples, 0xABCD + (i * 131 + k) as u32);
                    e += *dw as f64 * ((sc * fitted.d(*w) - g) as f64).powi(2);
                    n += *dw as f64 * (g as f64).powi(2);
                }
                (e / n).sqrt() as f32
            })
            .collect();
        out.push(summarise(name, &errs));
    }
    out
}

fn summarise(name: &str, errs: &[f32]) -> CheckResult {
    let rms =
        (errs.iter().map(|e| (*e as f64).powi(2)).sum::<f64>() / errs.len().max(1) as f64).sqrt();
    let metric = match name {
        "M5" => "relative error against Monte Carlo (65k samples)",
        "M4" | "M2" => "RMS error of the CDF of microfacet angles against Monte Carlo / quadrature",
        _ => "L2 error of the fitted convolution relative to the L2 norm of the Monte Carlo ground truth",
    };
    CheckResult {
        table: name.into(),
        metric: metric.into(),
        points: errs.len(),
        rmse: rms as f32,
        worst: errs.iter().cloned().fold(0.0, f32::max),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn m5_closed_form_matches_quadrature() {
        for a in [0.01f32, 0.1, 0.5, 0.9, 1.0] {
            // 2π ∫ D sinθ dθ, midpoint rule on 200k steps.
            let n = 200_000;
            let mut s = 0f64;
            for i in 0..n {
                let t = (i as f64 + 0.5) / n as f64 * std::f64::consts::FRAC_PI_2;
                s += ggx_iso(t.cos() as f32, a) as f64 * t.sin() * std::f64::consts::FRAC_PI_2
                    / n as f64;
            }
            let q = 2.0 * std::f64::consts::PI * s;
            assert!(
                (q - m5_exact(a) as f64).abs() < 2e-3 * q,
                "α={a}: {q} vs {}",
                m5_exact(a)
            );
        }
        assert!((m5_exact(1.0) - 2.0).abs() < 1e-5);
    }

    /// The closed-form lobe CDF against quadrature of D sinθ / M5.
    #[test]
    fn lobe_cdf_matches_quadrature() {
        for a in [0.05f32, 0.4, 1.0] {
            for t_end in [0.05f32, 0.5, 3.0] {
                let th = t_end.atan();
                let n = 100_000;
                let mut s = 0f64;
                for i in 0..n {
                    let t = (i as f64 + 0.5) / n as f64 * th as f64;
                    s += ggx_iso(t.cos() as f32, a) as f64 * t.sin() * th as f64 / n as f64;
                }
                let q = 2.0 * std::f64::consts::PI * s / m5_exact(a) as f64;
                assert!(
                    (q - ggx_lobe_cdf(t_end, a) as f64).abs() < 1e-3,
                    "α={a} t={t_end}: {q} vs {}",
                    ggx_lobe_cdf(t_end, a)
                );
            }
        }
    }

    #[test]
    fn nelder_mead_finds_minimum() {
        let x = nelder_mead(
            &|p| (p[0] - 1.0).powi(2) + 10.0 * (p[1] + 2.0).powi(2),
            &[0.0, 0.0],
            0.5,
            500,
        );
        assert!(
            (x[0] - 1.0).abs() < 1e-4 && (x[1] + 2.0).abs() < 1e-4,
            "{x:?}"
        );
    }

    /// The ground-truth convolution of a wide kernel with a narrow lobe has the kernel's shape,
    /// and a narrow kernel leaves a wide lobe unchanged.
    #[test]
    fn convolution_limits() {
        let narrow = Vec2::splat(0.002);
        for c in [1.0f32, 0.9, 0.6] {
            let w = Vec3::new((1.0 - c * c).sqrt(), 0.0, c);
            let gt = convolution_gt(narrow, Kernel::Ggx(0.5), w, 4096, 3);
            // A double-sided delta lobe has projected area 1 along z: ∫⟨z·m⟩D = 1 with mass 1 on
            // each side, so the convolution is 1 × kernel(w·z) (the lower delta is out of reach).
            let expect = Kernel::Ggx(0.5).eval(c);
            assert!((gt / expect - 1.0).abs() < 0.03, "c={c}: {gt} vs {expect}");
        }
        let wide = Vec2::new(0.6, 0.8);
        let w = Vec3::new(0.3, 0.2, 0.9).normalize();
        let gt = convolution_gt(wide, Kernel::Ggx(0.002), w, 4096, 5);
        let expect = lobe(wide).d(w);
        assert!((gt / expect - 1.0).abs() < 0.03, "{gt} vs {expect}");
    }

    #[test]
    fn fits_are_accurate_at_sample_points() {
        // The paper reports small errors; we require relative L2 below 10% at a few nodes.
        for (alpha, kernel) in [
            (Vec2::new(0.1, 0.4), Kernel::Ggx(0.2)),
            (Vec2::new(0.3, 0.3), Kernel::Sg(3.0)),
            (Vec2::new(0.05, 0.05), Kernel::Ggx(0.05)),
        ] {
            let (a, _, err, norm) = fit_convolution(alpha, kernel, 256, 1);
            assert!(
                err / norm < 0.1,
                "{alpha} {kernel:?}: α+ {a}, rel err {}",
                err / norm
            );
            assert!(
                a.x >= alpha.x * 0.9 && a.y >= alpha.y * 0.9,
                "convolution roughens: {alpha} -> {a}"
            );
        }
        // Unimodal betas fit to 0.5% of the angle CDF; U-shaped ones (a, b < 1, roughness spread
        // over three decades) are the hard case, within 6%.
        for (mu, nu, tol) in [
            (0.5, 0.1, 0.005),
            (0.2, 0.05, 0.005),
            (0.6, 0.2, 0.005),
            (0.3, 0.5, 0.06),
            (0.8, 0.9, 0.06),
        ] {
            let (q, e) = fit_m2(mu, nu);
            eprintln!("μ={mu} ν={nu}: {q:?} {e}");
            assert!(e < tol && q[1] <= q[2], "μ={mu} ν={nu}: {q:?} {e}");
        }
        // No variance: one lobe at the mean.
        let (q, e) = fit_m2(0.4, 0.0);
        assert!(
            e < 1e-3 && (q[0] * q[1] + (1.0 - q[0]) * q[2] - 0.4).abs() < 0.02,
            "{q:?}"
        );
        for a in [0.01f32, 0.3, 1.0] {
            let (inv_s, e) = fit_m4(a);
            assert!(e < 0.05 && inv_s > 0.0, "α={a}: {inv_s} {e}");
        }
    }
}

#[cfg(test)]
mod determinism {
    use super::*;

    /// The same settings give the same bytes, whatever the thread count.
    #[test]
    fn build_is_deterministic() {
        let s = BuildSettings {
            samples: 16,
            m3_res: 3,
            m1_res: 2,
        };
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| build(s, &crate::util::no_progress).to_bytes());
        let two = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap()
            .install(|| build(s, &crate::util::no_progress).to_bytes());
        assert_eq!(one, two);
    }
}

/// What `aggtool tables check` reports: each table's fit error.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CheckReport {
    /// Per table.
    pub tables: Vec<CheckResult>,
}

/// Settings of the table check (`aggtool tables check`).
#[derive(Clone, Copy, Debug)]
pub struct CheckSettings {
    /// Random parameter points per table.
    pub points: usize,
    /// Monte Carlo samples per strategy per ground-truth direction.
    pub samples: u32,
}

impl Default for CheckSettings {
    fn default() -> Self {
        CheckSettings {
            points: 64,
            samples: 512,
        }
    }
}

/// Checks the tables of `file` (the embedded ones when `None`) as [`check`] does.
pub fn check_file(
    file: Option<&std::path::Path>,
    settings: CheckSettings,
) -> anyhow::Result<CheckReport> {
    use anyhow::Context;
    let owned;
    let t = match file {
        Some(f) => {
            let bytes = std::fs::read(f).with_context(|| format!("cannot read {}", f.display()))?;
            owned = Tables::from_bytes(&bytes).with_context(|| f.display().to_string())?;
            &owned
        }
        None => Tables::embedded(),
    };
    Ok(CheckReport {
        tables: check(t, settings.points, settings.samples),
    })
}

impl std::fmt::Display for CheckReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:<6} {:>7} {:>9} {:>9}  metric",
            "table", "points", "RMSE", "worst"
        )?;
        for c in &self.tables {
            write!(
                f,
                "\n{:<6} {:>7} {:>9.4} {:>9.4}  {}",
                c.table, c.points, c.rmse, c.worst, c.metric
            )?;
        }
        Ok(())
    }
}

/// What `aggtool tables build` reports: the file written.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BuildReport {
    /// The table file.
    pub output: String,
    /// Its size.
    pub bytes: usize,
    /// Seconds of the fit.
    pub seconds: f64,
}

/// Fits every table ([`build`]) and writes the table file `output` atomically.
pub fn build_file(
    settings: BuildSettings,
    output: &std::path::Path,
    progress: crate::util::Progress,
) -> anyhow::Result<BuildReport> {
    let t0 = std::time::Instant::now();
    let bytes = build(settings, progress).to_bytes();
    crate::util::write_bytes_atomic(output, &bytes).map_err(crate::report::output)?;
    Ok(BuildReport {
        output: output.display().to_string(),
        bytes: bytes.len(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

impl std::fmt::Display for BuildReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "output: {} ({} bytes) in {:.1} s",
            self.output, self.bytes, self.seconds
        )
    }
}
