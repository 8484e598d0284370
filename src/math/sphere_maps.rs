//! Area-preserving maps between the unit square and the sphere or hemisphere, each with its
//! inverse: Clarberg's equal-area sphere map (used for the 32×32 interior-visibility maps) and
//! the concentric hemisphere map (used for the 64×64 boundary-visibility maps over a face's
//! inward hemisphere).

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4};

use glam::{Vec2, Vec3};

use super::safe_sqrt;
use super::sampling::{concentric_disk_to_square, square_to_concentric_disk};

/// Clarberg 2008, "Fast Equal-Area Mapping of the (Hemi)Sphere using SIMD": the square
/// [0, 1]² folds like an octahedron onto the sphere; every cell of a regular grid on the square
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
    /// The pyramid of the per-cell sums `sum`, weights `weight` and ray counts `count` of a
    /// `res × res` map.
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

/// For every cell of a `res × res` equal-area sphere map, the cells in order of the angle
/// between their centres and its own (itself first; ties by index): the neighbourhoods of the
/// spherical-cap estimator [`cap_averages`]. At most [`CAP_WIDTH`] a cell; built once per
/// resolution (res ≤ [`CAP_MAX_RES`]) and shared.
pub struct CapOrder {
    width: usize,
    order: Vec<u16>,
}

/// The most cells a cap of [`CapOrder`] may take in.
pub const CAP_WIDTH: usize = 384;

/// The largest map resolution [`CapOrder`] serves.
pub const CAP_MAX_RES: u32 = 64;

impl CapOrder {
    /// The order of a `res × res` map (a power of two, at most [`CAP_MAX_RES`]), built on first
    /// use.
    pub fn get(res: u32) -> Option<&'static CapOrder> {
        static ORDERS: [std::sync::OnceLock<CapOrder>; 7] =
            [const { std::sync::OnceLock::new() }; 7];
        if !res.is_power_of_two() || res > CAP_MAX_RES {
            return None;
        }
        Some(ORDERS[res.trailing_zeros() as usize].get_or_init(|| CapOrder::build(res)))
    }

    fn build(res: u32) -> CapOrder {
        let cells = (res * res) as usize;
        let centre = |i: usize| {
            let (x, y) = ((i as u32 % res) as f32, (i as u32 / res) as f32);
            equal_area_square_to_sphere(Vec2::new((x + 0.5) / res as f32, (y + 0.5) / res as f32))
        };
        let dirs: Vec<Vec3> = (0..cells).map(centre).collect();
        let width = cells.min(CAP_WIDTH);
        let mut order = Vec::with_capacity(cells * width);
        let mut idx: Vec<u16> = Vec::with_capacity(cells);
        for d in &dirs {
            idx.clear();
            idx.extend(0..cells as u16);
            // Descending cosine, ties by index: a total order, so the bake stays deterministic.
            let key = |j: &u16| (std::cmp::Reverse(ordered(d.dot(dirs[*j as usize]))), *j);
            if width < cells {
                idx.select_nth_unstable_by_key(width - 1, key);
                idx.truncate(width);
            }
            idx.sort_unstable_by_key(key);
            order.extend_from_slice(&idx);
        }
        CapOrder { width, order }
    }

    /// The cells around cell `i`, nearest first.
    #[inline]
    pub fn around(&self, i: usize) -> &[u16] {
        &self.order[i * self.width..(i + 1) * self.width]
    }
}

/// An f32's bits in an order that sorts like the value (no NaN here: cosines of unit vectors).
fn ordered(x: f32) -> i32 {
    let b = x.to_bits() as i32;
    b ^ (((b >> 31) as u32) >> 1) as i32
}

/// Per-cell averages of a `res × res` equal-area map of Monte Carlo sums over a *spherical cap*
/// centred on the cell: the nearest cells ([`CapOrder`]) taken in until they hold at least
/// `min_count` samples, one map per entry of `min_counts` (ascending). The cap is centred on
/// the direction estimated, so a smooth visibility's bias is of second order in the cap's
/// radius, where [`BlockPyramid`]'s enclosing block has the cell anywhere inside it (first
/// order; worst at the block's corners and across the octahedral folds, where a block's cells
/// are not neighbours on the sphere). A cap that runs out of cells keeps the average it has
/// (the largest with weight), `default` where no cell within reach has weight. `None` for a
/// resolution [`CapOrder`] does not serve.
pub fn cap_averages(
    sum: &[f64],
    weight: &[f64],
    count: &[u32],
    min_counts: &[u32],
    res: u32,
    default: f32,
) -> Option<Vec<Vec<f32>>> {
    let order = CapOrder::get(res)?;
    let cells = (res * res) as usize;
    debug_assert!(sum.len() == cells && weight.len() == cells && count.len() == cells);
    debug_assert!(min_counts.windows(2).all(|w| w[0] <= w[1]));
    let mut maps = vec![vec![default; cells]; min_counts.len()];
    for i in 0..cells {
        let (mut s, mut w, mut n) = (0f64, 0f64, 0u32);
        let mut k = 0;
        for &j in order.around(i) {
            let j = j as usize;
            s += sum[j];
            w += weight[j];
            n += count[j];
            while k < min_counts.len() && n >= min_counts[k] && w > 0.0 {
                maps[k][i] = (s / w) as f32;
                k += 1;
            }
            if k == min_counts.len() {
                break;
            }
        }
        if w > 0.0 {
            for m in &mut maps[k..] {
                m[i] = (s / w) as f32;
            }
        }
    }
    Some(maps)
}

/// Summed-area tables of a `res × res` map's (Σ value, Σ weight, count): averages over square
/// windows of cells *centred* on a cell, each in constant time. On Shirley and Chiu's
/// concentric hemisphere map ([`concentric_square_to_hemisphere`], equal-area and continuous
/// inside the square) a centred window is a neighbourhood centred on the cell's direction, as
/// the spherical cap of [`cap_averages`] is on the sphere map, so a smooth visibility's bias is
/// of second order in its size where [`BlockPyramid`]'s enclosing block's is of first; only
/// at the square's edge (the horizon) is a window clipped to one side.
pub struct CentredWindows {
    res: u32,
    max_radius: u32,
    /// `(res + 1)²` prefix sums; entry (x, y) sums the cells below x and y.
    table: Vec<(f64, f64, u32)>,
}

impl CentredWindows {
    /// Windows up to `max_radius` cells either side of their centre (side `2r + 1`).
    pub fn new(sum: &[f64], weight: &[f64], count: &[u32], res: u32, max_radius: u32) -> Self {
        let n = res as usize;
        debug_assert!(sum.len() == n * n && weight.len() == n * n && count.len() == n * n);
        let mut table = vec![(0.0, 0.0, 0u32); (n + 1) * (n + 1)];
        for y in 0..n {
            let mut row = (0.0, 0.0, 0u32);
            for x in 0..n {
                let c = y * n + x;
                row = (row.0 + sum[c], row.1 + weight[c], row.2 + count[c]);
                let above = table[y * (n + 1) + x + 1];
                table[(y + 1) * (n + 1) + x + 1] =
                    (above.0 + row.0, above.1 + row.1, above.2 + row.2);
            }
        }
        CentredWindows {
            res,
            max_radius,
            table,
        }
    }

    /// The sums over cells [x0, x1) × [y0, y1).
    #[inline]
    fn rect(&self, x0: u32, y0: u32, x1: u32, y1: u32) -> (f64, f64, u32) {
        let w = self.res as usize + 1;
        let at = |x: u32, y: u32| self.table[y as usize * w + x as usize];
        let (a, b, c, d) = (at(x1, y1), at(x0, y1), at(x1, y0), at(x0, y0));
        (
            a.0 - b.0 - c.0 + d.0,
            a.1 - b.1 - c.1 + d.1,
            a.2 + d.2 - b.2 - c.2,
        )
    }

    /// For each of `min_counts` (ascending), the average over the smallest window centred on
    /// cell `i` holding at least that many samples and some weight, written to `out`; `None`
    /// where no window up to the largest does (the caller falls back to a block).
    pub fn values(&self, i: u32, min_counts: &[u32], out: &mut [Option<f32>]) {
        debug_assert_eq!(min_counts.len(), out.len());
        debug_assert!(min_counts.windows(2).all(|w| w[0] <= w[1]));
        out.fill(None);
        let (x, y) = (i % self.res, i / self.res);
        let mut k = 0;
        for r in 0..=self.max_radius {
            let (x0, y0) = (x.saturating_sub(r), y.saturating_sub(r));
            let (x1, y1) = ((x + r + 1).min(self.res), (y + r + 1).min(self.res));
            let (s, w, n) = self.rect(x0, y0, x1, y1);
            while k < min_counts.len() && n >= min_counts[k] && w > 0.0 {
                out[k] = Some((s / w) as f32);
                k += 1;
            }
            if k == min_counts.len() || (x0 == 0 && y0 == 0 && x1 == self.res && y1 == self.res) {
                return;
            }
        }
    }

    /// [`CentredWindows::values`] for one `min_count`.
    #[inline]
    pub fn value(&self, i: u32, min_count: u32) -> Option<f32> {
        let mut out = [None];
        self.values(i, &[min_count], &mut out);
        out[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every cap starts at its own cell and grows by angle; across the octahedral fold (the
    /// square's edge, where the quadtree's blocks are not neighbours on the sphere) the nearest
    /// cells are the mirrored ones.
    #[test]
    fn cap_order_grows_by_angle_across_the_folds() {
        let res = 32;
        let order = CapOrder::get(res).expect("served");
        let centre = |i: u16| {
            let (x, y) = ((i as u32 % res) as f32 + 0.5, (i as u32 / res) as f32 + 0.5);
            equal_area_square_to_sphere(Vec2::new(x, y) / res as f32)
        };
        for i in 0..(res * res) as usize {
            let a = order.around(i);
            assert_eq!(a[0] as usize, i);
            let c = centre(i as u16);
            for w in a.windows(2) {
                assert!(c.dot(centre(w[0])) >= c.dot(centre(w[1])), "cell {i}");
            }
        }
        // Cell (0, 16) on the left edge: its mirror (0, 15) is a neighbour on the sphere.
        let i = 16 * res as usize;
        assert!(order.around(i)[..4].contains(&(15 * res as u16)));
        assert!(CapOrder::get(128).is_none() && CapOrder::get(12).is_none());
        // Caps of at least 1, 4 and 1000 rays over a map with one ray in cell 0.
        let mut sum = vec![0.0; 1024];
        let mut weight = vec![0.0; 1024];
        let mut count = vec![0; 1024];
        (sum[0], weight[0], count[0]) = (1.0, 1.0, 1);
        let m = cap_averages(&sum, &weight, &count, &[1, 4, 1000], res, 0.5).expect("served");
        assert!(m.iter().all(|m| m[0] == 1.0));
        // A cap that runs out of cells before reaching its rays keeps what it has, and one
        // that reaches no ray takes the default.
        let far = (0..1024)
            .find(|&j| !order.around(j).contains(&0))
            .expect("a far cell");
        assert!(m.iter().all(|m| m[far] == 0.5));
    }

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

    /// A centred window's average equals a brute-force sum over the clipped square, grows
    /// only until it holds the samples asked for, and gives up past its largest radius.
    #[test]
    fn centred_windows_match_brute_force() {
        let res = 16u32;
        let cells = (res * res) as usize;
        let mut rng = crate::math::rng::Pcg32::new(3, 1);
        let count: Vec<u32> = (0..cells).map(|_| (rng.next_f32() < 0.2) as u32).collect();
        let weight: Vec<f64> = count.iter().map(|&c| c as f64).collect();
        let sum: Vec<f64> = weight.iter().map(|&w| w * rng.next_f32() as f64).collect();
        let win = CentredWindows::new(&sum, &weight, &count, res, 4);
        for i in 0..res * res {
            let (x, y) = ((i % res) as i64, (i / res) as i64);
            let mut out = [None; 3];
            win.values(i, &[1, 3, 12], &mut out);
            for (k, &min) in [1u32, 3, 12].iter().enumerate() {
                let brute = (0..=4).find_map(|r: i64| {
                    let (mut s, mut w, mut n) = (0.0, 0.0, 0);
                    for yy in (y - r).max(0)..=(y + r).min(res as i64 - 1) {
                        for xx in (x - r).max(0)..=(x + r).min(res as i64 - 1) {
                            let c = (yy * res as i64 + xx) as usize;
                            (s, w, n) = (s + sum[c], w + weight[c], n + count[c]);
                        }
                    }
                    (n >= min && w > 0.0).then(|| (s / w) as f32)
                });
                match (out[k], brute) {
                    (Some(a), Some(b)) => assert!((a - b).abs() < 1e-5, "cell {i}: {a} {b}"),
                    (a, b) => assert_eq!(a, b, "cell {i}"),
                }
                assert_eq!(win.value(i, min), out[k]);
            }
        }
        assert_eq!(win.value(0, 1000), None);
    }
}
