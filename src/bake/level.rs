//! One level of the bake in memory: every non-empty voxel's statistics (ABSDF inputs,
//! truncated ellipsoid, interior visibility as a sparse Haar tree) and every boundary face's
//! visibility tree. Voxels are processed in parallel with rayon, each with seeds derived from
//! its Morton key, so the result does not depend on the thread count.

use std::collections::{BTreeSet, HashMap};

use glam::Vec3;
use rayon::prelude::*;

use super::boundary::{boundary_faces, Face, UVec3Key};
use super::boundary_visibility::{abv_map, PrimitiveLevel};
use super::primitive::{fit_ellipsoid, Ellipsoid};
use super::sampling::{pieces_by_voxel, sample_voxel};
use super::visibility::aiv_map;
use super::voxelize::{demorton3, Grid};
use crate::absdf::estimate::{estimate, EstimateSettings};
use crate::absdf::VoxelAppearance;
use crate::math::haar::{forward, truncate, SparseHaar};
use crate::scene::Scene;
use crate::trace::Accel;

/// Settings of one level's bake.
#[derive(Clone, Copy, Debug)]
pub struct LevelSettings {
    /// Surface samples per voxel at this level.
    pub samples_per_voxel: u32,
    /// Interior-visibility rays per surface sample.
    pub aiv_rays: u32,
    pub aiv_res: u32,
    pub abv_res: u32,
    /// Boundary-visibility rays per direction cell.
    pub abv_rays: u32,
    /// Fraction of wavelet coefficients kept at most, and detail energy to keep.
    pub keep: f32,
    pub energy: f32,
    pub estimate: EstimateSettings,
}

impl Default for LevelSettings {
    fn default() -> Self {
        LevelSettings {
            samples_per_voxel: 64,
            aiv_rays: 16,
            aiv_res: 32,
            abv_res: 64,
            abv_rays: 1,
            keep: 0.10,
            energy: 0.95,
            estimate: EstimateSettings::default(),
        }
    }
}

/// A voxel's baked data.
#[derive(Clone, Debug, PartialEq)]
pub struct VoxelData {
    pub key: u64,
    /// Surface area inside the voxel (world units²).
    pub area: f64,
    /// Fraction of that area that exists after cut-outs.
    pub coverage: f32,
    pub appearance: VoxelAppearance,
    pub ellipsoid: Ellipsoid,
    pub aiv: SparseHaar,
}

/// A boundary face's baked data.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceData {
    pub face: Face,
    pub abv: SparseHaar,
}

/// One baked level.
#[derive(Clone, Debug, PartialEq)]
pub struct LevelData {
    pub grid: Grid,
    /// Sorted by Morton key.
    pub voxels: Vec<VoxelData>,
    pub faces: Vec<FaceData>,
    /// Rays traced for the interior and boundary visibility.
    pub rays: u64,
}

fn compress(map: &[f32], res: u32, keep: f32, energy: f32) -> SparseHaar {
    let (c, mut d) = forward(map, res as usize);
    truncate(c, &mut d, keep, energy);
    SparseHaar::new(c, &d, res as usize)
}

/// Bakes one level of `scene` on `grid`.
pub fn bake_level(scene: &Scene, accel: &Accel, grid: Grid, s: &LevelSettings) -> LevelData {
    let pieces = pieces_by_voxel(scene, &grid);
    let list: Vec<(u64, Vec<super::sampling::Piece>)> = pieces.into_iter().collect();
    let min_extent = 1e-3 * grid.voxel_size();
    let results: Vec<(Option<VoxelData>, u64)> = list
        .par_iter()
        .map(|(key, pieces)| {
            let area: f64 = pieces.iter().map(|p| p.area).sum();
            let seed = (*key as u32) ^ ((*key >> 32) as u32).rotate_left(16);
            let samples = sample_voxel(scene, pieces, s.samples_per_voxel, seed);
            let surf: Vec<_> = samples.iter().map(|p| p.surface).collect();
            let coverage: f32 = surf.iter().map(|x| x.weight).sum();
            let Some(appearance) = estimate(&surf, &s.estimate) else {
                return (None, 0);
            };
            let pts: Vec<Vec3> = samples.iter().map(|p| p.position).collect();
            let Some(ellipsoid) = fit_ellipsoid(&pts, min_extent) else {
                return (None, 0);
            };
            let (map, rays) = aiv_map(accel, &samples, s.aiv_res, s.aiv_rays, seed);
            let aiv = compress(&map, s.aiv_res, s.keep, s.energy);
            (
                Some(VoxelData {
                    key: *key,
                    area,
                    coverage,
                    appearance,
                    ellipsoid,
                    aiv,
                }),
                rays,
            )
        })
        .collect();
    let mut rays = 0;
    let mut voxels = Vec::with_capacity(results.len());
    for (v, r) in results {
        rays += r;
        voxels.extend(v);
    }
    // Boundary faces and their visibility.
    let occupied: BTreeSet<UVec3Key> = voxels
        .iter()
        .map(|v| UVec3Key::from(demorton3(v.key)))
        .collect();
    let faces = boundary_faces(&occupied, grid.res);
    let level = PrimitiveLevel {
        grid,
        primitives: voxels
            .iter()
            .map(|v| (v.key, v.ellipsoid))
            .collect::<HashMap<_, _>>(),
    };
    let face_results: Vec<(FaceData, u64)> = faces
        .par_iter()
        .enumerate()
        .map(|(i, f)| {
            let m = abv_map(&level, accel, *f, s.abv_res, s.abv_rays, i as u32);
            (
                FaceData {
                    face: *f,
                    abv: compress(&m.values, s.abv_res, s.keep, s.energy),
                },
                m.traced,
            )
        })
        .collect();
    let faces = face_results.iter().map(|(f, _)| f.clone()).collect();
    rays += face_results.iter().map(|(_, r)| r).sum::<u64>();
    LevelData {
        grid,
        voxels,
        faces,
        rays,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gen::{generate, GenSettings};

    /// The same scene and settings give the same level with 1 and 2 threads.
    #[test]
    fn deterministic_across_threads() {
        let scene = generate(
            "foliage",
            &GenSettings {
                triangles: 600,
                ..Default::default()
            },
        )
        .unwrap()
        .to_scene();
        let accel = Accel::build(&scene);
        let (lo, hi) = scene.bounds();
        let grid = Grid::around(lo, hi, 4);
        let s = LevelSettings {
            samples_per_voxel: 32,
            aiv_rays: 4,
            abv_res: 16,
            ..Default::default()
        };
        let a = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| bake_level(&scene, &accel, grid, &s));
        let b = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap()
            .install(|| bake_level(&scene, &accel, grid, &s));
        assert_eq!(a, b);
        assert!(!a.voxels.is_empty() && !a.faces.is_empty() && a.rays > 0);
        // Areas add up to the scene's, less the voxels whose every sample was cut out (they
        // hold no surface and are not kept).
        let total: f64 = a.voxels.iter().map(|v| v.area).sum();
        let world = scene.world_area();
        assert!(
            total <= world * (1.0 + 1e-6) && total > 0.99 * world,
            "{total} vs {world}"
        );
        // Cut-out leaves: some voxels are partly transparent.
        assert!(a.voxels.iter().any(|v| v.coverage < 0.95));
    }
}
