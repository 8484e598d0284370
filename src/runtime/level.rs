//! A level prepared for cone tracing, laid out for the traversal's cache:
//!
//! - per voxel, in Morton order, one 64-byte record with what the hit test needs (the
//!   ellipsoid's centre and inverse axes; the voxel box comes from the DDA) and a few bytes the
//!   weight needs; a second record, read only for primitives actually hit, with the normal
//!   lobes for E|n·ω|, the exposure and the zero-copy AIV handle; and the voxel's ABSDF, built
//!   the first time the voxel is shaded (once, thread-safely);
//! - occupancy as a hierarchy of bits, one per cell of 4^g voxels for g = 1 (bricks) up to
//!   the coarsest granularity with at most 4 cells per axis, and per occupied brick a 64-bit
//!   mask of its voxels with the index of its first voxel, so that the traversal crosses empty
//!   space in large steps and finds a voxel without hashing;
//! - the boundary faces by (voxel key, direction).

use std::collections::HashMap;
use std::hash::BuildHasherDefault;
use std::sync::OnceLock;

use glam::{IVec3, Mat3, UVec3, Vec3};

use crate::absdf::Absdf;
use crate::format::read::FaceRef;
use crate::format::{Aggregate, VoxelRef};
use crate::math::microfacet::m5_exact;
use crate::math::sggx::Sggx;
use crate::spatial::ellipsoid::AreaCase;
use crate::spatial::{morton3, Ellipsoid, Grid, TruncatedEllipsoid};

/// A hasher for Morton keys: one mixing step instead of SipHash.
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

type FastMap<V> = HashMap<u64, V, BuildHasherDefault<KeyHasher>>;

/// Brick edge in voxels (a brick's 64 voxels are one Morton range).
pub const BRICK: i32 = 4;

/// What the hit test reads: one cache line.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct HitRecord {
    /// The ellipsoid's centre.
    pub center: Vec3,
    /// The inverse of its axes.
    pub inv: Mat3,
    /// area · coverage: the voxel's surface area after cut-outs.
    pub area: f32,
    /// How |B|_ω is computed; `None` for a voxel without a usable ellipsoid.
    pub area_case: Option<AreaCase>,
}

/// What the weight and the visibility read, for primitives hit.
pub struct WeightRecord<'a> {
    /// The normal lobes scaled so that E|n·ω| = Σ σ_k(ω) (SGGX matrices times (w_k / m5_k)²).
    pub lobes: [Sggx; 4],
    pub lobe_count: u8,
    /// 1 / exposure: the incident AIV counts exposed sides only.
    pub inv_exposure: f32,
    /// The ellipsoid's axes and |det| (for |B|_ω).
    pub axes: Mat3,
    pub det: f32,
    pub vref: VoxelRef<'a>,
}

impl WeightRecord<'_> {
    /// E|n·ω| of the voxel's surfaces, from its normal distribution.
    #[inline]
    pub fn mean_cosine(&self, w: Vec3) -> f32 {
        let mut s = 0.0;
        for l in &self.lobes[..self.lobe_count as usize] {
            s += l.sigma(w);
        }
        s.clamp(0.0, 1.0)
    }
}

/// An occupied brick: which of its 64 voxels exist, and the index of the first.
#[derive(Clone, Copy, Debug)]
pub struct Brick {
    pub mask: u64,
    pub first: u32,
}

/// Where occupied bricks are found.
enum BrickIndex {
    /// Bricks per axis ≤ 128: a dense table of indices into `bricks` (u32::MAX: empty).
    Dense(Vec<u32>),
    /// Larger grids: a hash from brick Morton key.
    Sparse(FastMap<u32>),
}

/// Most granularities of the occupancy hierarchy (cells of 4^g voxels, g = 0 the voxels):
/// enough for 4^7 = 16384 voxels per axis with at most 4 cells per axis at the top (bakes go to
/// 4096; a finer level just has more cells at its top).
pub const MAX_GRANULARITY: usize = 8;

/// A prepared level.
pub struct Level<'a> {
    pub grid: Grid,
    /// Voxel size, and the padding of a voxel's interval (spatial::VOXEL_PAD of it).
    pub voxel_size: f32,
    pub pad: f32,
    /// Bricks per axis.
    pub brick_res: i32,
    /// The coarsest granularity `top` (cells of 4^top voxels, at most 4 per axis), and per
    /// granularity its grid (g = 0: the voxels; g = 1: the bricks) and, for g ≥ 1, one bit per
    /// cell (x fastest): whether it holds any voxel.
    pub top: usize,
    pub grids: [Grid; MAX_GRANULARITY],
    occ: Vec<Vec<u64>>,
    pub hit: Vec<HitRecord>,
    pub weight: Vec<WeightRecord<'a>>,
    absdf: Vec<OnceLock<Box<Absdf<'static>>>>,
    bricks: Vec<Brick>,
    index: BrickIndex,
    /// Boundary faces: key · 8 + direction.
    faces: FastMap<FaceRef<'a>>,
}

impl<'a> Level<'a> {
    /// Prepares level `l` of `agg`, verifying its blocks.
    pub fn prepare(agg: &'a Aggregate, l: usize) -> Result<Level<'a>, String> {
        let grid = agg.grid(l);
        let (nv, nf) = agg.block_counts(l);
        let mut refs: Vec<VoxelRef<'a>> = Vec::with_capacity(agg.counts(l).voxels as usize);
        for b in 0..nv {
            let block = agg.voxel_block(l, b).map_err(|e| e.to_string())?;
            refs.extend((0..block.len()).map(|i| block.voxel(i)));
        }
        let mut hit = Vec::with_capacity(refs.len());
        let mut weight = Vec::with_capacity(refs.len());
        for v in &refs {
            let (lo, hi) = grid.voxel_bounds(v.coords());
            let e: Ellipsoid = v.ellipsoid();
            let prim = TruncatedEllipsoid::new(&e, lo, hi);
            hit.push(HitRecord {
                center: e.center,
                inv: prim.map_or(Mat3::ZERO, |p| p.inv),
                area: v.area() * v.coverage(),
                area_case: prim.map(|p| p.area_case),
            });
            let mut lobes = [Sggx::from_frame_roughness(Mat3::IDENTITY, glam::Vec2::ONE); 4];
            let mut lobe_count = 0;
            for lb in v.lobes().take(4) {
                let mass = m5_exact((lb.alpha.x * lb.alpha.y).sqrt()).max(1e-6);
                let k = (lb.weight / mass).max(0.0);
                let s = Sggx::from_frame_roughness(lb.frame, lb.alpha);
                let k2 = k * k;
                lobes[lobe_count] = Sggx {
                    xx: s.xx * k2,
                    yy: s.yy * k2,
                    zz: s.zz * k2,
                    xy: s.xy * k2,
                    xz: s.xz * k2,
                    yz: s.yz * k2,
                };
                lobe_count += 1;
            }
            weight.push(WeightRecord {
                lobes,
                lobe_count: lobe_count as u8,
                inv_exposure: 1.0 / v.exposure().clamp(1.0 / 16.0, 1.0),
                axes: e.axes,
                det: prim.map_or(0.0, |p| p.det),
                vref: *v,
            });
        }
        // Bricks: voxels are sorted by Morton key, so each brick is a run of keys >> 6.
        let brick_res = (grid.res as i32 + BRICK - 1) / BRICK;
        let mut bricks: Vec<Brick> = Vec::new();
        let mut brick_keys: Vec<u64> = Vec::new();
        for (i, v) in refs.iter().enumerate() {
            let bk = v.key >> 6;
            if brick_keys.last() != Some(&bk) {
                brick_keys.push(bk);
                bricks.push(Brick {
                    mask: 0,
                    first: i as u32,
                });
            }
            bricks.last_mut().expect("pushed").mask |= 1u64 << (v.key & 63);
        }
        let cells = (brick_res as u64).pow(3);
        let mut occupied = vec![0u64; cells.div_ceil(64) as usize];
        let index = if brick_res <= 128 {
            let mut dense = vec![u32::MAX; cells as usize];
            for (i, &bk) in brick_keys.iter().enumerate() {
                let c = crate::spatial::demorton3(bk).as_ivec3();
                dense[Self::linear(brick_res, c)] = i as u32;
            }
            BrickIndex::Dense(dense)
        } else {
            BrickIndex::Sparse(
                brick_keys
                    .iter()
                    .enumerate()
                    .map(|(i, &k)| (k, i as u32))
                    .collect(),
            )
        };
        for &bk in &brick_keys {
            let c = crate::spatial::demorton3(bk).as_ivec3();
            let i = Self::linear(brick_res, c);
            occupied[i / 64] |= 1u64 << (i % 64);
        }
        // The coarser granularities: 4^g voxels per cell, until at most 4 cells per axis.
        let mut top = 0usize;
        let mut cells_g = [0i32; MAX_GRANULARITY];
        cells_g[0] = grid.res as i32;
        while cells_g[top] > BRICK && top + 1 < MAX_GRANULARITY {
            top += 1;
            cells_g[top] = (cells_g[top - 1] + BRICK - 1) / BRICK;
        }
        let mut grids = [grid; MAX_GRANULARITY];
        for g in 1..=top {
            grids[g] = Grid {
                origin: grid.origin,
                size: grid.voxel_size() * (cells_g[g] as f32) * (BRICK as f32).powi(g as i32),
                res: cells_g[g] as u32,
            };
        }
        let mut occ = Vec::with_capacity(top);
        for g in 1..=top {
            if g == 1 {
                occ.push(std::mem::take(&mut occupied));
                continue;
            }
            let n = cells_g[g];
            let mut bits = vec![0u64; (n as u64).pow(3).div_ceil(64) as usize];
            for &bk in &brick_keys {
                let c = crate::spatial::demorton3(bk).as_ivec3() >> (2 * (g - 1)) as i32;
                let i = ((c.z * n + c.y) * n + c.x) as usize;
                bits[i / 64] |= 1u64 << (i % 64);
            }
            occ.push(bits);
        }
        let mut faces =
            FastMap::with_capacity_and_hasher(agg.counts(l).faces as usize, Default::default());
        for b in 0..nf {
            let block = agg.face_block(l, b).map_err(|e| e.to_string())?;
            for i in 0..block.len() {
                let f = block.face(i);
                faces.insert(f.key() * 8 + f.face().dir as u64, f);
            }
        }
        let voxel_size = grid.voxel_size();
        Ok(Level {
            grid,
            voxel_size,
            pad: crate::spatial::VOXEL_PAD * voxel_size,
            brick_res,
            top,
            grids,
            occ,
            absdf: (0..hit.len()).map(|_| OnceLock::new()).collect(),
            hit,
            weight,
            bricks,
            index,
            faces,
        })
    }

    #[inline]
    fn linear(brick_res: i32, c: IVec3) -> usize {
        ((c.z * brick_res + c.y) * brick_res + c.x) as usize
    }

    /// Whether cell `c` of granularity `g` ≥ 1 holds any voxel.
    #[inline]
    pub fn occupied_at(&self, g: usize, c: IVec3) -> bool {
        let n = self.grids[g].res as i32;
        let i = ((c.z * n + c.y) * n + c.x) as usize;
        self.occ[g - 1][i / 64] >> (i % 64) & 1 != 0
    }

    /// The occupied brick `c`.
    #[inline]
    pub fn brick(&self, c: IVec3) -> Option<Brick> {
        let i = match &self.index {
            BrickIndex::Dense(d) => d[Self::linear(self.brick_res, c)],
            BrickIndex::Sparse(m) => *m.get(&morton3(c.as_uvec3()))?,
        };
        self.bricks.get(i as usize).copied()
    }

    /// The index of voxel `v` in the level's records, if it exists.
    #[inline]
    pub fn find(&self, v: IVec3) -> Option<u32> {
        let b = self.brick(v >> 2)?;
        Self::in_brick(&b, v)
    }

    /// The index of voxel `v` of brick `b`, if it exists.
    #[inline]
    pub fn in_brick(b: &Brick, v: IVec3) -> Option<u32> {
        // The Morton code of the voxel within its brick: two bits per axis.
        let spread = |x: i32| ((x & 1) | ((x & 2) << 2)) as u32;
        let bit = spread(v.x) | spread(v.y) << 1 | spread(v.z) << 2;
        (b.mask >> bit & 1 != 0).then(|| b.first + (b.mask & ((1u64 << bit) - 1)).count_ones())
    }

    /// The boundary face of voxel `v` in direction `dir`.
    #[inline]
    pub fn face(&self, v: UVec3, dir: u8) -> Option<&FaceRef<'a>> {
        self.faces.get(&(morton3(v) * 8 + dir as u64))
    }

    /// The primitive of voxel `idx`, rebuilt (for |B|_ω in the crossing case).
    pub fn primitive(&self, idx: u32) -> Option<TruncatedEllipsoid> {
        let (h, w) = (&self.hit[idx as usize], &self.weight[idx as usize]);
        let area_case = h.area_case?;
        let (lo, hi) = self.grid.voxel_bounds(w.vref.coords());
        let pad = Vec3::splat(self.pad);
        Some(TruncatedEllipsoid {
            center: h.center,
            axes: w.axes,
            inv: h.inv,
            det: w.det,
            lo: lo - pad,
            hi: hi + pad,
            area_case,
        })
    }

    /// The ABSDF of voxel `idx`, built on first use.
    #[inline]
    pub fn absdf(&self, idx: u32) -> &Absdf<'static> {
        self.absdf[idx as usize].get_or_init(|| {
            Box::new(Absdf::new(
                &self.weight[idx as usize].vref.appearance(),
                crate::tables::Tables::embedded(),
            ))
        })
    }
}
