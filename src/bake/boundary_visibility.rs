//! Aggregated boundary visibility (paper Eq. 26): for a boundary face and each direction of its
//! inward hemisphere (64×64 concentric map), among the rays from the face that hit some
//! primitive of the level (the P⁺ of Eq. 26), the fraction that escapes the real geometry.
//! Primitives are the voxels' truncated ellipsoids, tested by the same
//! [`TruncatedEllipsoid::intersect`] the runtime counts hits with, found along a ray by a BVH
//! over their boxes.

use glam::{IVec3, UVec3, Vec2, Vec3};

use super::visibility::Bandwidth;
use crate::math::frame::Frame;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::rng::Pcg32;
use crate::math::sphere_maps::{
    concentric_square_to_hemisphere, grid_cell, BlockPyramid, CentredWindows,
};
use crate::spatial::{demorton3, face_normal, Dda, Ellipsoid, Face, Grid, TruncatedEllipsoid};
use crate::trace::{Accel, Ray};

/// The primitives of one level, in a BVH (obvhs) over the boxes of the truncated ellipsoids
/// (each ellipsoid's bounding box clipped to its voxel): "does this ray meet any primitive"
/// is an any-hit query. (A 3D DDA over the sparse grid spent most of the bake stepping
/// through empty voxels on the rays that miss.)
pub struct PrimitiveLevel {
    /// The grid of the level.
    pub grid: Grid,
    /// In the BVH's primitive order.
    prims: Vec<TruncatedEllipsoid>,
    bvh: Option<obvhs::cwbvh::CwBvh>,
    /// One bit per voxel of the grid (x fastest): whether it is occupied, and one per cell of
    /// 4³ voxels: whether any of them is ([`PrimitiveLevel::occupied`] crosses empty cells in
    /// one step).
    occupancy: Vec<u64>,
    cells: Vec<u64>,
}

impl PrimitiveLevel {
    /// The level of these (Morton key, ellipsoid) pairs; degenerate ellipsoids are left out.
    pub fn new(grid: Grid, prims: impl IntoIterator<Item = (u64, Ellipsoid)>) -> Self {
        let all: Vec<(u64, Ellipsoid)> = prims.into_iter().collect();
        let res = grid.res as usize;
        let cres = res.div_ceil(4);
        let mut occupancy = vec![0u64; (res * res * res).div_ceil(64)];
        let mut cells = vec![0u64; (cres * cres * cres).div_ceil(64)];
        let set = |bits: &mut Vec<u64>, i: usize| {
            if let Some(w) = bits.get_mut(i / 64) {
                *w |= 1 << (i % 64);
            }
        };
        for (k, _) in &all {
            let v = demorton3(*k);
            let (x, y, z) = (v.x as usize, v.y as usize, v.z as usize);
            set(&mut occupancy, (z * res + y) * res + x);
            set(&mut cells, ((z / 4) * cres + y / 4) * cres + x / 4);
        }
        let list: Vec<(TruncatedEllipsoid, (Vec3, Vec3))> = all
            .into_iter()
            .filter_map(|(k, e)| {
                let (vlo, vhi) = grid.voxel_bounds(demorton3(k));
                let p = TruncatedEllipsoid::new(&e, vlo, vhi)?;
                Some((p, p.bounds()?))
            })
            .collect();
        if list.is_empty() {
            return PrimitiveLevel {
                grid,
                prims: Vec::new(),
                bvh: None,
                occupancy,
                cells,
            };
        }
        let aabbs: Vec<obvhs::aabb::Aabb> = list
            .iter()
            .map(|(_, (lo, hi))| obvhs::aabb::Aabb::new((*lo).into(), (*hi).into()))
            .collect();
        let bvh = obvhs::cwbvh::builder::build_cwbvh(
            &aabbs,
            obvhs::BvhBuildParams::medium_build(),
            &mut std::time::Duration::default(),
        );
        let prims = bvh
            .primitive_indices
            .iter()
            .map(|&i| list[i as usize].0)
            .collect();
        PrimitiveLevel {
            grid,
            prims,
            bvh: Some(bvh),
            occupancy,
            cells,
        }
    }

    /// Whether the ray meets an occupied voxel of the level for t in [ray.tmin, ray.tmax]: a
    /// point of a boundary face from which the ray, followed backwards, meets none is one where
    /// a cone can enter the aggregate in that direction (the runtime's ABV queries).
    pub fn occupied(&self, ray: &Ray) -> bool {
        let g = &self.grid;
        let (lo, hi) = (g.origin, g.origin + Vec3::splat(g.size));
        let inv = ray.dir.recip();
        let (t0, t1) = crate::spatial::box_interval(lo, hi, ray.origin, inv);
        let (t0, t1) = (t0.max(ray.tmin), t1.min(ray.tmax));
        if !(t0 <= t1) {
            return false;
        }
        // The cells of 4³ voxels the ray crosses, in order, and in an occupied one its voxels
        // (the DDA of the runtime's walk, two granularities of it).
        let res = g.res as i32;
        if res % 4 != 0 {
            let mut dda = Dda::new(g, ray.origin, ray.dir, inv, t0, None);
            loop {
                if self.voxel_occupied(dda.v) {
                    return true;
                }
                if dda.t_exit() >= t1 || dda.advance().is_none() {
                    return false;
                }
            }
        }
        let coarse = Grid {
            res: g.res / 4,
            ..*g
        };
        let cres = coarse.res as i32;
        let inv_s = g.res as f32 / g.size;
        let mut cell = Dda::new(&coarse, ray.origin, ray.dir, inv, t0, None);
        let mut t = t0;
        loop {
            let c = cell.v;
            let exit = cell.t_exit().min(t1);
            let i = ((c.z * cres + c.y) * cres + c.x) as usize;
            if self.cells[i / 64] & (1 << (i % 64)) != 0 {
                let p = ray.origin + ray.dir * t - g.origin;
                let lo = c * 4;
                let v = (p * inv_s)
                    .floor()
                    .as_ivec3()
                    .clamp(lo, lo + IVec3::splat(3));
                let mut voxel = cell.child(v);
                loop {
                    if self.voxel_occupied(voxel.v) {
                        return true;
                    }
                    if voxel.t_exit() >= exit || voxel.advance().is_none() {
                        break;
                    }
                }
            }
            if exit >= t1 || cell.advance().is_none() {
                return false;
            }
            t = exit;
        }
    }

    /// Whether voxel `v` (inside the grid) is occupied.
    #[inline]
    fn voxel_occupied(&self, v: IVec3) -> bool {
        let res = self.grid.res as i32;
        let i = ((v.z * res + v.y) * res + v.x) as usize;
        self.occupancy[i / 64] & (1 << (i % 64)) != 0
    }

    /// Number of primitives.
    pub fn len(&self) -> usize {
        self.prims.len()
    }

    /// Whether the level has no primitive.
    pub fn is_empty(&self) -> bool {
        self.prims.is_empty()
    }

    /// Whether the ray meets any truncated ellipsoid (the intersection of a voxel and its
    /// ellipsoid) for t in [ray.tmin, ray.tmax].
    pub fn hits(&self, ray: &Ray) -> bool {
        let Some(bvh) = &self.bvh else {
            return false;
        };
        let inv_d = ray.dir.recip();
        let (o, d) = (ray.origin, ray.dir);
        !bvh.ray_traverse_miss(ray.to_bvh(), |r, id| {
            self.prims[id]
                .intersect(o, d, inv_d, r.tmin, r.tmax)
                .unwrap_or(f32::INFINITY)
        })
    }
}

/// The ABV map of one face.
#[derive(Clone, Debug)]
pub struct AbvMap {
    /// `res × res` concentric cells over the inward hemisphere, values in [0, 1]; cells where no
    /// ray met a primitive hold the average of the smallest enclosing block of cells that some did.
    pub values: Vec<f32>,
    /// Rays per cell that met a primitive (0 marks an undefined cell).
    pub hits: Vec<u32>,
    /// Rays traced (reachability tests, primitive tests and occlusion rays).
    pub traced: u64,
    /// P⁺ rays per cell over the blocks of cells that have any (below one when blocks of
    /// cells share rays): the Monte Carlo noise of the map's defined part.
    pub rays_per_cell: f32,
    /// How a cell's value gathers its P⁺ rays, chosen by cross-validation among
    /// [`ABV_BANDWIDTHS`] (see [`abv_map`]); a block of 1 ray is the per-cell average.
    pub bandwidth: Bandwidth,
}

/// Computes the ABV map of one face: `rays` stratified rays per block of `stride × stride`
/// direction cells (stride 1: per cell; a power of two up to `res`). A block's empty cells take
/// the block's average ([`BlockPyramid`]), so a stride of 2^k traces 4^k times fewer rays and
/// resolves `res / stride` directions across the hemisphere. With `windows`, a cell may also
/// average a window of cells centred on it (`BakeSettings::abv_windows`; see
/// [`ABV_BANDWIDTHS`]).
///
/// Only the points where a cone can enter the aggregate are sampled: the runtime reads a
/// face's ABV where a cone enters the level's first occupied voxel through it, so the cone,
/// followed backwards from the face, meets no occupied voxel. A P⁺ ray whose origin fails
/// that test ([`PrimitiveLevel::occupied`]) is drawn again ([`ABV_REACH_TRIES`] draws, the
/// second in a uniform direction: a cell blocked from the whole face is never read) and is
/// dropped if every draw fails. Eq. 26's average over P⁺ is then the one the runtime's queries see,
/// and no ray goes to directions it never reads; their cells take the fill of their enclosing
/// blocks, which costs few bytes (the maple's default 64³ bake: 0.72× the bytes, the bias of
/// its 64² image −3%, 1.02× the bake time; `docs/src/studies/2026-12-07-reachable-abv.md`). Origins are a
/// scrambled Sobol sequence indexed in Z order of the rays' direction blocks, so that every
/// aligned block of cells that the bandwidths average has its origins stratified over the
/// face.
#[allow(clippy::too_many_arguments)]
pub fn abv_map(
    level: &PrimitiveLevel,
    accel: &Accel,
    face: Face,
    res: u32,
    rays: u32,
    stride: u32,
    seed: u32,
    windows: bool,
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
    let mut fold_hit = [vec![0u32; cells], vec![0u32; cells]];
    let mut fold_escape = [vec![0u32; cells], vec![0u32; cells]];
    let mut traced = 0u64;
    let blocks = (res / stride.clamp(1, res)).max(1);
    let total = blocks * blocks * rays;
    // Directions are stratified by block of cells (every block gets its rays), jittered inside
    // the block from a PCG stream; the origins on the face are stratified across blocks (Sobol
    // in Z order): blocks the bandwidths average then sample the face evenly (the maple's 64³
    // bake: 0.93× the bytes and a 2% lower bias at 64² than with PCG origins).
    let mut rng = Pcg32::new(seed as u64, 0xab5);
    for k in 0..total {
        let block = k / rays;
        let j = rng.next_2d();
        let u = Vec2::new(
            ((block % blocks) as f32 + j.x) / blocks as f32,
            ((block / blocks) as f32 + j.y) / blocks as f32,
        );
        let d = inward.to_world(concentric_square_to_hemisphere(u));
        let (mut u, mut d) = (u, d);
        for attempt in 0..ABV_REACH_TRIES {
            let o2 = if attempt == 0 {
                let (bx, by) = (block % blocks, block / blocks);
                let index = morton2(bx, by) * rays + k % rays;
                sobol_2d(index, seed ^ 0x0a6b_5eed)
            } else {
                // Blocked: another direction, uniform, from another point.
                u = rng.next_2d();
                d = inward.to_world(concentric_square_to_hemisphere(u));
                rng.next_2d()
            };
            let mut o = corner;
            o[a1] += o2.x * s;
            o[a2] += o2.y * s;
            // Start just outside the face.
            let start = o + n * (1e-4 * s);
            let ray = Ray::new(start, d);
            traced += 1;
            if !level.hits(&ray) {
                break;
            }
            // A P⁺ ray: kept if a cone can come in this way (rays outside P⁺ count for
            // nothing, so only these are tested).
            traced += 1;
            if level.occupied(&Ray::new(start, -d)) {
                continue;
            }
            let c = grid_cell(u, res) as usize;
            let f = (k % 2) as usize;
            hit[c] += 1;
            fold_hit[f][c] += 1;
            traced += 1;
            if !accel.occluded(&ray) {
                escape[c] += 1;
                fold_escape[f][c] += 1;
            }
            break;
        }
    }
    // The bandwidth: a cell's value is the average of the smallest enclosing block of cells
    // (itself first) holding at least K P⁺ rays, or of the smallest window of cells centred
    // on it that does, the kind and K chosen per face by two-fold cross-validation over its
    // rays (even and odd ray index), as the AIV's ([`super::visibility`]). A silhouette
    // face sees few P⁺ rays, spread over the hemisphere: a fixed rule (the finest power of two
    // whose reached cells average 16 rays, earlier versions) gave such a face a map of 4² or 8²
    // directions however sharp its visibility, where the held-out rays choose per face between
    // noise and blur (barrel 64³: RMSE 0.0092 -> 0.0081; a fixed 4 rays 0.0086).
    // Cells no P⁺ ray reached take the average of the smallest enclosing block of cells that
    // some did: the runtime reads them wherever its ray meets a primitive that the bake's one
    // ray per cell missed, and a local value is closer than the mean over the hemisphere
    // (chandelier, 32³ level of a 64³ bake: RMSE 0.0224 against 0.0242 with the mean, for
    // 2.44 against 1.43 MiB). A block of `stride²` cells that shared rays is filled so too.
    let (h_sum, e_sum) = (hit.iter().sum::<u32>(), escape.iter().sum::<u32>());
    let fill = if h_sum > 0 {
        e_sum as f32 / h_sum as f32
    } else {
        1.0
    };
    let bandwidth = if h_sum > 1 {
        let candidates = if windows {
            &ABV_BANDWIDTHS[..]
        } else {
            &ABV_BANDWIDTHS[..ABV_BLOCKS]
        };
        cross_validated_bandwidth(&fold_hit, &fold_escape, res, candidates)
    } else {
        ABV_BANDWIDTHS[0]
    };
    let (escape_f, hit_f) = (counts_f64(&escape), counts_f64(&hit));
    let pyramid = BlockPyramid::new(&escape_f, &hit_f, &hit, res);
    let k = bandwidth.min_rays;
    let values = if bandwidth.cap {
        let windows = CentredWindows::new(&escape_f, &hit_f, &hit, res, window_radius(res));
        (0..res * res)
            .map(|i| {
                windows
                    .value(i, k)
                    .unwrap_or_else(|| pyramid.value(i, k, fill))
            })
            .collect()
    } else {
        pyramid.map(k, fill)
    };
    let side = (res / blocks).max(1);
    let mut block_hit = vec![false; (blocks * blocks) as usize];
    for (c, &h) in hit.iter().enumerate() {
        let (x, y) = (c as u32 % res, c as u32 / res);
        block_hit[((y / side) * blocks + x / side) as usize] |= h > 0;
    }
    let covered = block_hit.iter().filter(|&&b| b).count() as u32 * side * side;
    AbvMap {
        values,
        hits: hit,
        traced,
        rays_per_cell: if covered > 0 {
            h_sum as f32 / covered as f32
        } else {
            1.0
        },
        bandwidth,
    }
}

/// Draws of a ray's origin (and, after the first, its direction) until it is one where a cone
/// can enter the aggregate ([`abv_map`]). Two: on the maple's 64³ bake seen at 64² (every ray
/// tested, an earlier variant of this rule), one draw gave a bias of 0.0110 (0.68× the bytes of
/// no test), two 0.0106 (0.74×), eight 0.0104 (0.85×) for twice the bake's time.
pub const ABV_REACH_TRIES: u32 = 2;

/// Interleaves the bits of `x` and `y` (x in the even bits): the Z order of a cell, in which
/// every aligned 2^k × 2^k block of cells is an aligned run of 4^k indices.
fn morton2(x: u32, y: u32) -> u32 {
    fn spread(mut v: u32) -> u32 {
        v &= 0xffff;
        v = (v | (v << 8)) & 0x00ff_00ff;
        v = (v | (v << 4)) & 0x0f0f_0f0f;
        v = (v | (v << 2)) & 0x3333_3333;
        v = (v | (v << 1)) & 0x5555_5555;
        v
    }
    spread(x) | (spread(y) << 1)
}

/// Ray counts as the sums a [`BlockPyramid`] averages.
fn counts_f64(v: &[u32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

/// The largest window of [`CentredWindows`] an ABV map's cell may average: a quarter of the
/// map either side (a window of `res/2 + 1` cells a side, about a quarter of the hemisphere).
/// A cell whose window that large holds too few P⁺ rays falls back to its block.
fn window_radius(res: u32) -> u32 {
    (res / 4).max(1)
}

/// The bandwidths an ABV map chooses among: blocks of at least 1 to 64 P⁺ rays, then (with
/// `BakeSettings::abv_windows`) centred windows of 2 to 64 (a window of 1 ray is the cell
/// itself where it has one, as a block of 1). A block has the direction it estimates anywhere
/// inside it (first-order bias on a smooth visibility), a centred window has it at its centre
/// (second order); blocks win along a horizon that runs on their edges.
///
/// Measured with `tools/src/bin/shading_noise.rs` on 64³ bakes (default preset, RMSE of the default
/// render and file, blocks → blocks and windows): fantasy_sawmill 0.0072 / 6.45 MiB →
/// 0.0065 / 11.5, mill 0.0090 / 6.11 → 0.0084 / 10.6, barrel 0.0064 / 7.52 → 0.0055 / 13.1,
/// fence 0.0080 / 1.04 → 0.0073 / 2.40, spiral staircase 0.0143 / 2.70 → 0.0139 / 7.35,
/// road-split 0.0080 → 0.0079, building-small-b 0.0196 → 0.0195. A window's map is smooth,
/// so truncation keeps more of its Haar details: shrinking them at the noise of the window's
/// rays brought the sawmill back to 6.36 MiB but the barrel to 0.0076 (its silhouettes blurred), and pooling the map into 2×2 or 4×4 blocks
/// before the windows lost most of the gain (barrel 0.0061 / 0.0064). Hence a setting, off by
/// default and on in `high`.
pub const ABV_BANDWIDTHS: [Bandwidth; 13] =
    Bandwidth::list(&[1, 2, 4, 8, 16, 32, 64], &[2, 4, 8, 16, 32, 64]);

/// The number of block bandwidths at the head of [`ABV_BANDWIDTHS`].
const ABV_BLOCKS: usize = 7;

/// The candidate (of `candidates`, a prefix of [`ABV_BANDWIDTHS`]) whose map from one fold's
/// rays best predicts the other fold's rays (squared error of the binary outcomes, both ways;
/// ties to the earlier candidate). Each fold's block sums and window tables are built once and
/// only the held-out rays' cells are evaluated.
fn cross_validated_bandwidth(
    hit: &[Vec<u32>; 2],
    escape: &[Vec<u32>; 2],
    res: u32,
    candidates: &[Bandwidth],
) -> Bandwidth {
    let with_windows = candidates.len() > ABV_BLOCKS;
    let tables = [0, 1].map(|f| {
        let (e, h) = (counts_f64(&escape[f]), counts_f64(&hit[f]));
        (
            BlockPyramid::new(&e, &h, &hit[f], res),
            with_windows.then(|| CentredWindows::new(&e, &h, &hit[f], res, window_radius(res))),
        )
    });
    let fill = [0, 1].map(|f| {
        let (h, e) = (hit[f].iter().sum::<u32>(), escape[f].iter().sum::<u32>());
        if h > 0 {
            e as f32 / h as f32
        } else {
            0.5
        }
    });
    let window_counts: [u32; ABV_BANDWIDTHS.len() - ABV_BLOCKS] =
        std::array::from_fn(|i| ABV_BANDWIDTHS[ABV_BLOCKS + i].min_rays);
    let mut windowed = [None; ABV_BANDWIDTHS.len() - ABV_BLOCKS];
    let mut score = [0f64; ABV_BANDWIDTHS.len()];
    for f in 0..2 {
        let held_out = 1 - f;
        let (pyramid, windows) = &tables[f];
        for (c, (&h, &e)) in hit[held_out].iter().zip(&escape[held_out]).enumerate() {
            if h == 0 {
                continue;
            }
            let (h, e) = (h as f64, e as f64);
            let add = |s: &mut f64, p: f32| {
                let p = p.clamp(0.0, 1.0) as f64;
                *s += e * (1.0 - p) * (1.0 - p) + (h - e) * p * p;
            };
            for (s, b) in score.iter_mut().zip(&ABV_BANDWIDTHS[..ABV_BLOCKS]) {
                add(s, pyramid.value(c as u32, b.min_rays, fill[f]));
            }
            if let Some(windows) = windows {
                windows.values(c as u32, &window_counts, &mut windowed);
                for ((s, w), &k) in score[ABV_BLOCKS..]
                    .iter_mut()
                    .zip(&windowed)
                    .zip(&window_counts)
                {
                    add(s, w.unwrap_or_else(|| pyramid.value(c as u32, k, fill[f])));
                }
            }
        }
    }
    let mut best = (f64::INFINITY, candidates[0]);
    for (&s, &b) in score.iter().zip(candidates) {
        if s < best.0 - 1e-12 {
            best = (s, b);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::boundary::boundary_faces;
    use crate::bake::primitive::fit_ellipsoid;
    use crate::bake::sampling::{pieces_by_voxel, sample_voxel};
    use crate::gen::glb::{MaterialData, SceneData};
    use crate::gen::shapes;
    use crate::spatial::{morton3, UVec3Key};
    use std::collections::BTreeSet;
    use std::collections::HashMap;

    /// The BVH query finds exactly the primitives a brute-force test over every voxel finds: sparse random ellipsoids on a 40³ grid (bricks partly outside the grid),
    /// random rays from inside and outside, axis-aligned ones included.
    #[test]
    fn primitive_query_matches_brute_force() {
        let grid = Grid {
            origin: Vec3::new(-1.0, -2.0, 0.5),
            size: 4.0,
            res: 40,
        };
        let s = grid.voxel_size();
        let mut rng = crate::math::rng::Pcg32::new(3, 9);
        let mut prims = Vec::new();
        for _ in 0..60 {
            let v = UVec3::new(
                rng.next_u32() % 40,
                rng.next_u32() % 40,
                rng.next_u32() % 40,
            );
            let (lo, _) = grid.voxel_bounds(v);
            let c = lo + Vec3::splat(0.5 * s);
            let axes = glam::Mat3::from_diagonal(Vec3::new(0.6, 0.3, 0.45) * s);
            prims.push((morton3(v), Ellipsoid { center: c, axes }));
        }
        let level = PrimitiveLevel::new(grid, prims.clone());
        let brute = |ray: &Ray| {
            prims.iter().any(|(k, e)| {
                let (vlo, vhi) = grid.voxel_bounds(demorton3(*k));
                // Brute force over every primitive with the plain slab and ellipsoid tests.
                let inv = ray.dir.recip();
                let (a, b) = ((vlo - ray.origin) * inv, (vhi - ray.origin) * inv);
                let t0 = a.min(b).max_element().max(ray.tmin);
                let t1 = a.max(b).min_element().min(ray.tmax);
                match crate::spatial::ellipsoid_ray_interval(
                    e.center,
                    e.axes.inverse(),
                    ray.origin,
                    ray.dir,
                ) {
                    Some((e0, e1)) => e0.max(t0) <= e1.min(t1),
                    None => false,
                }
            })
        };
        let (mut agree, mut hits) = (0, 0);
        for i in 0..4000 {
            let u = |r: &mut crate::math::rng::Pcg32| r.next_u32() as f32 / u32::MAX as f32;
            let o = grid.origin + Vec3::new(u(&mut rng), u(&mut rng), u(&mut rng)) * 6.0 - 1.0;
            let mut d = crate::math::sampling::square_to_uniform_sphere(glam::Vec2::new(
                u(&mut rng),
                u(&mut rng),
            ));
            if i % 2 == 0 {
                // Aimed near a primitive, so that about half of these hit.
                let target = prims[(rng.next_u32() % 60) as usize].1.center
                    + (Vec3::new(u(&mut rng), u(&mut rng), u(&mut rng)) - 0.5) * s;
                d = (target - o).normalize();
            } else if i % 10 == 1 {
                d = [Vec3::X, Vec3::NEG_Y, Vec3::Z][i / 10 % 3];
            }
            let ray = Ray::new(o, d);
            let want = brute(&ray);
            // Grazing hits within rounding may differ; count agreement.
            if level.hits(&ray) == want {
                agree += 1;
            }
            hits += want as u32;
        }
        assert!(hits > 800, "{hits}");
        assert!(agree >= 3996, "{agree} of 4000 agree");
    }

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

    /// [`PrimitiveLevel::occupied`] (two granularities of DDA) agrees with testing the ray
    /// against every occupied voxel's box, on random occupancies and rays, with grids that
    /// are and are not multiples of the 4³ cells.
    #[test]
    fn occupied_agrees_with_every_box() {
        let mut rng = Pcg32::new(7, 1);
        for (res, density) in [(16u32, 0.02), (6, 0.1)] {
            let grid = Grid {
                origin: Vec3::new(-1.0, 0.5, 2.0),
                size: 3.0,
                res,
            };
            let mut voxels = Vec::new();
            for z in 0..res {
                for y in 0..res {
                    for x in 0..res {
                        if rng.next_f32() < density {
                            voxels.push(UVec3::new(x, y, z));
                        }
                    }
                }
            }
            let e = Ellipsoid {
                center: Vec3::ZERO,
                axes: glam::Mat3::IDENTITY,
            };
            let level = PrimitiveLevel::new(grid, voxels.iter().map(|&v| (morton3(v), e)));
            let (mut met, mut missed) = (0, 0);
            for _ in 0..4000 {
                let o = grid.origin
                    + (Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 1.4
                        - Vec3::splat(0.2))
                        * grid.size;
                let d = crate::math::sphere_maps::equal_area_square_to_sphere(rng.next_2d());
                let ray = Ray::new(o, d);
                let inv = d.recip();
                let truth = voxels.iter().any(|&v| {
                    let (lo, hi) = grid.voxel_bounds(v);
                    let (t0, t1) = crate::spatial::box_interval(lo, hi, o, inv);
                    t0.max(ray.tmin) <= t1.min(ray.tmax)
                });
                assert_eq!(level.occupied(&ray), truth, "res {res}: ray {o} {d}");
                if truth {
                    met += 1;
                } else {
                    missed += 1;
                }
            }
            assert!(
                met > 400 && missed > 400,
                "res {res}: {met} met, {missed} missed"
            );
        }
    }

    /// A floor seen through a one-voxel hole in the ceiling of a closed room: a cone can enter
    /// the floor voxel
    /// below the hole only within about 18° of straight down (the hole's width over the
    /// height it must be crossed), so every ray the ABV map keeps comes from such a way in,
    /// and the map still has rays near the normal. Without the reachability test the rays
    /// spread over the hemisphere.
    #[test]
    fn abv_rays_come_only_from_where_a_cone_can_enter() {
        let mut mesh = shapes::quad(Vec3::new(-1.0, -1.0, 0.1), Vec3::X * 2.0, Vec3::Y * 2.0, 8);
        // The ceiling at z = 0.85 (voxels 0.75..1), open over x, y in [-0.25, 0].
        let (z, h) = (0.85, -0.25f32);
        for (o, a, b) in [
            (Vec3::new(-1.0, -1.0, z), 0.75, 2.0),
            (Vec3::new(0.0, -1.0, z), 1.0, 2.0),
            (Vec3::new(h, -1.0, z), 0.25, 0.75),
            (Vec3::new(h, 0.0, z), 0.25, 1.0),
        ] {
            mesh.append(&shapes::quad(o, Vec3::X * a, Vec3::Y * b, 4));
        }
        // Walls all round, so that no way in passes between floor and ceiling.
        for (o, e) in [
            (Vec3::new(-0.9, -1.0, 0.3), Vec3::Y * 2.0),
            (Vec3::new(0.9, -1.0, 0.3), Vec3::Y * 2.0),
            (Vec3::new(-1.0, -0.9, 0.3), Vec3::X * 2.0),
            (Vec3::new(-1.0, 0.9, 0.3), Vec3::X * 2.0),
        ] {
            mesh.append(&shapes::quad(o, e, Vec3::Z * 0.69, 4));
        }
        let scene =
            SceneData::single(mesh, MaterialData::new("room", [0.5; 3], 0.0, 1.0)).to_scene();
        let accel = Accel::build(&scene);
        let grid = Grid {
            origin: Vec3::splat(-1.0),
            size: 2.0,
            res: 8,
        };
        let (level, occ) = level_of(&scene, grid);
        assert!(occ.contains(&UVec3Key(3, 3, 4)) && !occ.contains(&UVec3Key(3, 3, 7)));
        let face = Face {
            voxel: UVec3Key(3, 3, 4),
            dir: 5,
        };
        // Straight up through the hole is open; sideways under the ceiling is not.
        let top = Vec3::new(-0.125, -0.125, 0.25 + 1e-4);
        assert!(!level.occupied(&Ray::new(top, Vec3::Z)));
        assert!(level.occupied(&Ray::new(top, Vec3::new(1.0, 0.0, 1.0).normalize())));
        let m = abv_map(&level, &accel, face, 16, 4, 1, 5, false);
        let mut near = 0;
        for (c, &h) in m.hits.iter().enumerate() {
            if h == 0 {
                continue;
            }
            let (x, y) = ((c % 16) as f32 + 0.5, (c / 16) as f32 + 0.5);
            let local = concentric_square_to_hemisphere(Vec2::new(x, y) / 16.0);
            // Cells are ~8° wide at this angle: allow one beyond the hole's 18.4°.
            assert!(
                local.z > 25f32.to_radians().cos(),
                "cell {c} at {:.1}° met by {h} rays",
                local.z.acos().to_degrees()
            );
            near += h;
        }
        assert!(near > 10, "{near} P⁺ rays near the normal");
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
        let m = abv_map(&level, &accel, wall_face, 16, 2, 1, 1, true);
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
        // Every direction is blocked, except that a ray grazing the face near the wall's rim
        // can pass beyond the wall's edge: allow a few cells at the horizon (each open ray's
        // value spreads over the block of cells its estimate pools).
        let open = defined.iter().filter(|&&v| v > 0.05).count();
        let (mut num, mut den) = (0f32, 0f32);
        for (v, &h) in m.values.iter().zip(&m.hits) {
            num += v * h as f32;
            den += h as f32;
        }
        let mean = num / den;
        assert!(
            open * 20 <= defined.len() && mean < 0.01,
            "{open} open cells, P⁺-weighted mean {mean}: {defined:?}"
        );
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
        // A ray per cell's worth of rays either per cell or shared by blocks of 2×2 cells
        // (the budget of levels above --abv-full-res): both unbiased.
        for (rays, stride) in [(64, 1), (256, 2)] {
            let m = abv_map(&level, &accel, face, 16, rays, stride, 3, true);
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
                "stride {stride}: mean ABV {mean}, expected {}",
                1.0 - w / p
            );
        }
        // One ray per block of 4×4 cells: 16 P⁺ tests, at most one defined cell per block, and
        // (with a block bandwidth) every other cell of a block with a P⁺ ray takes that ray's
        // value; a centred window averages the rays around each cell instead.
        let m = abv_map(&level, &accel, face, 16, 1, 4, 3, true);
        assert!(
            !abv_map(&level, &accel, face, 16, 1, 4, 3, false)
                .bandwidth
                .cap
        );
        let p_plus = m.hits.iter().sum::<u32>() as u64;
        // Nothing above the layer blocks a way in: a primitive test per ray, and a
        // reachability test and an occlusion ray per P⁺ ray.
        assert_eq!(m.traced, 16 + 2 * p_plus);
        for by in 0..4 {
            for bx in 0..4 {
                let cells: Vec<usize> = (0..16)
                    .map(|i| (by * 4 + i / 4) * 16 + bx * 4 + i % 4)
                    .collect();
                let hit: Vec<usize> = cells.iter().copied().filter(|&c| m.hits[c] > 0).collect();
                assert!(hit.len() <= 1, "block ({bx},{by}): {} cells hit", hit.len());
                if let Some(&h) = hit.first().filter(|_| !m.bandwidth.cap) {
                    assert!(cells.iter().all(|&c| m.values[c] == m.values[h]));
                }
            }
        }
    }

    /// The bandwidth's cross-validation keeps a sharp silhouette at the full resolution, pools
    /// a map whose rays are noise about one value, and takes a centred window where the
    /// visibility is smooth: one ray per cell in each fold over 32² directions, (a) escaping
    /// exactly where x < 13 (a silhouette across blocks of cells), (b) escaping with
    /// probability 0.6 everywhere, (c) with a probability that ramps across the map, where the
    /// window's map is also nearer the truth than the best block's.
    #[test]
    fn cross_validation_keeps_silhouettes_pools_noise_and_centres_on_ramps() {
        let res = 32u32;
        let n = (res * res) as usize;
        let mut rng = Pcg32::new(5, 1);
        let hit = [vec![1u32; n], vec![1u32; n]];
        let sharp = [0, 1].map(|_| (0..n).map(|c| (c as u32 % res < 13) as u32).collect());
        assert_eq!(
            cross_validated_bandwidth(&hit, &sharp, res, &ABV_BANDWIDTHS),
            ABV_BANDWIDTHS[0]
        );
        let noise = [0, 1].map(|_| (0..n).map(|_| (rng.next_f32() < 0.6) as u32).collect());
        let b = cross_validated_bandwidth(&hit, &noise, res, &ABV_BANDWIDTHS);
        assert!(b.min_rays >= 16, "noise pooled over {b} only");
        let truth = |c: usize| {
            let (x, y) = ((c as u32 % res) as f32 + 0.5, (c as u32 / res) as f32 + 0.5);
            0.1 + 0.8 * (x + y) / (2 * res) as f32
        };
        let ramp: [Vec<u32>; 2] =
            [0, 1].map(|_| (0..n).map(|c| (rng.next_f32() < truth(c)) as u32).collect());
        let b = cross_validated_bandwidth(&hit, &ramp, res, &ABV_BANDWIDTHS);
        let blocks = cross_validated_bandwidth(&hit, &ramp, res, &ABV_BANDWIDTHS[..ABV_BLOCKS]);
        assert!(!blocks.cap, "blocks only took {blocks}");
        assert!(b.cap, "a ramp took {b}");
        // Both folds' rays: the window's map against the best block's, RMSE to the truth.
        let esc: Vec<f64> = (0..n).map(|c| (ramp[0][c] + ramp[1][c]) as f64).collect();
        let (h2, hf): (Vec<u32>, Vec<f64>) = (vec![2; n], vec![2.0; n]);
        let pyramid = BlockPyramid::new(&esc, &hf, &h2, res);
        let windows = CentredWindows::new(&esc, &hf, &h2, res, window_radius(res));
        let rmse = |f: &dyn Fn(u32) -> f32| {
            ((0..n)
                .map(|c| (f(c as u32) - truth(c)).powi(2))
                .sum::<f32>()
                / n as f32)
                .sqrt()
        };
        let window = rmse(&|c| windows.value(c, b.min_rays).expect("in reach"));
        let block = [1, 2, 4, 8, 16, 32, 64]
            .map(|k| rmse(&|c| pyramid.value(c, k, 0.5)))
            .into_iter()
            .fold(f32::INFINITY, f32::min);
        assert!(
            window < 0.9 * block,
            "window {window} against block {block}"
        );
    }

    /// A ray missing every primitive, and the DDA on a diagonal ray through a filled grid.
    #[test]
    fn query_finds_primitives() {
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
