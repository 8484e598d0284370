//! Area-preserving maps between the unit square and the sphere or hemisphere, each with its
//! inverse: Clarberg's equal-area sphere map (used for the 32×32 interior-visibility maps) and
//! the concentric hemisphere map (used for the 64×64 boundary-visibility maps over a face's
//! inward hemisphere).

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4};

use glam::{Vec2, Vec3};

use super::safe_sqrt;
use super::sampling::{concentric_disk_to_square, square_to_concentric_disk};

/// Clarberg 2008, "Fast Equal-Area Mapping of the (Hemi)Sphere using SIMD": the square
/// [0,1]² folds like an octahedron onto the sphere; every cell of a regular grid on the square
/// covers the same solid angle (4π / cells). The centre of the square is +z, its corners −z.
pub fn equal_area_square_to_sphere(p: Vec2) -> Vec3 {
    let u = 2.0 * p.x - 1.0;
    let v = 2.0 * p.y - 1.0;
    let (au, av) = (u.abs(), v.abs());
    // Signed distance from the diagonal |u| + |v| = 1: positive inside (northern hemisphere).
    let sd = 1.0 - (au + av);
    let r = 1.0 - sd.abs();
    // Angle within the quadrant.
    let phi = if r == 0.0 { 1.0 } else { (av - au) / r + 1.0 } * FRAC_PI_4;
    let z = (1.0 - r * r).copysign(sd);
    let s = r * safe_sqrt(2.0 - r * r);
    Vec3::new(phi.cos().copysign(u) * s, phi.sin().copysign(v) * s, z)
}

/// Inverse of [`equal_area_square_to_sphere`].
pub fn equal_area_sphere_to_square(d: Vec3) -> Vec2 {
    let (x, y, z) = (d.x.abs(), d.y.abs(), d.z.abs());
    let r = safe_sqrt(1.0 - z);
    let a = x.max(y);
    let b = if a == 0.0 { 0.0 } else { x.min(y) / a };
    let mut phi = atan01(b) / FRAC_PI_2;
    if x < y {
        phi = 1.0 - phi;
    }
    let mut v = phi * r;
    let mut u = r - v;
    if d.z < 0.0 {
        std::mem::swap(&mut u, &mut v);
        u = 1.0 - u;
        v = 1.0 - v;
    }
    let u = u.copysign(d.x);
    let v = v.copysign(d.y);
    Vec2::new(0.5 * (u + 1.0), 0.5 * (v + 1.0))
}

/// atan(b) for b in [0, 1] by an odd polynomial of degree 11 (least squares on Chebyshev
/// nodes, error below 2e-6 rad, tested): the map's one transcendental, a third of an AIV
/// look-up with libm's atanf.
#[inline]
fn atan01(b: f32) -> f32 {
    let b2 = b * b;
    b * (0.999_979_8
        + b2 * (-0.332_655_5
            + b2 * (0.193_670_3 + b2 * (-0.116_651_1 + b2 * (0.052_823_5 + b2 * -0.011_770_5)))))
}

/// Density of a uniform point of the square mapped by [`equal_area_square_to_sphere`]: 1/(4π).
pub fn equal_area_sphere_pdf() -> f32 {
    1.0 / (4.0 * std::f32::consts::PI)
}

/// Concentric equal-area map from the square to the +z hemisphere (Shirley–Chiu disk, lifted
/// with z = 1 − r²).
pub fn concentric_square_to_hemisphere(p: Vec2) -> Vec3 {
    let d = square_to_concentric_disk(p);
    let r2 = d.length_squared();
    let s = safe_sqrt(2.0 - r2);
    Vec3::new(d.x * s, d.y * s, 1.0 - r2)
}

/// Inverse of [`concentric_square_to_hemisphere`] (directions below the horizon are folded up).
pub fn concentric_hemisphere_to_square(w: Vec3) -> Vec2 {
    let r2 = (1.0 - w.z.abs()).clamp(0.0, 1.0);
    let s = safe_sqrt(2.0 - r2);
    let d = if s > 0.0 {
        Vec2::new(w.x, w.y) / s
    } else {
        Vec2::ZERO
    };
    concentric_disk_to_square(d)
}

/// Density of a uniform point of the square mapped by [`concentric_square_to_hemisphere`].
pub fn concentric_hemisphere_pdf() -> f32 {
    1.0 / (2.0 * std::f32::consts::PI)
}

/// The cell of a `res × res` grid that contains square point `p` (row-major index).
#[inline]
pub fn grid_cell(p: Vec2, res: u32) -> u32 {
    let x = ((p.x * res as f32) as u32).min(res - 1);
    let y = ((p.y * res as f32) as u32).min(res - 1);
    y * res + x
}

/// Per-cell averages of a `res × res` map of Monte Carlo sums (`sum[i] / weight[i]`), where a
/// cell that no sample reached takes the average of the smallest enclosing 2^k × 2^k block that
/// some sample did reach, and `default` if none did.
///
/// The cells of both maps here nest: a block of 2×2 cells is one cell of the map at half the
/// resolution, so this is the estimate the coarser map would give. A visibility map with fewer
/// rays than cells (a finest-level voxel: 16 samples × 16 rays over 32² cells) then stays
/// unbiased in every direction instead of falling back to the mean over the whole sphere.
pub fn average_with_coarser_fill(sum: &[f64], weight: &[f64], res: u32, default: f32) -> Vec<f32> {
    let count: Vec<u32> = weight.iter().map(|&w| (w > 0.0) as u32).collect();
    average_with_min_count(sum, weight, &count, 1, res, default)
}

/// As [`average_with_coarser_fill`], but a cell's estimate comes from the smallest enclosing
/// 2^k × 2^k block (the cell itself first) that holds at least `min_count` samples (`count`
/// per cell) and some weight: an adaptive bandwidth, fine where samples are dense and coarse
/// where they are sparse, so that no cell rests on one binary ray.
pub fn average_with_min_count(
    sum: &[f64],
    weight: &[f64],
    count: &[u32],
    min_count: u32,
    res: u32,
    default: f32,
) -> Vec<f32> {
    BlockPyramid::new(sum, weight, count, res).map(min_count, default)
}

/// The (Σ value, Σ weight, count) of every 2^k × 2^k block of a `res × res` map, level 0 being
/// the map itself: [`average_with_min_count`] for many `min_count`s, or for a few cells, from
/// one pass over the map (a bandwidth chosen by cross-validation scores each candidate on the
/// held-out rays' cells only).
pub struct BlockPyramid {
    levels: Vec<(u32, Vec<(f64, f64, u32)>)>,
}

impl BlockPyramid {
    pub fn new(sum: &[f64], weight: &[f64], count: &[u32], res: u32) -> Self {
        debug_assert_eq!(sum.len(), (res * res) as usize);
        debug_assert_eq!(weight.len(), sum.len());
        debug_assert_eq!(count.len(), sum.len());
        let mut levels: Vec<(u32, Vec<(f64, f64, u32)>)> = vec![(
            res,
            sum.iter()
                .zip(weight)
                .zip(count)
                .map(|((&s, &w), &n)| (s, w, n))
                .collect(),
        )];
        while levels.last().is_some_and(|(r, _)| *r > 1) {
            let (r, cells) = levels.last().expect("non-empty");
            let (r, h) = (*r, (*r).div_ceil(2));
            let mut next = vec![(0.0, 0.0, 0u32); (h * h) as usize];
            for y in 0..r {
                for x in 0..r {
                    let (s, w, n) = cells[(y * r + x) as usize];
                    let c = &mut next[((y / 2) * h + x / 2) as usize];
                    c.0 += s;
                    c.1 += w;
                    c.2 += n;
                }
            }
            levels.push((h, next));
        }
        BlockPyramid { levels }
    }

    /// The estimate of cell `i`: the average of the smallest enclosing block holding at least
    /// `min_count` samples and some weight; the largest block with weight if none holds that
    /// many; `default` if no block has weight.
    #[inline]
    pub fn value(&self, i: u32, min_count: u32, default: f32) -> f32 {
        let res = self.levels[0].0;
        let (mut x, mut y) = (i % res, i / res);
        let mut last = None;
        for (r, cells) in &self.levels {
            let (s, w, n) = cells[(y * r + x) as usize];
            if w > 0.0 {
                last = Some((s / w) as f32);
                if n >= min_count {
                    return (s / w) as f32;
                }
            }
            (x, y) = (x / 2, y / 2);
        }
        last.unwrap_or(default)
    }

    /// [`BlockPyramid::value`] of every cell.
    pub fn map(&self, min_count: u32, default: f32) -> Vec<f32> {
        let res = self.levels[0].0;
        (0..res * res)
            .map(|i| self.value(i, min_count, default))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atan_polynomial_is_accurate() {
        let worst = (0..=10_000)
            .map(|i| {
                let b = i as f32 / 10_000.0;
                (atan01(b) - b.atan()).abs()
            })
            .fold(0.0f32, f32::max);
        assert!(worst < 3e-6, "{worst}");
    }
    use crate::validation::chi2::{chi2_test, Chi2Settings};

    fn grid() -> impl Iterator<Item = Vec2> {
        (0..50).flat_map(|i| {
            (0..50).map(move |j| Vec2::new((i as f32 + 0.37) / 50.0, (j as f32 + 0.61) / 50.0))
        })
    }

    #[test]
    fn clarberg_round_trip() {
        for p in grid() {
            let d = equal_area_square_to_sphere(p);
            assert!((d.length() - 1.0).abs() < 1e-5);
            let q = equal_area_sphere_to_square(d);
            assert!((q - p).length() < 1e-4, "{p} -> {d} -> {q}");
        }
        assert!((equal_area_square_to_sphere(Vec2::splat(0.5)) - Vec3::Z).length() < 1e-6);
        assert!((equal_area_square_to_sphere(Vec2::ZERO) + Vec3::Z).length() < 1e-6);
    }

    /// Equal area: uniform points on the square land uniformly on the sphere.
    #[test]
    fn clarberg_is_equal_area() {
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(equal_area_square_to_sphere(u)),
            |_| equal_area_sphere_pdf(),
        );
        assert!(r.passed(0.01), "{r:?}");
    }

    #[test]
    fn concentric_hemisphere_round_trip_and_chi2() {
        for p in grid() {
            let w = concentric_square_to_hemisphere(p);
            assert!((w.length() - 1.0).abs() < 1e-5 && w.z >= 0.0);
            assert!((concentric_hemisphere_to_square(w) - p).length() < 1e-3);
        }
        let r = chi2_test(
            Chi2Settings::default(),
            |u| Some(concentric_square_to_hemisphere(u)),
            |w| {
                if w.z >= 0.0 {
                    concentric_hemisphere_pdf()
                } else {
                    0.0
                }
            },
        );
        assert!(r.passed(0.01), "{r:?}");
    }

    #[test]
    fn grid_cells() {
        assert_eq!(grid_cell(Vec2::new(0.0, 0.0), 32), 0);
        assert_eq!(grid_cell(Vec2::new(1.0, 1.0), 32), 32 * 32 - 1);
        assert_eq!(grid_cell(Vec2::new(0.5, 0.0), 4), 2);
    }
    /// Empty cells take their nearest reached block's average, never the whole map's.
    #[test]
    fn coarser_fill_uses_the_enclosing_block() {
        // 4×4 map: one sample of value 1 in cell (0,0), one of value 0 in cell (3,3).
        let (mut sum, mut w) = (vec![0.0; 16], vec![0.0; 16]);
        (sum[0], w[0]) = (1.0, 1.0);
        (sum[15], w[15]) = (0.0, 2.0);
        let m = average_with_coarser_fill(&sum, &w, 4, 0.5);
        // The 2×2 block of (0,0) takes 1, the block of (3,3) takes 0, the other two blocks the
        // whole map's weighted mean 1/3.
        for (i, v) in m.iter().enumerate() {
            let (x, y) = (i % 4, i / 4);
            let want = match (x / 2, y / 2) {
                (0, 0) => 1.0,
                (1, 1) => 0.0,
                _ => 1.0 / 3.0,
            };
            assert!((v - want).abs() < 1e-6, "cell ({x},{y}): {v} vs {want}");
        }
        assert_eq!(
            average_with_coarser_fill(&[0.0; 4], &[0.0; 4], 2, 0.25),
            vec![0.25; 4]
        );
        // Not a power of two: still fills every cell.
        let (mut sum, mut w) = (vec![0.0; 9], vec![0.0; 9]);
        (sum[8], w[8]) = (0.25, 1.0);
        assert_eq!(average_with_coarser_fill(&sum, &w, 3, 0.7), vec![0.25; 9]);
    }
}
