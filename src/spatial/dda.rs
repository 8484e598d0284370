//! The 3D DDA (Amanatides–Woo) over one level's grid: the voxel a ray is in and the ray
//! parameters at which it crosses the next plane along each axis. The cone tracer (Algorithm 1,
//! line 8) and the exponential-volume baseline both walk it.

use glam::{IVec3, Vec3};

use super::grid::Grid;

/// A ray's walk through the voxels of a grid.
#[derive(Clone, Copy, Debug)]
pub struct Dda {
    /// The current voxel (inside the grid while the walk lasts).
    pub v: IVec3,
    /// The step along each axis (−1, 0 or +1).
    pub step: IVec3,
    t_next: Vec3,
    delta: Vec3,
    res: i32,
}

impl Dda {
    /// A walk that has not started (a placeholder to be overwritten): all zeros, so that an
    /// array of them is cleared rather than copied from a constant (a cone's walk holds one
    /// per granularity, and copying them in was 4% of a LoD render), and a grid of no voxels,
    /// so that advancing it ends at once.
    pub const IDLE: Dda = Dda {
        v: IVec3::ZERO,
        step: IVec3::ZERO,
        t_next: Vec3::ZERO,
        delta: Vec3::ZERO,
        res: 0,
    };

    /// Starts at parameter `t` of `origin + t·dir` (`inv` = 1/dir), in voxel `v` if given, else
    /// in the voxel holding the point (clamped into the grid).
    pub fn new(g: &Grid, origin: Vec3, dir: Vec3, inv: Vec3, t: f32, v: Option<IVec3>) -> Dda {
        let s = g.voxel_size();
        let res = g.res as i32;
        let inv_s = g.res as f32 / g.size;
        let step = IVec3::new(
            (dir.x > 0.0) as i32 - (dir.x < 0.0) as i32,
            (dir.y > 0.0) as i32 - (dir.y < 0.0) as i32,
            (dir.z > 0.0) as i32 - (dir.z < 0.0) as i32,
        );
        let v = v.unwrap_or_else(|| {
            ((origin + dir * t - g.origin) * inv_s)
                .floor()
                .as_ivec3()
                .clamp(IVec3::ZERO, IVec3::splat(res - 1))
        });
        let next = |a: usize| -> f32 {
            if step[a] == 0 {
                return f32::INFINITY;
            }
            let b = g.origin[a] + (v[a] + (step[a] > 0) as i32) as f32 * s;
            (b - origin[a]) * inv[a]
        };
        Dda {
            v,
            step,
            t_next: Vec3::new(next(0), next(1), next(2)),
            delta: Vec3::select(
                step.cmpeq(IVec3::ZERO),
                Vec3::INFINITY,
                (Vec3::splat(s) * inv).abs(),
            ),
            res,
        }
    }

    /// The walk of the same ray through the 4³ children of the current cell (a grid of four
    /// times the resolution), starting in child `v` (which must lie in the current cell): the
    /// children's planes are the cell's subdivided, so their crossings follow from the cell's
    /// own by exact steps of a quarter of its spacing, without recomputing from the origin.
    #[inline]
    pub fn child(&self, v: IVec3) -> Dda {
        let delta = self.delta * 0.25;
        let lo = self.v * 4;
        let mut t_next = self.t_next;
        for a in 0..3 {
            let k = if self.step[a] > 0 {
                lo[a] + 3 - v[a]
            } else {
                v[a] - lo[a]
            };
            if self.step[a] != 0 {
                t_next[a] -= delta[a] * k as f32;
            }
        }
        Dda {
            v,
            step: self.step,
            t_next,
            delta,
            res: self.res * 4,
        }
    }

    /// Where the ray leaves the current voxel.
    #[inline]
    pub fn t_exit(&self) -> f32 {
        self.t_next.min_element()
    }

    /// Moves into the next voxel: the axis crossed and the parameter there, or None when the
    /// ray leaves the grid.
    #[inline]
    pub fn advance(&mut self) -> Option<(usize, f32)> {
        let n = self.t_next;
        let axis = if n.x <= n.y && n.x <= n.z {
            0
        } else if n.y <= n.z {
            1
        } else {
            2
        };
        let t = n[axis];
        self.v[axis] += self.step[axis];
        if self.v[axis] < 0 || self.v[axis] >= self.res {
            return None;
        }
        self.t_next[axis] += self.delta[axis];
        Some((axis, t))
    }
}

/// The axis of the cube face through which a ray (`inv` = 1/dir) enters the box [lo, hi]: the
/// axis of the latest entering slab.
#[inline]
pub fn entry_axis(lo: Vec3, hi: Vec3, origin: Vec3, inv: Vec3) -> usize {
    let (a, b) = ((lo - origin) * inv, (hi - origin) * inv);
    let near = a.min(b);
    if near.x >= near.y && near.x >= near.z {
        0
    } else if near.y >= near.z {
        1
    } else {
        2
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A diagonal walk visits voxels whose boxes the ray really crosses, in order, and leaves
    /// the grid where the box interval says.
    /// A child walk started from a cell's DDA crosses the same planes as a walk of the finer
    /// grid started from scratch.
    #[test]
    fn child_walk_matches_a_fresh_one() {
        let coarse = Grid {
            origin: Vec3::new(-1.0, 0.5, 2.0),
            size: 3.0,
            res: 4,
        };
        let fine = coarse.with_res(16);
        let o = Vec3::new(-2.0, 1.1, 2.7);
        let d = Vec3::new(1.0, 0.23, 0.41).normalize();
        let inv = d.recip();
        let (t0, _) = crate::spatial::box_interval(coarse.origin, coarse.origin + 3.0, o, inv);
        let parent = Dda::new(&coarse, o, d, inv, t0, None);
        let fresh = Dda::new(&fine, o, d, inv, t0, None);
        let mut child = parent.child(fresh.v);
        let mut fresh = fresh;
        for _ in 0..3 {
            assert_eq!(child.v, fresh.v);
            assert!((child.t_exit() - fresh.t_exit()).abs() < 1e-5);
            if child.advance().is_none() || fresh.advance().is_none() {
                break;
            }
        }
    }

    #[test]
    fn walks_the_voxels_the_ray_crosses() {
        let g = Grid {
            origin: Vec3::ZERO,
            size: 1.0,
            res: 8,
        };
        let o = Vec3::new(-0.5, 0.13, 0.31);
        let d = Vec3::new(1.0, 0.41, 0.2).normalize();
        let inv = d.recip();
        let (t0, t1) = crate::spatial::box_interval(Vec3::ZERO, Vec3::ONE, o, inv);
        let mut dda = Dda::new(&g, o, d, inv, t0, None);
        let mut t = t0;
        let mut n = 0;
        loop {
            let (lo, hi) = g.voxel_bounds(dda.v.as_uvec3());
            let mid = o + d * (0.5 * (t + dda.t_exit().min(t1)));
            assert!(mid.cmpge(lo - 1e-5).all() && mid.cmple(hi + 1e-5).all());
            n += 1;
            match dda.advance() {
                Some((_, tc)) => {
                    assert!(tc >= t - 1e-6);
                    t = tc;
                }
                None => break,
            }
        }
        assert!((dda.t_exit().min(t1) - t1).abs() < 1e-4 || t <= t1 + 1e-4);
        assert!(n >= 8 && n <= 3 * 8, "{n}");
        assert_eq!(entry_axis(Vec3::ZERO, Vec3::ONE, o, inv), 0);
    }
}
