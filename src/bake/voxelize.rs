//! Sparse voxelization (paper §7.1): the non-empty voxels of a level, found by triangle–box
//! overlap with exact clipping, so that each voxel knows the surface area inside it.
//!
//! A triangle is clipped against each candidate voxel of its bounding box (Sutherland–Hodgman
//! against the six slabs); the clipped polygon's area is the triangle's area in that voxel, and
//! the areas over all voxels add up to the triangle's area (checked by tests). Voxels are keyed
//! by their integer coordinates packed into a Morton code, which orders a level spatially.

use std::collections::BTreeMap;

use glam::{DVec3, UVec3, Vec3};

use crate::scene::Scene;
use crate::spatial::{morton3, Grid};

/// Clips a convex polygon (in place, f64) to the half-open slab `lo ≤ p[axis] < hi`. Half-open,
/// so that a polygon lying exactly in a voxel boundary plane belongs to one voxel, not two.
fn clip_slab(poly: &mut Vec<DVec3>, scratch: &mut Vec<DVec3>, axis: usize, lo: f64, hi: f64) {
    for (bound, keep_above) in [(lo, true), (hi, false)] {
        scratch.clear();
        let n = poly.len();
        let inside = |d: f64| if keep_above { d >= 0.0 } else { d > 0.0 };
        for i in 0..n {
            let a = poly[i];
            let b = poly[(i + 1) % n];
            let da = if keep_above {
                a[axis] - bound
            } else {
                bound - a[axis]
            };
            let db = if keep_above {
                b[axis] - bound
            } else {
                bound - b[axis]
            };
            if inside(da) {
                scratch.push(a);
            }
            if inside(da) != inside(db) && da != db {
                let t = da / (da - db);
                scratch.push(a + (b - a) * t);
            }
        }
        std::mem::swap(poly, scratch);
        if poly.len() < 3 {
            poly.clear();
            return;
        }
    }
}

/// Area of a planar polygon.
fn polygon_area(poly: &[DVec3]) -> f64 {
    if poly.len() < 3 {
        return 0.0;
    }
    let mut c = DVec3::ZERO;
    for i in 1..poly.len() - 1 {
        c += (poly[i] - poly[0]).cross(poly[i + 1] - poly[0]);
    }
    0.5 * c.length()
}

/// Per-voxel surface area of a triangle: calls `emit(voxel, area)` for each voxel the triangle
/// overlaps with positive area.
pub fn clip_triangle(grid: &Grid, tri: [Vec3; 3], mut emit: impl FnMut(UVec3, f64)) {
    clip_triangle_polygons(grid, tri, |v, _, a| emit(v, a));
}

/// Like [`clip_triangle`], also passing the clipped polygon in grid units (voxel size 1, grid
/// origin at 0).
pub fn clip_triangle_polygons(
    grid: &Grid,
    tri: [Vec3; 3],
    mut emit: impl FnMut(UVec3, &[DVec3], f64),
) {
    let s = grid.voxel_size() as f64;
    let o = grid.origin.as_dvec3();
    let p: Vec<DVec3> = tri.iter().map(|v| (v.as_dvec3() - o) / s).collect();
    let lo = p[0].min(p[1]).min(p[2]);
    let hi = p[0].max(p[1]).max(p[2]);
    let max = (grid.res - 1) as f64;
    let l = lo.floor().clamp(DVec3::ZERO, DVec3::splat(max)).as_uvec3();
    let h = hi.floor().clamp(DVec3::ZERO, DVec3::splat(max)).as_uvec3();
    let mut poly = Vec::with_capacity(9);
    let mut scratch = Vec::with_capacity(9);
    for z in l.z..=h.z {
        for y in l.y..=h.y {
            for x in l.x..=h.x {
                poly.clear();
                poly.extend_from_slice(&p);
                for (axis, c) in [(0usize, x), (1, y), (2, z)] {
                    // The outermost voxels extend to infinity so that nothing is lost at the
                    // grid's boundary through rounding.
                    let lo_b = if c == 0 { f64::NEG_INFINITY } else { c as f64 };
                    let hi_b = if c == grid.res - 1 {
                        f64::INFINITY
                    } else {
                        c as f64 + 1.0
                    };
                    clip_slab(&mut poly, &mut scratch, axis, lo_b, hi_b);
                    if poly.is_empty() {
                        break;
                    }
                }
                // Pieces below 1e-9 of a voxel face are rounding slivers of a triangle that
                // only touches the voxel (exactly zero in exact arithmetic).
                let a = polygon_area(&poly);
                if a > 1e-9 {
                    emit(UVec3::new(x, y, z), &poly, a * s * s);
                }
            }
        }
    }
}

/// The non-empty voxels of a level with their surface area (world units²), keyed by Morton
/// code (so iteration is in Z-order).
pub fn occupancy(scene: &Scene, grid: &Grid) -> BTreeMap<u64, f64> {
    let mut out = BTreeMap::new();
    for inst in &scene.instances {
        let m = &scene.meshes[inst.mesh as usize];
        for t in 0..m.triangles.len() {
            let tri = m.triangle(t).map(|p| inst.transform.transform_point3(p));
            clip_triangle(grid, tri, |v, a| *out.entry(morton3(v)).or_insert(0.0) += a);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;

    /// Clipped areas add up to the triangle's area, for random triangles of every size.
    #[test]
    fn areas_are_conserved() {
        let grid = Grid {
            origin: Vec3::ZERO,
            size: 1.0,
            res: 16,
        };
        let mut rng = Pcg32::new(1, 2);
        for k in 0..500 {
            let scale = [0.01f32, 0.1, 0.7][k % 3];
            let c = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let tri = [0, 1, 2].map(|_| {
                c + (Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5) * scale
            });
            let area = 0.5 * ((tri[1] - tri[0]).cross(tri[2] - tri[0])).length() as f64;
            let mut sum = 0.0;
            let mut count = 0;
            clip_triangle(&grid, tri, |_, a| {
                sum += a;
                count += 1;
            });
            assert!(
                (sum - area).abs() <= 1e-6 * area.max(1e-9) + 1e-12,
                "{sum} vs {area}"
            );
            assert!(count >= 1);
        }
    }

    /// A unit plane at 45° through a 4³ grid: every reported voxel really intersects it, and the
    /// area per voxel matches the known value where the plane crosses a voxel whole.
    #[test]
    fn diagonal_plane() {
        let grid = Grid {
            origin: Vec3::ZERO,
            size: 4.0,
            res: 4,
        };
        // The plane x = y, from (0,0,0) to (4,4,4) in z: two triangles.
        let a = Vec3::new(0.0, 0.0, 0.0);
        let b = Vec3::new(4.0, 4.0, 0.0);
        let c = Vec3::new(4.0, 4.0, 4.0);
        let d = Vec3::new(0.0, 0.0, 4.0);
        let mut cells = BTreeMap::new();
        for t in [[a, b, c], [a, c, d]] {
            clip_triangle(&grid, t, |v, ar| {
                *cells.entry((v.x, v.y, v.z)).or_insert(0.0) += ar
            });
        }
        // The diagonal voxels (i, i, z) hold √2 each.
        for i in 0..4 {
            for z in 0..4 {
                let ar = cells.get(&(i, i, z)).copied().unwrap_or(0.0);
                assert!((ar - 2f64.sqrt()).abs() < 1e-9, "({i},{i},{z}): {ar}");
            }
        }
        let total: f64 = cells.values().sum();
        assert!((total - 16.0 * 2f64.sqrt()).abs() < 1e-9);
    }

    /// A triangle lying exactly in a voxel boundary plane is counted once.
    #[test]
    fn boundary_plane_counted_once() {
        let grid = Grid {
            origin: Vec3::ZERO,
            size: 4.0,
            res: 4,
        };
        let tri = [
            Vec3::new(0.5, 0.5, 2.0),
            Vec3::new(3.5, 0.5, 2.0),
            Vec3::new(0.5, 3.5, 2.0),
        ];
        let mut total = 0.0;
        let mut zs = std::collections::BTreeSet::new();
        clip_triangle(&grid, tri, |v, a| {
            total += a;
            zs.insert(v.z);
        });
        assert!((total - 4.5).abs() < 1e-9, "{total}");
        assert_eq!(zs.len(), 1);
    }
}
