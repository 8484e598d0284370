//! A level prepared for cone tracing: a resident skeleton, and blocks prepared on demand into
//! the block cache ([`super::cache`]).
//!
//! The skeleton, built the first time a cone needs the level (every voxel block verified and
//! its keys read, nothing else kept):
//! - occupancy as a hierarchy of bits, one per cell of 4^g voxels for g = 1 (bricks) up to
//!   the coarsest granularity with at most 4 cells per axis, and per occupied brick a 64-bit
//!   mask of its voxels with the index of its first voxel, so that the traversal crosses empty
//!   space in large steps and finds a voxel without hashing;
//! - the level's voxel and face blocks: where each starts, and a cache slot each.
//!
//! A prepared voxel block ([`Voxels`]) holds, per voxel in Morton order, one 64-byte record
//! with what the hit test needs (the ellipsoid's centre and inverse axes; the voxel box comes
//! from the DDA) and a few bytes the weight needs; a second record, read only for primitives
//! actually hit, with the normal lobes for E|n·ω|, the exposure and the zero-copy AIV handle;
//! and the voxel's ABSDF, built the first time the voxel is shaded (once, thread-safely). A
//! prepared face block ([`Faces`]) holds its faces by (voxel key, direction).

use std::collections::HashMap;
use std::hash::BuildHasherDefault;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, OnceLock};

use glam::{IVec3, Mat3, UVec3, Vec3};

use super::cache::{BlockCache, Slot};
use crate::absdf::Absdf;
use crate::format::FaceAbv;
use crate::format::{Aggregate, AivMap, LoadedBlock, VoxelRef};
use crate::math::sggx::{lobe_hemisphere_mass, Sggx};
use crate::spatial::AreaCase;
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
    /// The voxel's Morton key in its level.
    pub key: u64,
    /// The normal lobes scaled so that E|n·ω| = Σ σ_k(ω) (SGGX matrices times (w_k / M5_k)²,
    /// M5_k of the anisotropic lobe: [`lobe_hemisphere_mass`]).
    pub lobes: [Sggx; 4],
    pub lobe_count: u8,
    /// 1 / exposure: the incident AIV counts exposed sides only.
    pub inv_exposure: f32,
    /// The ellipsoid's axes and |det| (for |B|_ω).
    pub axes: Mat3,
    pub det: f32,
    /// The voxel's AIV map, read out of the block once (every hit and light sample looks it
    /// up).
    pub aiv: AivMap<'a>,
    /// The last cell of `aiv` a cone's weight looked up towards the viewer, plus one, in the
    /// high half, and its value's bits in the low half (0: none yet): [`ViewerAiv`].
    viewer_aiv: AtomicU64,
}

/// V̂(ω_o) of a hit's weight as [`WeightRecord::viewer_aiv`] finds it.
pub enum ViewerAiv {
    /// The value: the map is constant, or the record holds the cell's value.
    Known(f32),
    /// The map's cell to look up ([`WeightRecord::keep_viewer_aiv`]).
    Cell(u32),
}

impl WeightRecord<'_> {
    /// V̂(ω_o) towards the viewer along `d` (unit), if the record holds the value of its cell.
    ///
    /// The map is constant over a cell, and the cones that meet a voxel of one instance look
    /// at it from nearly the same direction, so a voxel's weights mostly ask for the cell
    /// asked for last. Keeping that cell's value in the record (which the weight reads
    /// anyway) spares the look-up, whose first load of the voxel's tree misses the cache. The
    /// value is the tree's, whichever thread stored it, so renders are the same bits
    /// (`tests/runtime.rs` `viewer_aiv_kept_in_the_record_is_the_lookup`). The maple's 128³
    /// bake at 256², 64 spp: 1.51–1.53 CPU s against 1.56–1.59; a forest of 1,000 instances
    /// of four trees, whose instances see a voxel from as many directions, 1–2% less.
    #[inline]
    pub fn viewer_aiv(&self, d: Vec3) -> ViewerAiv {
        let Some(cell) = self.aiv.cell(d) else {
            return ViewerAiv::Known(self.aiv.eval_cell(0));
        };
        let kept = self.viewer_aiv.load(Relaxed);
        if kept >> 32 == cell as u64 + 1 {
            ViewerAiv::Known(f32::from_bits(kept as u32))
        } else {
            ViewerAiv::Cell(cell)
        }
    }

    /// The value of `cell` ([`ViewerAiv::Cell`]), looked up and kept in the record.
    #[inline]
    pub fn keep_viewer_aiv(&self, cell: u32) -> f32 {
        let v = self.aiv.eval_cell(cell);
        self.viewer_aiv
            .store((cell as u64 + 1) << 32 | v.to_bits() as u64, Relaxed);
        v
    }

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

/// A prepared voxel block: its records, and its voxels' ABSDFs as they are built.
pub struct Voxels {
    /// The level index of the block's first voxel.
    pub first: u32,
    pub hit: Box<[HitRecord]>,
    pub weight: Box<[WeightRecord<'static>]>,
    /// The block's voxels as the format reads them (what an ABSDF is built from): once for
    /// the block, not in each voxel's record.
    block: crate::format::VoxelBlock<'static>,
    absdf: Box<[OnceLock<Box<Absdf<'static>>>]>,
    /// Bytes counted for the block in its cache (grows as ABSDFs are built).
    bytes: AtomicU64,
    cache: Arc<BlockCache>,
    /// The block's bytes, which `weight` borrows: declared last, dropped last.
    _loaded: LoadedBlock<'static>,
}

impl Voxels {
    /// Prepares `loaded`, voxel block of `grid` whose first voxel is `first` in its level.
    fn prepare(
        loaded: LoadedBlock<'static>,
        grid: &Grid,
        first: u32,
        cache: Arc<BlockCache>,
    ) -> Result<Voxels, String> {
        let block = loaded.voxels().ok_or("not a voxel block")?;
        // SAFETY: the records borrow the block's bytes, which live in the file's map (held by
        // the scene, which outlives every block: `Level` empties its slots when dropped, and
        // handles borrow the scene) or in `_loaded`'s heap buffer, which does not move when
        // `Voxels` does and is dropped after the records (field order).
        let block: crate::format::VoxelBlock<'static> = unsafe { std::mem::transmute(block) };
        let n = block.len();
        let mut hit = Vec::with_capacity(n);
        let mut weight = Vec::with_capacity(n);
        for i in 0..n {
            let v = block.voxel(i);
            let (h, w) = records(grid, v);
            hit.push(h);
            weight.push(w);
        }
        let absdf: Box<[OnceLock<Box<Absdf<'static>>>]> = (0..n).map(|_| OnceLock::new()).collect();
        let bytes = (std::mem::size_of::<Voxels>()
            + n * (std::mem::size_of::<HitRecord>()
                + std::mem::size_of::<WeightRecord>()
                + std::mem::size_of::<OnceLock<Box<Absdf>>>())
            + loaded.owned_bytes()) as u64;
        cache.grow(bytes);
        Ok(Voxels {
            first,
            hit: hit.into_boxed_slice(),
            weight: weight.into_boxed_slice(),
            block,
            absdf,
            bytes: AtomicU64::new(bytes),
            cache,
            _loaded: loaded,
        })
    }

    /// Voxels in the block.
    #[inline]
    pub fn len(&self) -> usize {
        self.hit.len()
    }

    /// Whether the level index `idx` falls in this block.
    #[inline]
    pub fn holds(&self, idx: u32) -> bool {
        idx.wrapping_sub(self.first) < self.hit.len() as u32
    }

    /// The ABSDF of voxel `i` of the block, built on first use (and counted in the cache,
    /// which may evict other blocks to make room).
    #[inline]
    pub fn absdf(&self, i: u32) -> &Absdf<'static> {
        let slot = &self.absdf[i as usize];
        if let Some(a) = slot.get() {
            return a;
        }
        let mut built = 0;
        let a = slot.get_or_init(|| {
            // The moments may be read in place from the block's bytes, which outlive the
            // ABSDF (dropped with the block, before `_loaded`).
            let a = Box::new(
                self.block
                    .voxel(i as usize)
                    .absdf(crate::tables::Tables::embedded()),
            );
            built = a.memory_bytes() as u64;
            a
        });
        if built > 0 {
            self.bytes.fetch_add(built, Relaxed);
            self.cache.grow(built);
            self.cache.evict_over_budget();
        }
        a
    }

    /// The primitive of voxel `i` of the block, rebuilt (for |B|_ω in the crossing case).
    pub fn primitive(&self, level: &Level, i: u32) -> Option<TruncatedEllipsoid> {
        let (h, w) = (&self.hit[i as usize], &self.weight[i as usize]);
        let area_case = h.area_case?;
        let (lo, hi) = level.grid.voxel_bounds(crate::spatial::demorton3(w.key));
        let pad = Vec3::splat(level.pad);
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
}

impl Drop for Voxels {
    fn drop(&mut self) {
        self.cache.shrink(self.bytes.load(Relaxed));
    }
}

/// The hit and weight records of voxel `v` of a level of grid `grid`.
fn records<'a>(grid: &Grid, v: VoxelRef<'a>) -> (HitRecord, WeightRecord<'a>) {
    let (lo, hi) = grid.voxel_bounds(v.coords());
    let e: Ellipsoid = v.ellipsoid();
    let prim = TruncatedEllipsoid::new(&e, lo, hi);
    let hit = HitRecord {
        center: e.center,
        inv: prim.map_or(Mat3::ZERO, |p| p.inv),
        area: v.area() * v.coverage(),
        area_case: prim.map(|p| p.area_case),
    };
    let mut lobes = [Sggx::from_frame_roughness(Mat3::IDENTITY, glam::Vec2::ONE); 4];
    let mut lobe_count = 0;
    for lb in v.lobes().take(4) {
        let mass = lobe_hemisphere_mass(lb.alpha).max(1e-6);
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
    let weight = WeightRecord {
        lobes,
        lobe_count: lobe_count as u8,
        inv_exposure: 1.0 / v.exposure().clamp(1.0 / 16.0, 1.0),
        axes: e.axes,
        det: prim.map_or(0.0, |p| p.det),
        aiv: v.aiv_map(),
        viewer_aiv: AtomicU64::new(0),
        key: v.key,
    };
    (hit, weight)
}

/// A prepared face block: its faces by key · 8 + direction, sorted.
pub struct Faces {
    keys: Box<[u64]>,
    /// What the ABV look-up reads of each face, in the order of `keys`.
    faces: Box<[FaceAbv]>,
    /// The block's reader (its ABV nodes).
    block: crate::format::FaceBlock<'static>,
    bytes: u64,
    cache: Arc<BlockCache>,
    /// The block's bytes, which `block` borrows: declared last, dropped last.
    _loaded: LoadedBlock<'static>,
}

impl Faces {
    fn prepare(loaded: LoadedBlock<'static>, cache: Arc<BlockCache>) -> Result<Faces, String> {
        let block = loaded.faces().ok_or("not a face block")?;
        // SAFETY: as for `Voxels::prepare`.
        let block: crate::format::FaceBlock<'static> = unsafe { std::mem::transmute(block) };
        let mut pairs: Vec<(u64, FaceAbv)> = (0..block.len())
            .map(|i| {
                let f = block.face(i);
                (f.key() * 8 + f.face().dir as u64, f.abv_ref())
            })
            .collect();
        pairs.sort_by_key(|p| p.0);
        let keys: Box<[u64]> = pairs.iter().map(|p| p.0).collect();
        let faces: Box<[FaceAbv]> = pairs.into_iter().map(|p| p.1).collect();
        let bytes = (std::mem::size_of::<Faces>()
            + keys.len() * (8 + std::mem::size_of::<FaceAbv>())
            + loaded.owned_bytes()) as u64;
        cache.grow(bytes);
        Ok(Faces {
            keys,
            faces,
            block,
            bytes,
            cache,
            _loaded: loaded,
        })
    }

    /// The ABV towards `d` of the face `key8` (voxel key · 8 + direction), if the block has it.
    #[inline]
    fn abv(&self, key8: u64, d: Vec3) -> Option<f32> {
        let i = self.keys.binary_search(&key8).ok()?;
        Some(self.block.abv(&self.faces[i], d))
    }
}

impl Drop for Faces {
    fn drop(&mut self) {
        self.cache.shrink(self.bytes);
    }
}

/// A prepared level: the skeleton, and the slots of its blocks.
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
    bricks: Vec<Brick>,
    index: BrickIndex,
    /// Per voxel block b, the level index of its first voxel (and one past the last at the
    /// end), and its block number in the file (blocks that failed to verify are left out).
    block_first: Vec<u32>,
    block_number: Vec<u32>,
    voxel_slots: Vec<Arc<Slot<Voxels>>>,
    /// Per face block, its first and last voxel keys, and its slot.
    face_ranges: Vec<(u64, u64)>,
    face_slots: Vec<Arc<Slot<Faces>>>,
    agg: &'a Aggregate,
    l: usize,
    cache: Arc<BlockCache>,
    /// The first block that failed to verify or to load, if any.
    error: OnceLock<String>,
}

impl Drop for Level<'_> {
    fn drop(&mut self) {
        for s in &self.voxel_slots {
            s.clear();
        }
        for s in &self.face_slots {
            s.clear();
        }
        self.cache.forget_empty();
    }
}

impl<'a> Level<'a> {
    /// Builds the skeleton of level `l` of `agg` from the voxel keys its index holds
    /// (`Level.voxel_keys`, when `index_keys`), or, in files without them, by verifying every voxel block and
    /// reading its keys (no block is kept); its blocks are prepared into `cache` on demand. A
    /// voxel block that fails to verify is left out (its voxels are empty space) and reported
    /// by [`Level::error`], when the skeleton is built or when a cone first needs the block;
    /// a level none of whose blocks verify fails, and so does one whose keys are damaged.
    pub fn prepare(
        agg: &'a Aggregate,
        l: usize,
        cache: Arc<BlockCache>,
        index_keys: bool,
    ) -> Result<Level<'a>, String> {
        let grid = agg.grid(l);
        let (nv, _) = agg.block_counts(l);
        let error = OnceLock::new();
        let mut keys: Vec<u64> = Vec::new();
        let mut block_first = Vec::with_capacity(nv + 1);
        let mut block_number = Vec::with_capacity(nv);
        match agg.voxel_keys(l).filter(|_| index_keys) {
            // The index has the keys: no block is read until a cone needs it.
            Some(Ok(k)) => {
                keys = k;
                let mut at = 0u32;
                for (b, r) in agg.voxel_block_ranges(l).iter().enumerate() {
                    block_first.push(at);
                    block_number.push(b as u32);
                    at += r.2;
                }
            }
            Some(Err(e)) => return Err(e.to_string()),
            None => {}
        }
        // Files without the keys: every voxel block is read for its keys.
        let to_read = if block_number.is_empty() { nv } else { 0 };
        for b in 0..to_read {
            let loaded = match agg.load_voxel_block(l, b) {
                Ok(x) => x,
                Err(e) => {
                    let _ = error.set(format!("level {l}, voxel block {b}: {e}"));
                    continue;
                }
            };
            let Some(block) = loaded.voxels() else {
                continue;
            };
            block_first.push(keys.len() as u32);
            block_number.push(b as u32);
            keys.extend((0..block.len()).map(|i| block.key(i)));
        }
        block_first.push(keys.len() as u32);
        if nv > 0 && block_number.is_empty() {
            return Err(error
                .get()
                .cloned()
                .unwrap_or_else(|| "no voxel block".into()));
        }
        // Bricks: voxels are sorted by Morton key, so each brick is a run of keys >> 6.
        let brick_res = (grid.res as i32 + BRICK - 1) / BRICK;
        let mut bricks: Vec<Brick> = Vec::new();
        let mut brick_keys: Vec<u64> = Vec::new();
        for (i, &key) in keys.iter().enumerate() {
            let bk = key >> 6;
            if brick_keys.last() != Some(&bk) {
                brick_keys.push(bk);
                bricks.push(Brick {
                    mask: 0,
                    first: i as u32,
                });
            }
            if let Some(b) = bricks.last_mut() {
                b.mask |= 1u64 << (key & 63);
            }
        }
        drop(keys);
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
        let face_ranges: Vec<(u64, u64)> = agg
            .face_block_ranges(l)
            .iter()
            .map(|r| (r.0, r.1))
            .collect();
        let voxel_size = grid.voxel_size();
        Ok(Level {
            grid,
            voxel_size,
            pad: crate::spatial::VOXEL_PAD * voxel_size,
            brick_res,
            top,
            grids,
            occ,
            bricks,
            index,
            voxel_slots: (0..block_number.len()).map(|_| Arc::default()).collect(),
            block_first,
            block_number,
            face_slots: (0..face_ranges.len()).map(|_| Arc::default()).collect(),
            face_ranges,
            agg,
            l,
            cache,
            error,
        })
    }

    #[inline]
    fn linear(brick_res: i32, c: IVec3) -> usize {
        ((c.z * brick_res + c.y) * brick_res + c.x) as usize
    }

    /// The first block of the level that failed to verify or to load, if any (its voxels or
    /// faces were treated as absent).
    pub fn error(&self) -> Option<&String> {
        self.error.get()
    }

    /// Bytes the skeleton holds (resident while the scene is open, outside the cache).
    pub fn skeleton_bytes(&self) -> usize {
        let index = match &self.index {
            BrickIndex::Dense(d) => d.len() * 4,
            BrickIndex::Sparse(m) => m.capacity() * 16,
        };
        self.occ.iter().map(|o| o.len() * 8).sum::<usize>()
            + self.bricks.len() * std::mem::size_of::<Brick>()
            + index
            + self.block_first.len() * 8
            + self.face_ranges.len() * 16
            + (self.voxel_slots.len() + self.face_slots.len()) * 64
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

    /// The prepared block holding voxel `idx` of the level, prepared now if it is not in the
    /// cache; `None` when it fails to load (recorded in [`Level::error`]).
    #[inline(never)]
    pub fn voxels(&self, idx: u32) -> Option<Arc<Voxels>> {
        let b = self
            .block_first
            .partition_point(|&f| f <= idx)
            .checked_sub(1)?;
        if b >= self.voxel_slots.len() {
            return None;
        }
        let first = self.block_first[b];
        let r = self.voxel_slots[b].get_or_load(&self.cache, || {
            let loaded = self
                .agg
                .load_voxel_block(self.l, self.block_number[b] as usize)
                .map_err(|e| e.to_string())?;
            // SAFETY: see `Voxels::prepare`: the block lives in this level's slot or in a
            // cone's hands, never past the scene that owns `agg`.
            let loaded: LoadedBlock<'static> = unsafe { std::mem::transmute(loaded) };
            let v = Voxels::prepare(loaded, &self.grid, first, self.cache.clone())?;
            if v.len() as u32 != self.block_first[b + 1] - first {
                return Err("block changed since the level was indexed".to_string());
            }
            Ok(v)
        });
        match r {
            Ok(v) => Some(v),
            Err(e) => {
                let _ = self
                    .error
                    .set(format!("level {}: voxel block {b}: {e}", self.l));
                None
            }
        }
    }

    /// The boundary visibility of the face of voxel `v` in direction `dir` towards `d`
    /// (1 where the level has no such face, or its block fails to load).
    pub fn abv(&self, v: UVec3, dir: u8, d: Vec3) -> f32 {
        let key = morton3(v);
        let key8 = key * 8 + dir as u64;
        let mut b = self.face_ranges.partition_point(|r| r.1 < key);
        while b < self.face_ranges.len() && self.face_ranges[b].0 <= key {
            let load = || {
                let loaded = self
                    .agg
                    .load_face_block(self.l, b)
                    .map_err(|e| e.to_string())?;
                // SAFETY: as for voxel blocks (`Level::voxels`).
                let loaded: LoadedBlock<'static> = unsafe { std::mem::transmute(loaded) };
                Faces::prepare(loaded, self.cache.clone())
            };
            match self.face_slots[b].with(&self.cache, load, |faces| faces.abv(key8, d)) {
                Ok(Some(v)) => return v,
                Ok(None) => {}
                Err(e) => {
                    let _ = self
                        .error
                        .set(format!("level {}: face block {b}: {e}", self.l));
                }
            }
            b += 1;
        }
        1.0
    }
}
