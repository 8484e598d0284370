//! Aggregated boundary visibility (paper Eq. 26): for a boundary face and each direction of its
//! inward hemisphere (64×64 concentric map), among the rays from the face that hit some
//! primitive of the level (the P⁺ of Eq. 26), the fraction that escapes the real geometry.
//! Primitives are the voxels' truncated ellipsoids, found along a ray by a 3D DDA over the
//! sparse level.

use std::collections::HashMap;

use glam::{UVec3, Vec2, Vec3};

use super::boundary::Face;
use super::primitive::Ellipsoid;
use super::voxelize::{morton3, Grid};
use crate::math::frame::Frame;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::sphere_maps::{concentric_square_to_hemisphere, grid_cell};
use crate::trace::{Accel, Ray};

/// A hasher for Morton keys (already well spread by one mixing step), much cheaper than
/// SipHash in the DDA's inner loop.
#[derive(Default, Clone, Copy)]
pub struct KeyHasher(u64);

impl std::hash::Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        crate::math::rng::mix64(self.0)
    }
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 = (self.0 << 8) ^ *b as u64;
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = v;
    }
}

/// A voxel's ellipsoid, ready for ray tests: centre and inverse axes.
#[derive(Clone, Copy, Debug)]
struct Prepared {
    center: Vec3,
    inv: glam::Mat3,
}

/// The primitives of one level.
pub struct PrimitiveLevel {
    pub grid: Grid,
    primitives: HashMap<u64, Prepared, std::hash::BuildHasherDefault<KeyHasher>>,
}

impl PrimitiveLevel {
    /// The level of these (Morton key, ellipsoid) pairs; degenerate ellipsoids are left out.
    pub fn new(grid: Grid, prims: impl IntoIterator<Item = (u64, Ellipsoid)>) -> Self {
        let primitives = prims
            .into_iter()
            .filter_map(|(k, e)| {
                let inv = e.axes.inverse();
                inv.is_finite().then_some((
                    k,
                    Prepared {
                        center: e.center,
                        inv,
                    },
                ))
            })
            .collect();
        PrimitiveLevel { grid, primitives }
    }

    pub fn len(&self) -> usize {
        self.primitives.len()
    }

    pub fn is_empty(&self) -> bool {
        self.primitives.is_empty()
    }
}

/// Parameter interval where `o + t d` is inside the ellipsoid.
fn ellipsoid_interval(e: &Prepared, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
    let inv = e.inv;
    let p = inv * (o - e.center);
    let q = inv * d;
    let a = q.dot(q);
    let b = p.dot(q);
    let c = p.dot(p) - 1.0;
    let disc = b * b - a * c;
    if !(a > 0.0) || disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    Some(((-b - s) / a, (-b + s) / a))
}

impl PrimitiveLevel {
    /// Whether the ray meets any truncated ellipsoid (the intersection of a voxel and its
    /// ellipsoid) for t in [ray.tmin, ray.tmax].
    pub fn hits(&self, ray: &Ray) -> bool {
        let g = &self.grid;
        let s = g.voxel_size();
        let lo = g.origin;
        let hi = g.origin + Vec3::splat(g.size);
        // Entry and exit of the grid cube.
        let inv = ray.dir.recip();
        let t0 = (lo - ray.origin) * inv;
        let t1 = (hi - ray.origin) * inv;
        let tmin = t0.min(t1).max_element().max(ray.tmin);
        let tmax = t0.max(t1).min_element().min(ray.tmax);
        if !(tmin <= tmax) {
            return false;
        }
        let p = ray.at(tmin);
        let res = g.res as i32;
        let mut v = ((p - lo) / s)
            .floor()
            .as_ivec3()
            .clamp(glam::IVec3::ZERO, glam::IVec3::splat(res - 1));
        let step = ray.dir.signum().as_ivec3();
        let next_boundary = |i: i32, axis: usize| -> f32 {
            let b = lo[axis] + (i + if ray.dir[axis] > 0.0 { 1 } else { 0 }) as f32 * s;
            (b - ray.origin[axis]) * inv[axis]
        };
        let mut t_next = Vec3::new(
            next_boundary(v.x, 0),
            next_boundary(v.y, 1),
            next_boundary(v.z, 2),
        );
        let delta = (Vec3::splat(s) * inv).abs();
        let mut t = tmin;
        for _ in 0..(3 * g.res + 3) {
            let t_exit = t_next.min_element().min(tmax);
            if let Some(e) = self.primitives.get(&morton3(v.as_uvec3())) {
                if let Some((e0, e1)) = ellipsoid_interval(e, ray.origin, ray.dir) {
                    if e0.max(t) <= e1.min(t_exit) {
                        return true;
                    }
                }
            }
            if t_exit >= tmax {
                return false;
            }
            // Step along the axis whose boundary comes first.
            let axis = if t_next.x <= t_next.y && t_next.x <= t_next.z {
                0
            } else if t_next.y <= t_next.z {
                1
            } else {
                2
            };
            t = t_next[axis];
            v[axis] += step[axis];
            if v[axis] < 0 || v[axis] >= res || step[axis] == 0 {
                return false;
            }
            t_next[axis] += delta[axis];
        }
        false
    }
}

/// The outward unit normal of a face direction (0..6: −x, +x, −y, +y, −z, +z).
pub fn face_normal(dir: u8) -> Vec3 {
    let axis = (dir / 2) as usize;
    let mut n = Vec3::ZERO;
    n[axis] = if dir % 2 == 0 { -1.0 } else { 1.0 };
    n
}

/// The ABV map of one face.
#[derive(Clone, Debug)]
pub struct AbvMap {
    /// `res × res` concentric cells over the inward hemisphere, values in [0, 1]; cells where no
    /// ray met a primitive hold 1 (no P⁺: the runtime never reads them).
    pub values: Vec<f32>,
    /// Rays per cell that met a primitive (0 marks an undefined cell).
    pub hits: Vec<u32>,
    /// Rays traced (primitive tests and occlusion rays).
    pub traced: u64,
}

/// Computes the ABV map of one face with `rays_per_cell` stratified rays per direction cell.
pub fn abv_map(
    level: &PrimitiveLevel,
    accel: &Accel,
    face: Face,
    res: u32,
    rays_per_cell: u32,
    seed: u32,
) -> AbvMap {
    let g = &level.grid;
    let s = g.voxel_size();
    let v = UVec3::new(face.voxel.0, face.voxel.1, face.voxel.2);
    let (vlo, _) = g.voxel_bounds(v);
    let n = face_normal(face.dir);
    let axis = (face.dir / 2) as usize;
    // The face's plane and its two in-plane axes.
    let mut corner = vlo;
    if face.dir % 2 == 1 {
        corner[axis] += s;
    }
    let (a1, a2) = ((axis + 1) % 3, (axis + 2) % 3);
    let inward = Frame::from_z(-n);
    let cells = (res * res) as usize;
    let mut hit = vec![0u32; cells];
    let mut escape = vec![0u32; cells];
    let mut traced = 0u64;
    let total = cells as u32 * rays_per_cell;
    for k in 0..total {
        // Stratify directions by cell, jitter inside it; origins by a second sequence.
        let cell = k / rays_per_cell;
        let j = sobol_2d(k, seed);
        let u = Vec2::new(
            ((cell % res) as f32 + j.x) / res as f32,
            ((cell / res) as f32 + j.y) / res as f32,
        );
        let d = inward.to_world(concentric_square_to_hemisphere(u));
        let o2 = sobol_2d(k, seed ^ 0x9e37_79b9);
        let mut o = corner;
        o[a1] += o2.x * s;
        o[a2] += o2.y * s;
        // Start just outside the face.
        let ray = Ray::new(o + n * (1e-4 * s), d);
        traced += 1;
        if level.hits(&ray) {
            hit[grid_cell(u, res) as usize] += 1;
            traced += 1;
            if !accel.occluded(&ray) {
                escape[grid_cell(u, res) as usize] += 1;
            }
        }
    }
    let values = hit
        .iter()
        .zip(&escape)
        .map(|(&h, &e)| if h > 0 { e as f32 / h as f32 } else { 1.0 })
        .collect();
    AbvMap {
        values,
        hits: hit,
        traced,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::boundary::{boundary_faces, UVec3Key};
    use crate::bake::primitive::fit_ellipsoid;
    use crate::bake::sampling::{pieces_by_voxel, sample_voxel};
    use crate::bake::voxelize::demorton3;
    use crate::gen::glb::{MaterialData, SceneData};
    use crate::gen::shapes;
    use std::collections::BTreeSet;

    fn level_of(scene: &crate::scene::Scene, grid: Grid) -> (PrimitiveLevel, BTreeSet<UVec3Key>) {
        let pieces = pieces_by_voxel(scene, &grid);
        let mut prims = HashMap::new();
        let mut occ = BTreeSet::new();
        for (k, list) in &pieces {
            let s = sample_voxel(scene, list, 64, *k as u32);
            let pts: Vec<Vec3> = s.iter().map(|p| p.position).collect();
            if let Some(e) = fit_ellipsoid(&pts, 1e-3 * grid.voxel_size()) {
                prims.insert(*k, e);
                occ.insert(UVec3Key::from(demorton3(*k)));
            }
        }
        (PrimitiveLevel::new(grid, prims), occ)
    }

    /// A face looking onto an opaque wall: every ray that meets the wall's primitives is
    /// blocked by the wall, so the ABV is 0 wherever it is defined.
    #[test]
    fn wall_blocks_everything() {
        // A wall in the plane z = 0 and a small cube in front of it at z = 0.6.
        let mut wall = shapes::quad(Vec3::new(-1.0, -1.0, 0.0), Vec3::X * 2.0, Vec3::Y * 2.0, 4);
        wall.append(&shapes::cuboid(
            Vec3::new(0.0, 0.0, 0.6),
            Vec3::splat(0.05),
            1,
        ));
        let scene =
            SceneData::single(wall, MaterialData::new("wall", [0.5; 3], 0.0, 1.0)).to_scene();
        let accel = Accel::build(&scene);
        let (lo, hi) = scene.bounds();
        let grid = Grid::around(lo, hi, 8);
        let (level, occ) = level_of(&scene, grid);
        let faces = boundary_faces(&occ, 8);
        // A +z face of a wall voxel away from the cube: it looks down (−z) onto the wall.
        let wall_face = faces
            .iter()
            .find(|f| {
                f.dir == 5 && {
                    let (vlo, _) = grid.voxel_bounds(UVec3::new(f.voxel.0, f.voxel.1, f.voxel.2));
                    vlo.z < 0.0 && vlo.x < -0.5
                }
            })
            .copied()
            .expect("a wall face");
        let m = abv_map(&level, &accel, wall_face, 16, 2, 1);
        assert!(m.traced > 0);
        let defined: Vec<f32> = m
            .values
            .iter()
            .zip(&m.hits)
            .filter(|(_, &h)| h > 0)
            .map(|(v, _)| *v)
            .collect();
        assert!(
            defined.len() > 100,
            "most directions see the wall: {}",
            defined.len()
        );
        assert!(defined.iter().all(|&v| v == 0.0), "{defined:?}");
    }

    /// A face looking onto one layer of thin flat strips (width w every p, in one plane): any
    /// direction crossing the layer inside a primitive is blocked with probability w/p, so the
    /// ABV is 1 − w/p = 0.6 in every defined direction. The P⁺-weighted mean over the map, from
    /// ~12k rays that meet the layer (standard error 0.0044), must be within 0.02.
    #[test]
    fn strips_let_through_one_minus_coverage() {
        let (w, p) = (0.02f32, 0.05f32);
        let mut strips = crate::gen::glb::MeshData::default();
        let n = (2.0 / p) as usize;
        for i in 0..n {
            let x0 = -1.0 + i as f32 * p;
            strips.append(&shapes::quad(
                Vec3::new(x0, -1.0, 0.013),
                Vec3::X * w,
                Vec3::Y * 2.0,
                1,
            ));
        }
        // Frame the layer in a cube so that the strips sit inside one layer of voxels.
        strips.append(&shapes::quad(
            Vec3::new(-1.0, -1.0, 1.0),
            Vec3::X * 0.001,
            Vec3::Y * 0.001,
            1,
        ));
        let scene =
            SceneData::single(strips, MaterialData::new("strips", [0.5; 3], 0.0, 1.0)).to_scene();
        let accel = Accel::build(&scene);
        let grid = Grid {
            origin: Vec3::new(-1.0, -1.0, -0.5),
            size: 2.0,
            res: 8,
        };
        let (level, occ) = level_of(&scene, grid);
        let faces = boundary_faces(&occ, 8);
        // A +z face of a layer voxel in the middle of the layer, looking down through it.
        let face = faces
            .iter()
            .find(|f| f.dir == 5 && f.voxel.0 == 3 && f.voxel.1 == 3)
            .copied()
            .expect("a face above the layer");
        let m = abv_map(&level, &accel, face, 16, 64, 3);
        // Weighted by the P⁺ rays of each cell.
        let (mut num, mut den) = (0f32, 0f32);
        for (v, &h) in m.values.iter().zip(&m.hits) {
            num += v * h as f32;
            den += h as f32;
        }
        assert!(den > 10_000.0, "{den} rays met the layer");
        let mean = num / den;
        assert!(
            (mean - (1.0 - w / p)).abs() < 0.02,
            "mean ABV {mean}, expected {}",
            1.0 - w / p
        );
    }

    /// A ray missing every primitive, and the DDA on a diagonal ray through a filled grid.
    #[test]
    fn dda_finds_primitives() {
        let grid = Grid {
            origin: Vec3::ZERO,
            size: 4.0,
            res: 4,
        };
        let mut prims = HashMap::new();
        prims.insert(
            morton3(UVec3::new(3, 3, 3)),
            Ellipsoid {
                center: Vec3::splat(3.5),
                axes: glam::Mat3::from_diagonal(Vec3::splat(0.4)),
            },
        );
        let level = PrimitiveLevel::new(grid, prims);
        assert!(level.hits(&Ray::new(Vec3::splat(-1.0), Vec3::ONE.normalize())));
        assert!(!level.hits(&Ray::new(Vec3::new(-1.0, 0.5, 0.5), Vec3::X)));
        // Through the voxel but outside its ellipsoid (corner region).
        assert!(!level.hits(&Ray::new(Vec3::new(3.05, 3.05, -1.0), Vec3::Z)));
    }
}
