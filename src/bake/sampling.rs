//! Surface sampling inside voxels (paper §7.1): area-proportional, low-discrepancy points on the
//! part of each triangle that lies in the voxel, with the triangle's shading normal and material
//! evaluated at the point, and alpha cut-outs honoured (a cut-out point is dropped, so a voxel's
//! samples describe only the surface that exists).

use glam::{DVec3, UVec3, Vec2, Vec3};

use crate::absdf::estimate::SurfaceSample;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::sampling::square_to_triangle;
use crate::scene::Scene;
use crate::spatial::Grid;

/// A piece of one triangle inside one voxel.
#[derive(Clone, Debug)]
pub struct Piece {
    /// Index of the scene instance the triangle belongs to.
    pub instance: u32,
    /// Index of the triangle in its mesh.
    pub triangle: u32,
    /// The clipped polygon, world space.
    pub polygon: Vec<Vec3>,
    /// Its area (world units²).
    pub area: f64,
}

/// A sampled point with everything the per-voxel statistics need.
#[derive(Clone, Copy, Debug)]
pub struct PointSample {
    /// World-space position.
    pub position: Vec3,
    /// Unit geometric normal of the triangle (for offsetting rays off the surface).
    pub geometric_normal: Vec3,
    /// Normal, material and area weight for the statistics.
    pub surface: SurfaceSample,
}

/// Barycentric weights (of vertices 1 and 2) of point `p` in triangle `t` (least squares in the
/// triangle's plane).
fn barycentric(t: [Vec3; 3], p: Vec3) -> Vec2 {
    let (a, b, c) = (t[0].as_dvec3(), t[1].as_dvec3(), t[2].as_dvec3());
    let (e1, e2, d) = (b - a, c - a, p.as_dvec3() - a);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (r1, r2) = (d.dot(e1), d.dot(e2));
    let det = d11 * d22 - d12 * d12;
    if det.abs() < 1e-300 {
        return Vec2::ZERO;
    }
    Vec2::new(
        ((d22 * r1 - d12 * r2) / det) as f32,
        ((d11 * r2 - d12 * r1) / det) as f32,
    )
}

/// Draws `n` points over the pieces of a voxel, each piece getting a share proportional to its
/// area (largest-remainder rounding, so the total is exactly `n`), points placed by a scrambled
/// Sobol sequence over a fan triangulation of the piece. Each point's weight is its share of the
/// voxel's area (the weights of all drawn points sum to one). `seed` decorrelates voxels.
/// Cut-out points are dropped, so the weights left sum to the fraction of surface that exists.
pub fn sample_voxel(scene: &Scene, pieces: &[Piece], n: u32, seed: u32) -> Vec<PointSample> {
    let total: f64 = pieces.iter().map(|p| p.area).sum();
    if !(total > 0.0) || n == 0 {
        return Vec::new();
    }
    // Largest-remainder apportionment.
    let quotas: Vec<f64> = pieces.iter().map(|p| p.area / total * n as f64).collect();
    let mut counts: Vec<u32> = quotas.iter().map(|q| q.floor() as u32).collect();
    let mut left = n - counts.iter().sum::<u32>();
    let mut order: Vec<usize> = (0..pieces.len()).collect();
    order.sort_by(|&a, &b| {
        (quotas[b] - quotas[b].floor())
            .total_cmp(&(quotas[a] - quotas[a].floor()))
            .then(a.cmp(&b))
    });
    for &i in order.iter().cycle().take(pieces.len().max(1) * 2) {
        if left == 0 {
            break;
        }
        counts[i] += 1;
        left -= 1;
    }
    // Pieces too small to get a sample hand their area to the others: the weights of the
    // drawn points sum to one, and cut-out points that are dropped lower the sum to the
    // fraction of the voxel's surface that exists.
    let assigned: f64 = pieces
        .iter()
        .zip(&counts)
        .filter(|(_, &c)| c > 0)
        .map(|(p, _)| p.area)
        .sum();
    let mut out = Vec::with_capacity(n as usize);
    let mut index = 0u32;
    for (piece, &count) in pieces.iter().zip(&counts) {
        if count == 0 || piece.polygon.len() < 3 {
            continue;
        }
        let inst = &scene.instances[piece.instance as usize];
        let mesh = &scene.meshes[inst.mesh as usize];
        let Some(material) = scene.materials.get(mesh.material as usize) else {
            continue;
        };
        let world_tri = mesh
            .triangle(piece.triangle as usize)
            .map(|p| inst.transform.transform_point3(p));
        let ng = (world_tri[1] - world_tri[0])
            .cross(world_tri[2] - world_tri[0])
            .normalize_or(Vec3::Z);
        let normal_matrix = glam::Mat3::from(inst.transform.matrix3)
            .inverse()
            .transpose();
        // Fan triangulation and its cumulative areas.
        let fan: Vec<[Vec3; 3]> = (1..piece.polygon.len() - 1)
            .map(|k| [piece.polygon[0], piece.polygon[k], piece.polygon[k + 1]])
            .collect();
        let areas: Vec<f64> = fan
            .iter()
            .map(|t| {
                0.5 * (t[1] - t[0])
                    .as_dvec3()
                    .cross((t[2] - t[0]).as_dvec3())
                    .length()
            })
            .collect();
        let fan_total: f64 = areas.iter().sum();
        if !(fan_total > 0.0) {
            continue;
        }
        let weight = (piece.area / assigned / count as f64) as f32;
        let [i0, i1, i2] = mesh.triangles[piece.triangle as usize];
        for _ in 0..count {
            let u = sobol_2d(index, seed);
            index += 1;
            // Pick a fan triangle by area with u.x, reuse the remainder.
            let mut x = u.x as f64 * fan_total;
            let mut j = 0;
            while j + 1 < fan.len() && x >= areas[j] {
                x -= areas[j];
                j += 1;
            }
            let ux = (x / areas[j].max(1e-300)).clamp(0.0, 1.0 - 1e-7) as f32;
            let b = square_to_triangle(Vec2::new(ux, u.y));
            let t = fan[j];
            let p = t[0] * (1.0 - b.x - b.y) + t[1] * b.x + t[2] * b.y;
            let bc = barycentric(world_tri, p);
            let b0 = 1.0 - bc.x - bc.y;
            let uv = if mesh.uvs.is_empty() {
                Vec2::ZERO
            } else {
                mesh.uvs[i0 as usize] * b0
                    + mesh.uvs[i1 as usize] * bc.x
                    + mesh.uvs[i2 as usize] * bc.y
            };
            if !material.is_opaque_at(&scene.textures, uv) {
                continue;
            }
            let ns = if mesh.normals.is_empty() {
                ng
            } else {
                let n = mesh.normals[i0 as usize] * b0
                    + mesh.normals[i1 as usize] * bc.x
                    + mesh.normals[i2 as usize] * bc.y;
                (normal_matrix * n).try_normalize().unwrap_or(ng)
            };
            out.push(PointSample {
                position: p,
                geometric_normal: ng,
                surface: SurfaceSample {
                    normal: ns,
                    params: material.eval(&scene.textures, uv),
                    weight,
                },
            });
        }
    }
    out
}

/// The pieces of every triangle in the voxels of a level, grouped by voxel (Morton order).
pub fn pieces_by_voxel(scene: &Scene, grid: &Grid) -> std::collections::BTreeMap<u64, Vec<Piece>> {
    let mut out: std::collections::BTreeMap<u64, Vec<Piece>> = std::collections::BTreeMap::new();
    let s = grid.voxel_size() as f64;
    let o = grid.origin.as_dvec3();
    for (ii, inst) in scene.instances.iter().enumerate() {
        let m = &scene.meshes[inst.mesh as usize];
        for t in 0..m.triangles.len() {
            let tri = m.triangle(t).map(|p| inst.transform.transform_point3(p));
            super::voxelize::clip_triangle_polygons(
                grid,
                tri,
                |v: UVec3, poly: &[DVec3], area: f64| {
                    out.entry(crate::spatial::morton3(v))
                        .or_default()
                        .push(Piece {
                            instance: ii as u32,
                            triangle: t as u32,
                            polygon: poly.iter().map(|q| (o + *q * s).as_vec3()).collect(),
                            area,
                        });
                },
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gen::{generate, GenSettings};

    /// Every sample lies in its voxel; a plane's samples carry its normal and the weights of a
    /// voxel sum to one.
    #[test]
    fn samples_stay_in_their_voxel() {
        let scene = generate(
            "plane45",
            &GenSettings {
                triangles: 200,
                ..Default::default()
            },
        )
        .unwrap()
        .to_scene();
        let (lo, hi) = scene.bounds();
        let grid = Grid::around(lo, hi, 8);
        let pieces = pieces_by_voxel(&scene, &grid);
        assert!(!pieces.is_empty());
        for (key, list) in &pieces {
            let v = crate::spatial::demorton3(*key);
            let (blo, bhi) = grid.voxel_bounds(v);
            let samples = sample_voxel(&scene, list, 64, *key as u32);
            assert_eq!(samples.len(), 64);
            let wsum: f32 = samples.iter().map(|s| s.surface.weight).sum();
            assert!((wsum - 1.0).abs() < 1e-4, "{wsum}");
            let eps = 1e-4 * grid.size;
            for s in &samples {
                assert!(
                    s.position.cmpge(blo - eps).all() && s.position.cmple(bhi + eps).all(),
                    "{} outside {blo}..{bhi}",
                    s.position
                );
                // plane45: normal (±sin45°, 0, ±cos45°).
                assert!(
                    (s.surface.normal.y).abs() < 1e-4
                        && (s.surface.normal.x.abs() - std::f32::consts::FRAC_1_SQRT_2).abs()
                            < 1e-3
                );
            }
        }
    }

    /// Leaves with cut-outs: samples land only where the leaf exists.
    #[test]
    fn cutouts_are_honoured() {
        let scene = generate(
            "foliage",
            &GenSettings {
                triangles: 400,
                ..Default::default()
            },
        )
        .unwrap()
        .to_scene();
        let (lo, hi) = scene.bounds();
        let grid = Grid::around(lo, hi, 2);
        let pieces = pieces_by_voxel(&scene, &grid);
        let mut dropped = 0usize;
        for (key, list) in &pieces {
            let s = sample_voxel(&scene, list, 256, *key as u32);
            dropped += 256 - s.len();
        }
        // The leaf mask covers ~60% of each quad: a clear fraction of samples is dropped.
        assert!(dropped > 100, "{dropped}");
    }
}
