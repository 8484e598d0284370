//! The LoD runtime: a library host renderers link to trace cones through `.agg` aggregates
//! (paper §6.3, §7.3, Algorithm 1, Eq. 30).
//!
//! Two layers.
//!
//! - **Traversal**: [`LodScene::hits`] walks a [`Cone`] through the aggregate and yields, for
//!   every primitive the centre ray meets, in order, a [`Hit`]: the voxel (a [`VoxelHandle`]
//!   that answers its ABSDF `eval`/`pdf`/`sample` through [`crate::bsdf::Bsdf`] and its AIV
//!   towards any direction), the ray parameter, and the coverage weight V̂(ω_o)·|A|_ω/|B|_ω of
//!   Eq. 30; once the walk is over, [`Hits::transmittance`] is the background's weight, the ABV
//!   of the face where the cone entered the aggregate (Eq. 26; 1 when it met no primitive). A
//!   host that does its own lighting shades the hits with its own code and sampler (any
//!   [`crate::math::sampling::Sampler`]).
//! - **Shading**: [`LodScene::trace`] does Algorithm 1 with those pieces and the runtime's own
//!   [`Lights`]: the voxels' contributions L_o·V̂(ω_o)·|A|_ω/|B|_ω summed (order-independent),
//!   L_o from light and ABSDF samples combined by MIS with the AIV standing in for shadow rays,
//!   and the background through the ABV.
//!
//! Per cone a 3D DDA walks the level whose voxel matches the cone's footprint (Algorithm 1,
//! line 7), switching to a coarser level only where the ray crosses a plane of the coarser
//! grid, and skipping empty 4³ bricks whole (a bit per brick, a 64-bit mask per occupied
//! brick). Opening is lazy: [`LodScene::open`] maps the file and reads its index; a level's
//! skeleton (occupancy and block ranges) is built the first time a cone needs the level, once,
//! thread-safely, and each block of voxels or faces is inflated, verified and prepared the first
//! time a cone needs it, into a [`BlockCache`] shared by every aggregate opened with it (by
//! default the process's, [`BlockCache::global`]), bounded by a byte budget: what stays in
//! memory follows the picture, not the aggregate. Tracing allocates nothing but the blocks it
//! prepares. No NaN or infinity leaves the runtime: where one would, it is
//! counted ([`crate::math::numerics`]) and replaced by zero.

mod cache;
mod hits;
mod level;
mod shade;
mod volume;

use std::path::Path;
use std::sync::{Arc, OnceLock};

use glam::{Vec2, Vec3};

use crate::absdf::Absdf;
use crate::bsdf::{Bsdf, BsdfSample};
use crate::film::Stratified;
use crate::format::{Aggregate, FormatError};
use crate::lights::Lights;
use crate::math::rng::Pcg32;
use crate::math::sampling::Sampler;
use crate::spatial::Grid;

pub use cache::{default_budget, BlockCache, CacheStats};
pub use hits::{Hit, Hits, Occlusion, OCCLUSION_ONSET};
pub(crate) use shade::Walk;
pub use shade::{shade, Placement};

/// A cone: a centre ray and the full angle of its aperture (Algorithm 1's r and θ).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cone {
    /// Origin of the centre ray.
    pub origin: Vec3,
    /// Unit direction of the centre ray.
    pub dir: Vec3,
    /// Full aperture angle in radians (a pixel's cone: the angle the pixel subtends).
    pub aperture: f32,
    /// The part of the ray traced: from `tmin` to `tmax`.
    pub tmin: f32,
    /// See `tmin`; a host clips it to its own nearer surface.
    pub tmax: f32,
}

impl Cone {
    /// The cone of one sample of the shared image loop ([`crate::film::render_image`]): the
    /// pixel's aperture, over the whole ray.
    pub fn of_sample(s: &crate::film::Sample) -> Cone {
        let (origin, dir) = s.ray();
        Cone {
            origin,
            dir,
            aperture: s.aperture,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }

    /// A cone over the whole ray (t from 0 to infinity); `dir` is normalised.
    pub fn new(origin: Vec3, dir: Vec3, aperture: f32) -> Cone {
        Cone {
            origin,
            dir: dir.normalize_or_zero(),
            aperture,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }
}

/// What stands for a voxel's geometry.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum PrimitiveKind {
    /// The paper's truncated ellipsoid.
    #[default]
    TruncatedEllipsoid,
    /// The whole voxel (the Fig. 6 ablation).
    Cube,
    /// No primitive and no aggregated visibility: the voxel as a homogeneous medium with
    /// exponential transmittance (the "traditional volumetric model", a quality-study baseline;
    /// see `volume.rs`).
    Volume,
}

/// How [`LodScene::trace`] turns a cone's hits into radiance.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shading {
    /// Shade every primitive met and sum (Eq. 30 term by term).
    Every,
    /// Shade `picks` primitives chosen in proportion to their coverage weight by weighted
    /// reservoir sampling, each standing for the whole weight: an unbiased estimate of the same
    /// sum at the cost of `picks` shadings per cone, however many voxels the cone crosses.
    Reservoir {
        /// Primitives shaded per cone (1 or more).
        picks: u32,
        /// Shade a cone whose total coverage weight W is below one only with probability W
        /// (and weigh it by 1/W): still unbiased, and a cone grazing the aggregate's fringe is
        /// shaded as often as a ray of the reference renderer hits there. Off by default: it
        /// saves 10–19% of a 64² render's CPU time but raises the noise variance 2.4–5× on the
        /// quality study's scenes (`tools/src/bin/shading_noise.rs`), a loss at equal time too.
        roulette: bool,
    },
}

impl Default for Shading {
    fn default() -> Self {
        Shading::Reservoir {
            picks: 1,
            roulette: false,
        }
    }
}

/// Render-time options.
#[derive(Clone, Copy, Debug)]
pub struct TraceSettings {
    /// Light samples and ABSDF samples per shaded primitive (MIS; Algorithm 1's m).
    pub nee: u32,
    /// Force this level (0 = finest) instead of choosing by footprint.
    pub level: Option<usize>,
    /// The primitive.
    pub primitive: PrimitiveKind,
    /// Every primitive shaded, or a weighted few.
    pub shading: Shading,
    /// Divide each cone's surfaces and background weight by the sum of its weights,
    /// Σ V̂(ω_o)|A|_ω/|B|_ω + V̂_b (Eq. 30), which is 1 wherever the baked visibility is
    /// consistent: where the AIV's and the ABV's Monte Carlo and truncation errors make it
    /// more or less than 1, the pixel is too bright or too dark by that much. The error budget
    /// (`aggtool eval --budget`, issue 17) measured it removing 48% of the chandelier's bias at
    /// 64³ and 17% of the maple's (see the README's "Quality and speed studies"). Before the
    /// division, the hits behind surfaces that already cover most of the cone are attenuated
    /// ([`Occlusion`]: the hidden voxels' small baked V̂(ω_o) would otherwise mix their unlit
    /// surfaces in). Off: Eq. 30's weights as baked.
    pub normalize: bool,
    /// Continuous level of detail: [`LodScene::trace`] chooses each cone's level between the
    /// footprint's two neighbours with one random number of the cone
    /// ([`LodScene::hits_dithered`]), so that a moving camera sees levels blend instead of
    /// switching at a distance (popping). Off: the footprint's level, ⌊log2(tan(θ/2)·t/s)⌋.
    pub continuous_lod: bool,
    /// Samples of a pixel that shade from one walk in the image loop ([`render`]): a pixel's
    /// `spp` samples share ⌈spp / this⌉ walks of the pixel's cone, stratified over the pixel's
    /// area and over the level's dither, and each sample still draws its own shading (which
    /// hit, the light and ABSDF samples). 1 walks every sample's own cone; 0 (the default)
    /// chooses ([`TraceSettings::walk_reuse`]). The pixel's cone already covers the pixel, so
    /// fewer walks cost only the variance of which voxels the cone meets, and the walk is
    /// about half of a cone's time. Where the finest voxels are wider than a pixel's cone,
    /// the default shares further ([`MAX_MAGNIFIED_SHARING`]). Hosts' batches
    /// ([`LodScene::trace_batch`]) trace their own cones.
    pub samples_per_walk: u32,
    /// Level-of-detail bias, in levels: each cone chooses its level as if its footprint were
    /// 2^bias times as wide (a texture sampler's LOD bias). +1 walks the next coarser level,
    /// whose voxels a cone crosses half as many of, for about half the walk's time and a
    /// blurrier picture; negative values are sharper and slower. 0 (the default) is
    /// Algorithm 1's choice. Non-finite values count as 0.
    pub lod_bias: f32,
}

/// Most levels of magnification by which a pixel's walks are shared further
/// ([`render_sharing_walks`], [`magnified_reuse`]): a pixel whose cone is narrower than the
/// finest voxels by 2^m needs [`MIN_SHARED_WALKS`] / 2^min(m, this) walks, and shares each
/// among 2^min(m, this) times the default's samples from 64 spp up.
///
/// Measured at 64 spp (`aggtool render --samples-per-walk 2, 4, 8` against a 1,024-spp
/// reference; the book's magnified-walks page): where the finest voxels are 2^1.1 times the
/// cone (the maple's 128³ bake at 256²) sharing each walk among 4 samples instead of 2 adds
/// 1.1% to the RMSE for 0.68× the CPU time, among 8 4.8%; where they are 2^2.1–2^2.4 times
/// (64³ bakes at 256²), among 8 adds 0.7–2.2% for 0.54–0.58×; unmagnified (64³ bakes at 64²),
/// among 4 adds 6–14%. At 16 spp, 2^2.1–2^2.4 times: pairs add 0.4–1.2% for 0.64–0.66×, fours
/// 2–6%; 2^1.1 times: pairs 2.7%.
pub const MAX_MAGNIFIED_SHARING: u32 = 2;

/// The fewest walks a pixel gets when [`TraceSettings::samples_per_walk`] is left to choose:
/// below them the variance of which voxels (and, in an assembly, which meshes) the cone meets
/// shows. Measured: sharing walks in pairs at 16 spp raised the city's RMSE by 16%; at 64 spp
/// the maple's by 0.5–1% (see the book's shared-walks page).
pub const MIN_SHARED_WALKS: u32 = 32;

impl TraceSettings {
    /// [`TraceSettings::lod_bias`] as the level choice reads it: within ±16 levels, 0 where
    /// it is not finite.
    #[inline]
    pub(crate) fn bias_levels(&self) -> f32 {
        if self.lod_bias.is_finite() {
            self.lod_bias.clamp(-16.0, 16.0)
        } else {
            0.0
        }
    }

    /// The samples a pixel's walk serves at `spp` samples a pixel: `samples_per_walk` where
    /// set, else 2 where that leaves at least [`MIN_SHARED_WALKS`] walks, else 1.
    pub fn walk_reuse(&self, spp: u32) -> u32 {
        match self.samples_per_walk {
            0 if spp >= 2 * MIN_SHARED_WALKS => 2,
            0 => 1,
            r => r,
        }
    }
}

impl Default for TraceSettings {
    fn default() -> Self {
        TraceSettings {
            nee: 1,
            level: None,
            primitive: PrimitiveKind::TruncatedEllipsoid,
            shading: Shading::default(),
            normalize: true,
            continuous_lod: true,
            samples_per_walk: 0,
            lod_bias: 0.0,
        }
    }
}

/// What a cone brings back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConeResult {
    /// Radiance towards the cone's origin, background included.
    pub radiance: Vec3,
    /// The background's weight in `radiance` (1 when the cone met nothing).
    pub transmittance: f32,
    /// Primitives the centre ray met.
    pub primitives: u32,
    /// The surfaces' share of the cone, Σ V̂(ω_o)·|A|_ω/|B|_ω over the primitives met (the
    /// alpha of the aggregate). In expectation over a pixel, coverage + transmittance ≈ 1.
    pub coverage: f32,
}

impl ConeResult {
    /// The surfaces' radiance plus the background through `transmittance`. A non-finite sum
    /// is counted ([`crate::math::numerics`]) and replaced by zero.
    pub(crate) fn compose(
        surfaces: Vec3,
        background: Vec3,
        transmittance: f32,
        primitives: u32,
        coverage: f32,
    ) -> ConeResult {
        ConeResult {
            radiance: crate::math::finite_vec_or_zero(surfaces + background * transmittance),
            transmittance: crate::math::finite_or_zero(transmittance),
            primitives,
            coverage: crate::math::finite_or_zero(coverage),
        }
    }
}

/// Why an aggregate could not be opened or a level prepared.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    /// The file could not be read or failed verification.
    #[error("{0}")]
    Format(#[from] FormatError),
    /// A level's blocks failed verification.
    #[error("level {level}: {message}")]
    Level {
        /// The level (0 = finest).
        level: usize,
        /// What was wrong.
        message: String,
    },
}

/// An opened aggregate ready for cone tracing: owns the mapped file; levels are prepared on
/// first use.
pub struct LodScene {
    /// Prepared levels, borrowing from `agg`'s bytes. Declared before `agg` so that it is
    /// dropped first.
    levels: Vec<OnceLock<Result<level::Level<'static>, String>>>,
    grids: Vec<Grid>,
    /// Per level, the box a cone's walk is clipped to: the source asset's recorded bounds
    /// snapped outwards to the level's voxels and padded as its primitives are
    /// ([`crate::spatial::VOXEL_PAD`]). Every occupied voxel holds surface, so it lies in
    /// this box, and the walk need not cross the empty rest of the level's cube (on a tall
    /// tree a third of the steps). The level's cube where the file records no bounds.
    clip: Vec<(Vec3, Vec3)>,
    /// Finest voxel size.
    base: f32,
    /// Per level, the level holding its interior visibility and the shift from its voxel
    /// coordinates to that level's ([`Aggregate::shading_of`]): itself and 0, or for a
    /// visibility level the coarser level whose voxels hold its AIVs and exposures.
    shading: Vec<(usize, u32)>,
    cache: Arc<BlockCache>,
    /// Whether levels learn their voxels from the index's keys where the file has them
    /// (otherwise from the blocks, as for older files).
    index_keys: bool,
    agg: Aggregate,
}

/// The box a walk through level grid `g` is clipped to, for a source whose bounds are
/// [`lo`, `hi`] ([`LodScene`]'s `clip`): those bounds snapped outwards to the grid's voxels,
/// one voxel more on each side against rounding, padded by [`crate::spatial::VOXEL_PAD`] and
/// kept inside the cube (a flat source, such as a plane, still gets a box a voxel or more
/// thick); the cube itself when the bounds are missing (a point) or not finite.
fn clip_box(g: &Grid, lo: Vec3, hi: Vec3) -> (Vec3, Vec3) {
    let (cube_lo, cube_hi) = g.bounds();
    if !(lo.is_finite() && hi.is_finite() && lo.cmple(hi).all() && lo != hi) {
        return (cube_lo, cube_hi);
    }
    let s = g.voxel_size();
    let pad = Vec3::splat(crate::spatial::VOXEL_PAD * s);
    let a = ((lo - g.origin) / s).floor() - 1.0;
    let b = ((hi - g.origin) / s).ceil() + 1.0;
    let clo = (g.origin + a * s - pad).max(cube_lo);
    let chi = (g.origin + b * s + pad).min(cube_hi);
    if clo.cmplt(chi).all() {
        (clo, chi)
    } else {
        (cube_lo, cube_hi)
    }
}

impl LodScene {
    /// Opens an aggregate lazily: maps the file and verifies its header and index (milliseconds
    /// for a file of any size); levels are read and verified when cones first need them.
    /// Its blocks go to the process's shared cache ([`BlockCache::global`]).
    pub fn open(path: &Path) -> Result<LodScene, RuntimeError> {
        Ok(Self::new(Aggregate::open_lazy(path)?))
    }

    /// [`LodScene::open`] with the blocks prepared into `cache` (shared with whatever else
    /// was opened with it).
    pub fn open_with_cache(path: &Path, cache: Arc<BlockCache>) -> Result<LodScene, RuntimeError> {
        Ok(Self::with_cache(Aggregate::open_lazy(path)?, cache))
    }

    /// A scene over an opened aggregate, its blocks in the process's shared cache.
    pub fn new(agg: Aggregate) -> LodScene {
        Self::with_cache(agg, BlockCache::global().clone())
    }

    /// A scene over an opened aggregate, its blocks in `cache`.
    pub fn with_cache(agg: Aggregate, cache: Arc<BlockCache>) -> LodScene {
        let grids: Vec<Grid> = (0..agg.level_count()).map(|l| agg.grid(l)).collect();
        let (lo, hi) = agg.bounds();
        let clip = grids.iter().map(|g| clip_box(g, lo, hi)).collect();
        let shading = (0..grids.len()).map(|l| agg.shading_of(l)).collect();
        LodScene {
            levels: (0..grids.len()).map(|_| OnceLock::new()).collect(),
            shading,
            base: grids.first().map_or(1.0, |g| g.voxel_size()),
            clip,
            index_keys: true,
            grids,
            cache,
            agg,
        }
    }

    /// The cache this scene's blocks are prepared into.
    pub fn cache(&self) -> &Arc<BlockCache> {
        &self.cache
    }

    /// Bytes of the skeletons of the levels prepared so far (resident while the scene is
    /// open, outside the cache's budget: occupancy bits, bricks, block ranges).
    pub fn skeleton_bytes(&self) -> usize {
        self.levels
            .iter()
            .filter_map(|l| l.get().and_then(|r| r.as_ref().ok()))
            .map(|l| l.skeleton_bytes())
            .sum()
    }

    /// The aggregate.
    pub fn aggregate(&self) -> &Aggregate {
        &self.agg
    }

    /// Number of levels (0 = finest).
    pub fn level_count(&self) -> usize {
        self.grids.len()
    }

    /// The grid of level `l`.
    pub fn grid(&self, l: usize) -> Grid {
        self.grids[l]
    }

    /// The bounds of the finest level's cube (the whole aggregate), for framing views.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        self.grids.first().map(|g| g.bounds())
    }

    /// The box that cones of full aperture `aperture` walk in up to ray parameter `t_max`:
    /// the union of the clip boxes of the levels their footprints can choose before `t_max`
    /// (the walk's level only grows with t: at most ⌊log2(tan(θ/2)·2^(bias+1/2)·t_max/s)⌋,
    /// the half level for continuous level of detail's dither), or the forced level's. A cone
    /// whose ray misses it before `t_max` meets no primitive (no hits, transmittance 1), so a
    /// host may skip such cones before calling in: the Mitsuba host culls its rays with it.
    /// Every level's box for an infinite `t_max`; `None` without levels.
    pub fn walk_bounds(
        &self,
        aperture: f32,
        t_max: f32,
        settings: &TraceSettings,
    ) -> Option<(Vec3, Vec3)> {
        let n = self.clip.len();
        let last = match settings.level {
            Some(l) => l.min(n.checked_sub(1)?),
            None => {
                let tan = (0.5 * aperture).tan() * (settings.bias_levels() + 0.5).exp2();
                let x = tan * t_max / self.base;
                if x.is_nan() || x == f32::INFINITY {
                    n.checked_sub(1)?
                } else {
                    self.level_for_tan(tan, t_max)
                }
            }
        };
        let first = settings.level.map_or(0, |l| l.min(last));
        self.clip[first..=last]
            .iter()
            .copied()
            .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))
    }

    /// The level (0 = finest) whose voxel matches a cone of full aperture `aperture` at
    /// distance `t` (Algorithm 1, line 7: ⌊log2(tan(θ/2)·t / s)⌋, clamped).
    #[inline]
    pub fn level_for(&self, aperture: f32, t: f32) -> usize {
        self.level_for_tan((0.5 * aperture).tan(), t)
    }

    /// log2(tan(θ/2)·t / s) for a cone of full aperture `aperture` at distance `t`: the
    /// footprint's level before line 7's floor (negative where the cone is finer than the
    /// finest voxels), which [`Self::level_for`] floors and clamps and continuous level of
    /// detail ([`TraceSettings::continuous_lod`]) dithers.
    pub fn fractional_level(&self, aperture: f32, t: f32) -> f32 {
        ((0.5 * aperture).tan() * t / self.base).log2()
    }

    /// By how many whole levels the finest voxels are wider than `cone` inside the aggregate:
    /// ⌊−log2(tan(θ/2)·2^bias·t / s)⌋ at the ray parameter t halfway through the finest
    /// level's clip box, s the finest voxel size; 0 where the cone is as wide as the voxels
    /// there (its footprint's level is then the finest or a coarser one) or `settings`
    /// forces a level; `None` where the cone misses the box. The image loop shares the walks
    /// of a pixel whose centre cone this is as [`magnified_reuse`] says; a host that shares
    /// walks does the same.
    pub fn magnification(&self, cone: &Cone, settings: &TraceSettings) -> Option<u32> {
        let &(lo, hi) = self.clip.first()?;
        let (t0, t1) = crate::spatial::box_interval(lo, hi, cone.origin, cone.dir.recip());
        let (t0, t1) = (t0.max(cone.tmin), t1.min(cone.tmax));
        if !(t0 <= t1) {
            return None;
        }
        if settings.level.is_some() {
            return Some(0);
        }
        let f = self.fractional_level(cone.aperture, 0.5 * (t0 + t1)) + settings.bias_levels();
        // A cone of no width (f = −∞) or a NaN: no magnification to share by.
        Some(if f < 0.0 && f.is_finite() {
            (-f).floor().min(16.0) as u32
        } else {
            0
        })
    }

    /// [`Self::level_for`] with tan(θ/2) precomputed.
    #[inline]
    fn level_for_tan(&self, tan_half: f32, t: f32) -> usize {
        let x = tan_half * t / self.base;
        if !(x >= 2.0) {
            return 0;
        }
        (x.log2().floor() as usize).min(self.grids.len().saturating_sub(1))
    }

    /// Level `l`'s skeleton, built now if it was not: its voxel blocks verified and their keys
    /// read into the occupancy masks and bricks (the blocks themselves are prepared into the
    /// cache when cones need them). An error when no voxel block of the level verifies.
    pub fn prepare(&self, l: usize) -> Result<(), RuntimeError> {
        match self.level(l) {
            Some(_) => Ok(()),
            None => Err(RuntimeError::Level {
                level: l,
                message: self.levels[l]
                    .get()
                    .and_then(|r| r.as_ref().err().cloned())
                    .unwrap_or_else(|| "no such level".into()),
            }),
        }
    }

    /// Which levels' skeletons have been built so far (the levels cones have touched).
    pub fn prepared(&self) -> Vec<bool> {
        self.levels.iter().map(|l| l.get().is_some()).collect()
    }

    /// The resolutions of the levels prepared so far (the levels cones have touched).
    pub fn resolutions_used(&self) -> Vec<u32> {
        self.prepared()
            .iter()
            .enumerate()
            .filter(|(_, p)| **p)
            .map(|(l, _)| self.grid(l).res)
            .collect()
    }

    /// The first damaged block met so far, if any: a level none of whose blocks could be read
    /// was treated as empty, a block that could not be read as empty space (its voxels) or as
    /// no face (its faces); the rest of the scene rendered.
    pub fn first_error(&self) -> Option<RuntimeError> {
        self.levels
            .iter()
            .enumerate()
            .find_map(|(l, s)| match s.get() {
                Some(Err(e)) => Some(RuntimeError::Level {
                    level: l,
                    message: e.clone(),
                }),
                Some(Ok(lv)) => lv.error().map(|e| RuntimeError::Level {
                    level: l,
                    message: e.clone(),
                }),
                None => None,
            })
    }

    /// Level `l` prepared, or `None` when it failed (or does not exist).
    #[inline]
    fn level(&self, l: usize) -> Option<&level::Level<'_>> {
        let slot = self.levels.get(l)?;
        let r = slot.get_or_init(|| {
            let lv = level::Level::prepare(&self.agg, l, self.cache.clone(), self.index_keys)?;
            // SAFETY: the level borrows the bytes of `self.agg`, which this scene owns and
            // never mutates or drops before `self.levels` (field order); the bytes live in a
            // memory map or a heap buffer, so moving the scene does not move them. The
            // lifetime is narrowed back to `&self` by this function's signature.
            Ok(unsafe { std::mem::transmute::<level::Level<'_>, level::Level<'static>>(lv) })
        });
        r.as_ref().ok()
    }

    /// The same scene with its levels built from the voxel blocks' keys even where the index
    /// has them, as for files written before 2026-12-06: for tests that check both ways give
    /// the same walk.
    #[doc(hidden)]
    pub fn keys_from_blocks(mut self) -> LodScene {
        self.index_keys = false;
        self
    }

    /// The voxel with Morton key `key` at level `l` (0 = finest), as [`Hit::voxel`] hands it
    /// out: for hosts that keep (level, key) pairs, such as the C ABI's hit records. `None`
    /// when there is no such voxel or the level failed to prepare.
    pub fn voxel(&self, l: usize, key: u64) -> Option<VoxelHandle<'_>> {
        let data = self.level(l)?;
        let c = crate::spatial::demorton3(key);
        if key >> 63 != 0 || c.max_element() >= data.grid.res {
            return None;
        }
        let idx = data.find(c.as_ivec3())?;
        let block = data.voxels(idx)?;
        Some(VoxelHandle {
            data,
            i: idx - block.first,
            block,
            level: l,
            vis: self.visibility_voxel(l, c.as_ivec3()),
        })
    }

    /// For voxel `c` of visibility level `l` (format 1.7), the voxel of its shading level that
    /// contains it ([`Aggregate::shading_of`]: levels share one cube, so its coordinates are
    /// `c`'s shifted), whose AIV and exposure stand for the finer voxel's. `None` at a level
    /// that shades itself, or where that voxel is missing or its level cannot be read (the
    /// voxel then keeps its own stored AIV of 1, as a 1.6 reader reads it).
    #[inline]
    pub(crate) fn visibility_voxel(
        &self,
        l: usize,
        c: glam::IVec3,
    ) -> Option<(Arc<level::Voxels>, u32)> {
        let (sl, shift) = *self.shading.get(l)?;
        if sl == l {
            return None;
        }
        let level = self.level(sl)?;
        let idx = level.find(c >> shift as i32)?;
        let block = level.voxels(idx)?;
        let i = idx - block.first;
        Some((block, i))
    }

    /// Traces one cone with the runtime's lights and shading (Algorithm 1, Eq. 30).
    pub fn trace<S: Sampler + ?Sized>(
        &self,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
    ) -> ConeResult {
        shade::trace(self, cone, lights, settings, sampler)
    }

    /// [`LodScene::trace`] for a scene placed in a larger world (an instance of an assembly):
    /// `cone` is in the scene's own space, `lights` in the world's, directions are carried
    /// between the two by `place`, and light reaching a voxel is attenuated by
    /// [`Placement::occlusion`] besides the voxel's own AIV. The result's `radiance` holds the
    /// surfaces alone, **without the background**: the caller composes what lies behind through
    /// `transmittance`; with it comes the ray parameter of the first primitive met (infinite
    /// when none), by which a caller orders overlapping scenes along the cone.
    /// [`PrimitiveKind::Volume`] is not supported here (it is shaded as
    /// [`PrimitiveKind::TruncatedEllipsoid`]).
    pub fn trace_placed<S: Sampler + ?Sized, P: Placement + ?Sized>(
        &self,
        cone: &Cone,
        lights: &Lights,
        settings: &TraceSettings,
        sampler: &mut S,
        place: &P,
    ) -> (ConeResult, f32) {
        let mut settings = *settings;
        if settings.primitive == PrimitiveKind::Volume {
            settings.primitive = PrimitiveKind::TruncatedEllipsoid;
        }
        let (surfaces, transmittance, primitives, coverage, first) =
            shade::trace_surfaces(self, cone, lights, &settings, sampler, place);
        (
            ConeResult::compose(surfaces, Vec3::ZERO, transmittance, primitives, coverage),
            first,
        )
    }

    /// Traces a batch of cones in parallel with [`LodScene::trace`]: four floats per cone in
    /// `rgba` (radiance RGB, background transmittance). Cone `i` draws stream `i` of `seed`,
    /// so the result does not depend on the thread count. What the C ABI and the Python
    /// module call. `rgba` must hold `4 * cones.len()` floats (extra ones are left alone).
    pub fn trace_batch(
        &self,
        cones: &[Cone],
        lights: &Lights,
        settings: &TraceSettings,
        seed: u64,
        rgba: &mut [f32],
    ) {
        trace_batch_with(cones, seed, rgba, |c, rng| {
            self.trace(c, lights, settings, rng)
        });
    }

    /// [`LodScene::trace_batch`] for a host that draws several samples of each pixel, one
    /// call a pass: cone `i` is sample `at.sample` of pixel `at.pixels[i]`, stratified over
    /// the pixel's samples as the runtime's own image loop stratifies them ([`Stratified`],
    /// [`trace_batch_stratified_with`]). The same pixel ids with samples 0, 1, 2, … across
    /// calls give the pixel's estimate the image loop's lower variance; any one call is
    /// still an unbiased sample of each cone.
    pub fn trace_batch_stratified(
        &self,
        cones: &[Cone],
        at: PixelSamples<'_>,
        lights: &Lights,
        settings: &TraceSettings,
        seed: u64,
        rgba: &mut [f32],
    ) {
        trace_batch_stratified_with(cones, at, seed, rgba, |c, sampler| {
            self.trace(c, lights, settings, sampler)
        });
    }

    /// The primitives `cone` meets, appended to `out` (tagged `instance`), with their weights
    /// as a host compositing the aggregate over what lies behind it uses them; returns the
    /// transmittance. A cone that leaves the aggregate's bounds before `cone.tmax` gets the
    /// runtime's shading weights: Eq. 30's coverage weights (attenuated front to back) and the
    /// background's weight, each divided by their sum ([`TraceSettings::normalize`]). A cone
    /// that ends inside the bounds (at a host's surface, `cone.tmax`) keeps its weights and
    /// lets through max(T, 1 − Σw): the surfaces behind the cut are not there to make up the
    /// sum (an approximation where a mesh pierces an aggregate). The Mitsuba host's layer of
    /// an aggregate; [`crate::assembly::Assembly::layer_into`] composes instances' layers.
    pub fn layer_into(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        instance: u32,
        out: &mut Vec<LayerHit>,
    ) -> f32 {
        let start = out.len();
        let mut hits = self.hits(cone, settings);
        let mut sum = 0.0f32;
        for h in &mut hits {
            let weight = crate::math::finite_or_zero(h.weight);
            sum += weight;
            out.push(LayerHit {
                instance,
                level: h.voxel.level() as u32,
                key: h.voxel.key(),
                t: h.t,
                weight,
            });
        }
        let transmittance = crate::math::finite_or_zero(hits.transmittance());
        if out.len() > start {
            let (lo, hi) = self.aggregate().bounds();
            let (_, exit) = crate::spatial::box_interval(lo, hi, cone.origin, cone.dir.recip());
            if cone.tmax < exit {
                return transmittance.max((1.0 - sum).clamp(0.0, 1.0));
            }
        }
        let total = sum + transmittance;
        if total > 0.0 && total.is_finite() {
            for h in &mut out[start..] {
                h.weight /= total;
            }
            transmittance / total
        } else {
            transmittance
        }
    }

    /// The background's weight along a cone, the ABV of the face it enters the aggregate by
    /// (1 when it meets no primitive): what the aggregate lets through, for a host's shadow
    /// rays.
    pub fn transmittance(&self, cone: &Cone, settings: &TraceSettings) -> f32 {
        // The ABV is read at the first occupied voxel and counts from the first primitive met:
        // final there, so the walk stops (the rest of it cannot change the value).
        let mut h = self.hits(cone, settings);
        if h.next_primitive().is_some() {
            h.abv()
        } else {
            1.0
        }
    }
}

/// One primitive of a host's layer ([`LodScene::layer_into`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LayerHit {
    /// The instance of an assembly (0 for a single aggregate).
    pub instance: u32,
    /// The voxel's level (0 = finest).
    pub level: u32,
    /// The voxel's Morton key in its level.
    pub key: u64,
    /// Where the cone's centre ray enters the primitive (the cone's ray parameter).
    pub t: f32,
    /// Its weight in the layer (see [`LodScene::layer_into`]).
    pub weight: f32,
}

/// A voxel met by a cone: its ABSDF and its interior visibility. It holds the voxel's
/// prepared block (a reference count): the cache does not free a block while a handle to one
/// of its voxels lives.
#[derive(Clone)]
pub struct VoxelHandle<'s> {
    data: &'s level::Level<'s>,
    block: Arc<level::Voxels>,
    /// The voxel's index in its block.
    i: u32,
    level: usize,
    /// For a voxel of a visibility level (format 1.7), the voxel of the shading level that
    /// holds its interior visibility and exposure (block and index); `None` elsewhere.
    vis: Option<(Arc<level::Voxels>, u32)>,
}

impl<'s> VoxelHandle<'s> {
    /// The level the voxel belongs to (0 = finest).
    pub fn level(&self) -> usize {
        self.level
    }

    /// The voxel's Morton key in its level.
    pub fn key(&self) -> u64 {
        self.block.weight[self.i as usize].key
    }

    /// The voxel's ABSDF (Eq. 7–23), built the first time it is asked for.
    #[inline]
    pub fn absdf(&self) -> &Absdf<'static> {
        self.block.absdf(self.i)
    }

    /// The record holding the voxel's interior visibility and exposure: its own, or at a
    /// visibility level the containing voxel's of the shading level.
    #[inline]
    fn visibility_record(&self) -> &level::WeightRecord<'static> {
        match &self.vis {
            Some((b, i)) => &b.weight[*i as usize],
            None => &self.block.weight[self.i as usize],
        }
    }

    /// The interior visibility V̂(ω) of the voxel's surfaces towards unit `d` (Eq. 25); at a
    /// visibility level, that of the shading level's voxel containing it.
    #[inline]
    pub fn aiv(&self, d: Vec3) -> f32 {
        self.visibility_record().aiv.eval(d)
    }

    /// E|n·ω| of the voxel's surfaces towards unit `d`, from its normal lobes, as Eq. 24's
    /// coverage takes it ([`level::WeightRecord::mean_cosine`]).
    #[inline]
    pub fn mean_cosine(&self, d: Vec3) -> f32 {
        self.block.weight[self.i as usize].mean_cosine(d)
    }

    /// The voxel's exposure η in [1/16, 1] (see [`VoxelHandle::incident_visibility`]).
    #[inline]
    pub fn exposure(&self) -> f32 {
        1.0 / self.visibility_record().inv_exposure
    }

    /// The visibility to use for light arriving from `wi`: min(1, V̂(ω_i)/η), the AIV corrected
    /// for the correlation of incident and outgoing visibility by the voxel's exposure η (see
    /// the bake's interior visibility).
    #[inline]
    pub fn incident_visibility(&self, wi: Vec3) -> f32 {
        let w = self.visibility_record();
        (w.aiv.eval(wi) * w.inv_exposure).min(1.0)
    }
}

impl Bsdf for VoxelHandle<'_> {
    fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        self.absdf().eval(wi, wo)
    }
    fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        self.absdf().pdf(wi, wo)
    }
    fn eval_pdf(&self, wi: Vec3, wo: Vec3) -> (Vec3, f32) {
        self.absdf().eval_pdf(wi, wo)
    }
    fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        self.absdf().sample(wo, u_lobe, u)
    }
}

/// Renders an image with the LoD runtime through the shared image loop
/// ([`crate::film::render_image`]): `spp` cones per pixel, each of the pixel's aperture, with
/// the same stratified jitter and seeds as the reference renderer.
pub fn render(
    scene: &LodScene,
    camera: &crate::film::Camera,
    lights: &Lights,
    spp: u32,
    seed: u64,
    settings: &TraceSettings,
    progress: crate::util::Progress,
) -> (crate::film::Image, crate::film::ImageStats) {
    render_sharing_walks(
        camera,
        spp,
        seed,
        settings,
        progress,
        |cone, sampler| scene.trace(cone, lights, settings, sampler),
        |cone| scene.magnification(cone, settings).unwrap_or(0),
        |walk: &mut shade::Walk, cone, dither, pixel_dir| {
            walk.fill(scene, cone, lights, settings, dither, pixel_dir)
        },
        |walk, sampler| walk.estimate(lights, settings, sampler),
    )
}

/// The LoD's image loop, over [`crate::film::render_image_with`], for a single aggregate
/// ([`render`]) and an assembly ([`crate::assembly::render`]) alike: each sample traces its
/// own cone with `trace`, or, where [`TraceSettings::walk_reuse`] shares walks, runs of a
/// pixel's samples shade from one walk of kind `W`, which `start(walk, cone, dither,
/// pixel_dir)` begins (`pixel_dir` the pixel's centre ray, along which the walks of a pixel
/// take the |B|_ω of crossing primitives: [`shade::Walk::fill`]) and `estimate(walk,
/// sampler)` shades once a sample.
///
/// The pixel's samples fall in runs of `reuse` consecutive samples, run k shading from walk k
/// (walked by the run's first sample, [`shared_walk_cone`]); each sample's sampler skips the
/// dither's dimension, which the shared walk drew instead, so that its shading numbers stay
/// in the dimensions a sample of its own would give them. Where the reuse is the default's
/// ([`TraceSettings::samples_per_walk`] 0), a pixel whose centre cone `magnification` finds m
/// levels finer than the finest voxels ([`LodScene::magnification`]) has the longer runs of
/// [`magnified_reuse`] (walks from across a pixel that narrow meet the same voxels); a pixel
/// left at runs of 1 traces each sample's own cone with `trace`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn render_sharing_walks<W: Default>(
    camera: &crate::film::Camera,
    spp: u32,
    seed: u64,
    settings: &TraceSettings,
    progress: crate::util::Progress,
    trace: impl Fn(&Cone, &mut Stratified<'_, Pcg32>) -> ConeResult + Sync,
    magnification: impl Fn(&Cone) -> u32 + Sync,
    start: impl Fn(&mut W, &Cone, f32, Vec3) + Sync,
    estimate: impl Fn(&mut W, &mut Stratified<'_, Pcg32>) -> ConeResult + Sync,
) -> (crate::film::Image, crate::film::ImageStats) {
    let reuse = settings.walk_reuse(spp);
    // Only the default choice adapts to magnification; a reuse the user set is kept.
    let adapt = settings.samples_per_walk == 0 && settings.primitive != PrimitiveKind::Volume;
    if settings.primitive == PrimitiveKind::Volume || (reuse == 1 && !adapt) {
        return crate::film::render_image(camera, spp, seed, "LoD", progress, |mut s| {
            *s.rays += 1;
            let cone = Cone::of_sample(&s);
            trace(&cone, &mut Stratified::of_sample(&mut s)).radiance
        });
    }
    crate::film::render_image_with(
        camera,
        spp,
        seed,
        "LoD",
        progress,
        <(W, u32, Vec3)>::default,
        |mut s, (walk, pixel_reuse, pixel_dir)| {
            if s.index == 0 {
                *pixel_reuse = if adapt {
                    magnified_reuse(reuse, spp, magnification(&Cone::of_sample(&s)))
                } else {
                    reuse
                };
                *pixel_dir = camera.ray(s.pixel.as_vec2() + 0.5).1;
            }
            *s.rays += 1;
            let run = (*pixel_reuse).max(1);
            if run == 1 {
                // The pixel's samples walk their own cones, as without sharing.
                let cone = Cone::of_sample(&s);
                return trace(&cone, &mut Stratified::of_sample(&mut s)).radiance;
            }
            if s.index % run == 0 {
                let (cone, dither) = shared_walk_cone(camera, &s, run);
                start(walk, &cone, dither, *pixel_dir);
            }
            let mut sampler = Stratified::of_sample(&mut s);
            if shade::draws_dither(settings) {
                sampler.next_1d();
            }
            estimate(walk, &mut sampler).radiance
        },
    )
}

/// The samples each walk of a pixel serves under the default choice, for a pixel whose cone
/// is `m` levels narrower than the finest voxels ([`LodScene::magnification`]) at `spp`
/// samples a pixel, `reuse` being [`TraceSettings::walk_reuse`]'s: `reuse` where m is 0;
/// else `reuse` · 2^m where the pixel's walks are shared anyway (64 spp and more), and
/// below that as many as leave the pixel [`MIN_SHARED_WALKS`] / 2^m walks; m at most
/// [`MAX_MAGNIFIED_SHARING`].
pub fn magnified_reuse(reuse: u32, spp: u32, m: u32) -> u32 {
    let m = m.min(MAX_MAGNIFIED_SHARING);
    if m == 0 {
        reuse
    } else if reuse >= 2 {
        reuse.saturating_mul(1 << m)
    } else {
        (spp.saturating_mul(1 << m) / MIN_SHARED_WALKS).max(1)
    }
}

/// The cone and the level's dither of the walk sample `s` starts when a pixel's samples share
/// walks `reuse` at a time ([`TraceSettings::samples_per_walk`]; `s` is the first of its run).
/// The pixel's samples fall in runs of `reuse` consecutive samples, run k shading from walk k:
/// a run of the stratified sequence is itself stratified, so the shading numbers of one walk's
/// samples are spread out. Walk k's cone goes through point k of a (0, m, 2)-net over the
/// pixel and its dither through point k of another sequence, scrambled by the pixel's own
/// seed: the walks are stratified over the pixel's area and the level's blend.
pub(crate) fn shared_walk_cone(
    camera: &crate::film::Camera,
    s: &crate::film::Sample,
    reuse: u32,
) -> (Cone, f32) {
    let k = s.index / reuse;
    let h = crate::math::rng::mix64(((s.pixel_seed as u64) << 32) ^ 0x5741_4c4b);
    let seeds = [h as u32, (h >> 32) as u32, (h >> 16) as u32 ^ 0x9e37_79b9];
    let p = s.pixel.as_vec2() + crate::math::lowdiscrepancy::shifted_2d(k, seeds);
    let dither = crate::math::lowdiscrepancy::shifted_1d(
        k,
        [seeds[2].rotate_left(7) ^ 0x85eb_ca6b, seeds[0] ^ seeds[1]],
    );
    let (origin, dir) = camera.ray(p);
    let cone = Cone {
        origin,
        dir,
        aperture: s.aperture,
        tmin: 0.0,
        tmax: f32::INFINITY,
    };
    (cone, dither)
}

/// Which sample of which pixel each cone of a host's batch is
/// ([`LodScene::trace_batch_stratified`]).
#[derive(Clone, Copy, Debug)]
pub struct PixelSamples<'a> {
    /// One id per cone: the host's pixel (any number, the same for the same pixel in every
    /// call). Ids should be distinct within a call: two cones with the same id and sample
    /// draw the same random numbers (a host tracing several samples of a pixel in one batch
    /// passes them in separate calls, or as separate ids).
    pub pixels: &'a [u64],
    /// The index of this call's sample in every pixel: 0, 1, 2, … over a host's passes.
    pub sample: u32,
}

/// [`trace_batch_with`] with each cone's first [`crate::film::STRATIFIED_DIMENSIONS`] numbers stratified
/// over its pixel's samples ([`Stratified`], seeded by [`crate::film::pixel_seed`] as the image
/// loop's); the numbers after them come from stream `pixels[i]` of a seed of `seed` and the
/// sample, so that passes are independent. Cones beyond `at.pixels` (or `rgba`) are left
/// alone; callers check the lengths. The result does not depend on the thread count.
pub fn trace_batch_stratified_with(
    cones: &[Cone],
    at: PixelSamples<'_>,
    seed: u64,
    rgba: &mut [f32],
    trace: impl Fn(&Cone, &mut Stratified<'_, Pcg32>) -> ConeResult + Sync,
) {
    use rayon::prelude::*;
    let pass_seed = crate::math::rng::mix64(seed ^ crate::math::rng::mix64(at.sample as u64));
    rgba.par_chunks_mut(4)
        .zip(cones.par_iter().zip(at.pixels.par_iter()))
        .for_each(|(o, (c, &pixel))| {
            let mut rng = Pcg32::new(pass_seed, pixel);
            let mut sampler =
                Stratified::new(&mut rng, at.sample, crate::film::pixel_seed(seed, pixel));
            let r = trace(c, &mut sampler);
            o.copy_from_slice(&[r.radiance.x, r.radiance.y, r.radiance.z, r.transmittance]);
        });
}

/// The one batched cone loop: traces `cones` in parallel with `trace`, cone i drawing stream
/// i of `seed` (so the result does not depend on the thread count), into `rgba`, 4 floats a
/// cone (radiance, background transmittance). [`LodScene::trace_batch`] and the assemblies'
/// batch (the C ABI, the Python module) are this loop with their own `trace`.
pub fn trace_batch_with(
    cones: &[Cone],
    seed: u64,
    rgba: &mut [f32],
    trace: impl Fn(&Cone, &mut Pcg32) -> ConeResult + Sync,
) {
    use rayon::prelude::*;
    rgba.par_chunks_mut(4)
        .zip(cones.par_iter())
        .enumerate()
        .for_each(|(i, (o, c))| {
            let mut rng = Pcg32::new(seed, i as u64);
            let r = trace(c, &mut rng);
            o.copy_from_slice(&[r.radiance.x, r.radiance.y, r.radiance.z, r.transmittance]);
        });
}

#[cfg(test)]
mod clip_tests {
    use super::clip_box;
    use crate::spatial::Grid;
    use glam::Vec3;

    /// The clip box holds the source's bounds with a voxel to spare, stays in the cube, is a
    /// voxel or more thick for a flat source, and is the cube where the bounds are missing.
    #[test]
    fn clip_boxes_hold_the_source() {
        let g = Grid {
            origin: Vec3::new(-1.0, 0.0, 2.0),
            size: 4.0,
            res: 16,
        };
        let (cube_lo, cube_hi) = g.bounds();
        let s = g.voxel_size();
        let (lo, hi) = (Vec3::new(-0.3, 0.6, 2.9), Vec3::new(1.1, 1.7, 3.3));
        let (clo, chi) = clip_box(&g, lo, hi);
        assert!(
            clo.cmple(lo - s).all() && chi.cmpge(hi + s).all(),
            "{clo} {chi}"
        );
        assert!(clo.cmpge(cube_lo).all() && chi.cmple(cube_hi).all());
        assert!(
            (chi - clo).cmplt(cube_hi - cube_lo).any(),
            "no tighter than the cube"
        );
        // A plane: flat in y.
        let (plo, phi) = clip_box(&g, Vec3::new(0.0, 1.0, 3.0), Vec3::new(1.0, 1.0, 4.0));
        assert!(
            phi.y - plo.y >= 2.0 * s && plo.y < 1.0 && phi.y > 1.0,
            "{plo} {phi}"
        );
        // Missing (a point, as files without bounds read), not finite, or outside the cube.
        for (a, b) in [
            (Vec3::ZERO, Vec3::ZERO),
            (Vec3::splat(f32::NAN), Vec3::ONE),
            (Vec3::splat(50.0), Vec3::splat(60.0)),
        ] {
            assert_eq!(clip_box(&g, a, b), (cube_lo, cube_hi), "{a} {b}");
        }
    }
}
