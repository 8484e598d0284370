//! One level of the bake in memory: every non-empty voxel's statistics (ABSDF inputs,
//! truncated ellipsoid, interior visibility as a sparse Haar tree) and every boundary face's
//! visibility tree. Voxels are processed in parallel with rayon, each with seeds derived from
//! its Morton key, so the result does not depend on the thread count.

use std::collections::BTreeSet;

use glam::Vec3;
use rayon::prelude::*;

use super::boundary::boundary_faces;
use super::boundary_visibility::{abv_map, PrimitiveLevel};
use super::primitive::fit_ellipsoid_bounding;
use super::sampling::{pieces_by_voxel, sample_voxel};
use super::visibility::{aiv_map, aiv_rays_per_cell, exposed_weight, map_noise_sigma};
use crate::absdf::estimate::{estimate, usable, EstimateSettings, SurfaceSample};
use crate::format::{FaceData, LevelData, VoxelData};
use crate::math::haar::{forward, shrink, truncate, SparseHaar};
use crate::scene::Scene;
use crate::spatial::{demorton3, morton3, Ellipsoid, Face, Grid, UVec3Key};
use crate::trace::Accel;

/// Settings of one level's bake.
#[derive(Clone, Copy, Debug)]
pub struct LevelSettings {
    /// False at a visibility level ([`super::BakeSettings::visibility_levels`]): no AIV rays, a
    /// constant AIV of 1 and constant moments; the geometry and the faces as at any level.
    pub shade: bool,
    /// Surface samples per voxel at this level.
    pub samples_per_voxel: u32,
    /// Interior-visibility rays per surface sample.
    pub aiv_rays: u32,
    /// Fewest rays an AIV cell's estimate rests on; 0: chosen per voxel
    /// ([`super::visibility::aiv_map`]).
    pub aiv_min_rays: u32,
    /// Resolution of the AIV map (a sphere map of this many cells a side, §6.2).
    pub aiv_res: u32,
    /// Resolution of the ABV maps of the boundary faces (hemisphere maps, Eq. 26).
    pub abv_res: u32,
    /// Boundary-visibility rays per block of `abv_stride²` direction cells.
    pub abv_rays: u32,
    /// Side of the block of ABV direction cells that shares `abv_rays`.
    pub abv_stride: u32,
    /// ABV cells may average a window of cells centred on them ([`super::BakeSettings::abv_windows`]).
    pub abv_windows: bool,
    /// Fraction of wavelet coefficients kept at most.
    pub keep: f32,
    /// Fraction of the detail energy the kept wavelet coefficients must hold (paper Table 2).
    pub energy: f32,
    /// Shrink the Monte Carlo noise out of the wavelet coefficients before truncation.
    pub denoise: bool,
    /// How the per-voxel statistics are estimated from the surface samples (Eq. 7–10, 23).
    pub estimate: EstimateSettings,
}

/// The default bake's finest level ([`super::BakeSettings::level`]), with 64 surface samples a
/// voxel: one source for the defaults, not a second copy of them.
impl Default for LevelSettings {
    fn default() -> Self {
        let d = super::BakeSettings::default();
        LevelSettings {
            samples_per_voxel: 64,
            ..d.level(d.max_res)
        }
    }
}

/// Haar transform, shrinkage of the Monte Carlo noise (`rays_per_cell` rays estimated each
/// pixel, a binomial proportion: a threshold of `denoise` times its σ, [`map_noise_sigma`];
/// skipped when the level's `denoise` is off), truncation.
fn compress(
    map: &[f32],
    res: u32,
    rays_per_cell: f32,
    denoise: f32,
    s: &LevelSettings,
) -> SparseHaar {
    let (c, mut d) = forward(map, res as usize);
    if s.denoise && denoise > 0.0 {
        let mean = (map.iter().map(|&v| v as f64).sum::<f64>() / map.len().max(1) as f64) as f32;
        shrink(
            &mut d,
            denoise * map_noise_sigma(mean, rays_per_cell),
            res as usize,
        );
    }
    truncate(c, &mut d, s.keep, s.energy);
    SparseHaar::new(c, &d, res as usize)
}

/// The seed of a voxel's samples and rays, from its Morton key: the same on every thread and
/// every farm shard (tools that rerun the bake's estimators use it too).
pub fn voxel_seed(key: u64) -> u32 {
    (key as u32) ^ ((key >> 32) as u32).rotate_left(16)
}

/// The surface samples of a voxel, their coverage and the ellipsoid: everything of
/// [`bake_voxel`] before the AIV. No ellipsoid where no sample is usable by the ABSDF
/// ([`usable`]): `bake_voxel` keeps no such voxel.
fn voxel_statistics(
    scene: &Scene,
    grid: &Grid,
    pieces: &[super::sampling::Piece],
    s: &LevelSettings,
    seed: u32,
) -> (Vec<super::sampling::PointSample>, f32, Option<Ellipsoid>) {
    let samples = sample_voxel(scene, pieces, s.samples_per_voxel, seed);
    let coverage: f32 = samples.iter().map(|p| p.surface.weight).sum();
    if !samples.iter().any(|p| usable(&p.surface)) {
        return (samples, coverage, None);
    }
    let pts: Vec<Vec3> = samples.iter().map(|p| p.position).collect();
    let corners: Vec<Vec3> = pieces
        .iter()
        .flat_map(|p| p.polygon.iter().copied())
        .collect();
    let ellipsoid = fit_ellipsoid_bounding(&pts, &corners, 1e-3 * grid.voxel_size());
    (samples, coverage, ellipsoid)
}

/// The primitive [`bake_voxel`] would give this voxel (the same seed, samples and fit), without
/// its AIV: `None` where `bake_voxel` keeps no voxel. A sharded bake computes these for the
/// voxels of other shards, whose boundary faces need every primitive of the level.
pub fn voxel_primitive(
    scene: &Scene,
    grid: &Grid,
    key: u64,
    pieces: &[super::sampling::Piece],
    s: &LevelSettings,
) -> Option<Ellipsoid> {
    voxel_statistics(scene, grid, pieces, s, voxel_seed(key)).2
}

/// What baking one voxel cost, and the AIV bandwidth it chose.
#[derive(Clone, Copy, Debug, Default)]
pub struct VoxelCost {
    /// AIV rays traced.
    pub rays: u64,
    /// CPU seconds spent on (sampling + statistics, AIV).
    pub cpu: [f64; 2],
    /// How the AIV cells gathered their rays ([`super::visibility::AivEstimate::bandwidth`]);
    /// `None` where no voxel was kept.
    pub aiv_bandwidth: Option<super::visibility::Bandwidth>,
}

/// Bakes one voxel from the pieces of surface inside it: samples, the ellipsoid, the AIV tree,
/// and the ABSDF statistics of the samples weighted by how exposed each is (its AIV escape
/// fraction, [`exposed_weight`]). `None` when every sample was cut out (nothing to keep). Also
/// returns what it cost ([`VoxelCost`]).
pub fn bake_voxel(
    scene: &Scene,
    accel: &Accel,
    grid: &Grid,
    key: u64,
    pieces: &[super::sampling::Piece],
    s: &LevelSettings,
) -> (Option<VoxelData>, VoxelCost) {
    let t0 = std::time::Instant::now();
    let area: f64 = pieces.iter().map(|p| p.area).sum();
    let seed = voxel_seed(key);
    let (samples, coverage, ellipsoid) = voxel_statistics(scene, grid, pieces, s, seed);
    let Some(ellipsoid) = ellipsoid else {
        let cost = VoxelCost {
            cpu: [t0.elapsed().as_secs_f64(), 0.0],
            ..Default::default()
        };
        return (None, cost);
    };
    let (appearance, aiv, exposure, cost) = if s.shade {
        let Some(shaded) = interior_statistics(accel, &samples, s, seed, t0) else {
            return (None, VoxelCost::default());
        };
        shaded
    } else {
        // A visibility level: the statistics of the samples as they are (no AIV rays to weigh
        // them by exposure), constant moments (directional ones measured to buy nothing
        // there), a constant AIV of 1 and exposure 1. Readers of 1.7 take the AIV and the
        // exposure from the voxel of the shading level containing it; older readers shade it
        // as it is (without self-shadowing).
        let surface: Vec<SurfaceSample> = samples.iter().map(|p| p.surface).collect();
        let settings = EstimateSettings {
            moment_res: 0,
            ..s.estimate
        };
        let Some(appearance) = estimate(&surface, &settings) else {
            return (None, VoxelCost::default());
        };
        let res = s.aiv_res.max(1);
        let aiv = compress(&vec![1.0; (res * res) as usize], res, 1.0, 0.0, s);
        let cost = VoxelCost {
            cpu: [t0.elapsed().as_secs_f64(), 0.0],
            ..Default::default()
        };
        (appearance, aiv, 1.0, cost)
    };
    (
        Some(VoxelData {
            key,
            area,
            coverage: coverage.min(1.0),
            appearance,
            ellipsoid,
            aiv,
            exposure,
        }),
        cost,
    )
}

/// A shaded voxel's interior visibility (its AIV rays, map and exposure) and the ABSDF
/// statistics of its samples weighted by how exposed each is; `None` when no sample is usable.
fn interior_statistics(
    accel: &Accel,
    samples: &[super::sampling::PointSample],
    s: &LevelSettings,
    seed: u32,
    t0: std::time::Instant,
) -> Option<(crate::absdf::VoxelAppearance, SparseHaar, f32, VoxelCost)> {
    let t1 = std::time::Instant::now();
    let est = aiv_map(
        accel,
        samples,
        s.aiv_res,
        s.aiv_rays,
        s.aiv_min_rays,
        s.denoise,
        seed,
    );
    let t2 = std::time::Instant::now();
    let exposed: Vec<SurfaceSample> = samples
        .iter()
        .zip(&est.sample_escape)
        .map(|(p, &e)| SurfaceSample {
            weight: p.surface.weight * exposed_weight(e),
            ..p.surface
        })
        .collect();
    // Some sample is usable (the ellipsoid says so), and the weights stay positive.
    let appearance = estimate(&exposed, &s.estimate)?;
    let per_cell = aiv_rays_per_cell(est.rays, s.aiv_res);
    let aiv = compress(&est.map, s.aiv_res, per_cell, est.denoise, s);
    let cost = VoxelCost {
        rays: est.rays,
        cpu: [
            (t1 - t0).as_secs_f64() + t2.elapsed().as_secs_f64(),
            (t2 - t1).as_secs_f64(),
        ],
        aiv_bandwidth: Some(est.bandwidth),
    };
    // Exposure quantized to 1/256 so that stored and baked values compare equal.
    Some((appearance, aiv, quantize_exposure(est.exposure), cost))
}

/// Exposure as stored: multiples of 1/256 (exactly representable in f32), 1 when within 1/512.
pub fn quantize_exposure(e: f32) -> f32 {
    use super::visibility::MIN_EXPOSURE;
    ((e.clamp(MIN_EXPOSURE, 1.0) * 256.0).round() / 256.0).clamp(MIN_EXPOSURE, 1.0)
}

/// Bakes one boundary face's ABV tree; returns it with the rays traced and the bandwidth its
/// map chose (the fewest P⁺ rays a cell rests on).
pub fn bake_face(
    level: &PrimitiveLevel,
    accel: &Accel,
    face: Face,
    s: &LevelSettings,
) -> (FaceData, u64, super::visibility::Bandwidth) {
    let key = morton3(glam::UVec3::new(face.voxel.0, face.voxel.1, face.voxel.2));
    let seed = (key as u32).wrapping_mul(6) ^ face.dir as u32 ^ ((key >> 32) as u32).rotate_left(7);
    let m = abv_map(
        level,
        accel,
        face,
        s.abv_res,
        s.abv_rays,
        s.abv_stride,
        seed,
        s.abv_windows,
    );
    (
        FaceData {
            face,
            // Pooled over blocks of cells (or centred windows of them), the map's noise is
            // under control already. (Shrinking a window's map at the noise of its rays'
            // average blurs its silhouettes: barrel 64³ RMSE 0.0076, 0.0055 unshrunk.)
            abv: compress(
                &m.values,
                s.abv_res,
                m.rays_per_cell,
                1.0,
                &LevelSettings {
                    denoise: s.denoise && m.bandwidth.min_rays == 1 && !m.bandwidth.cap,
                    ..*s
                },
            ),
        },
        m.traced,
        m.bandwidth,
    )
}

/// The primitives of a baked set of voxels, for the boundary-visibility DDA.
pub fn primitive_level(
    grid: Grid,
    voxels: impl Iterator<Item = (u64, Ellipsoid)>,
) -> PrimitiveLevel {
    PrimitiveLevel::new(grid, voxels)
}

/// The boundary faces of a set of occupied voxel keys, sorted by (Morton key, direction).
pub fn sorted_boundary_faces(keys: impl Iterator<Item = u64>, res: u32) -> Vec<Face> {
    let occupied: BTreeSet<UVec3Key> = keys.map(|k| UVec3Key::from(demorton3(k))).collect();
    let mut faces = boundary_faces(&occupied, res);
    faces.sort_by_key(|f| {
        (
            morton3(glam::UVec3::new(f.voxel.0, f.voxel.1, f.voxel.2)),
            f.dir,
        )
    });
    faces
}

/// Bakes one level of `scene` on `grid`, in memory (the streaming bake of a whole asset is
/// [`super::bake_to_file`]).
pub fn bake_level(scene: &Scene, accel: &Accel, grid: Grid, s: &LevelSettings) -> LevelData {
    let pieces = pieces_by_voxel(scene, &grid);
    let list: Vec<(u64, Vec<super::sampling::Piece>)> = pieces.into_iter().collect();
    let results: Vec<(Option<VoxelData>, VoxelCost)> = list
        .par_iter()
        .map(|(key, pieces)| bake_voxel(scene, accel, &grid, *key, pieces, s))
        .collect();
    let mut rays = 0;
    let mut voxels = Vec::with_capacity(results.len());
    for (v, c) in results {
        rays += c.rays;
        voxels.extend(v);
    }
    let faces = sorted_boundary_faces(voxels.iter().map(|v| v.key), grid.res);
    let level = primitive_level(grid, voxels.iter().map(|v| (v.key, v.ellipsoid)));
    let face_results: Vec<(FaceData, u64, super::visibility::Bandwidth)> = faces
        .par_iter()
        .map(|f| bake_face(&level, accel, *f, s))
        .collect();
    rays += face_results.iter().map(|(_, r, _)| r).sum::<u64>();
    let faces = face_results.into_iter().map(|(f, _, _)| f).collect();
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

    /// A white box with a red box buried inside it, in one voxel: the red faces see nothing
    /// (AIV escape 0), so the ABSDF's albedo is the white box's ([`exposed_weight`]); by area
    /// alone the red box is 14% of the surface and the green channel would be about 0.86.
    #[test]
    fn buried_surfaces_do_not_colour_the_absdf() {
        use crate::gen::glb::{MaterialData, SceneData};
        use crate::gen::shapes::cuboid;
        let mut data = SceneData::single(
            cuboid(Vec3::ZERO, Vec3::splat(0.5), 2),
            MaterialData::new("white", [1.0, 1.0, 1.0], 0.0, 0.5),
        );
        data.meshes[0].push((cuboid(Vec3::ZERO, Vec3::splat(0.2), 2), 1));
        data.materials
            .push(MaterialData::new("red", [1.0, 0.0, 0.0], 0.0, 0.5));
        let scene = data.to_scene();
        let accel = Accel::build(&scene);
        let (lo, hi) = scene.bounds();
        let s = LevelSettings {
            samples_per_voxel: 256,
            aiv_rays: 16,
            ..Default::default()
        };
        let level = bake_level(&scene, &accel, Grid::around(lo, hi, 1), &s);
        assert_eq!(level.voxels.len(), 1);
        let green: Vec<f32> = match &level.voxels[0].appearance.moments {
            crate::absdf::Moments::Constant(m) => vec![m.c.y],
            crate::absdf::Moments::Directional { diffuse, .. } => {
                diffuse.iter().map(|m| m.c.y).collect()
            }
        };
        for g in green {
            assert!(g > 0.99, "green {g}: the buried red box shows");
        }
    }
}
