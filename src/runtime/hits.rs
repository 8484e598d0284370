//! The traversal layer: a cone's walk through the aggregate, as an iterator of [`Hit`]s
//! (Algorithm 1, lines 6–12, 19).
//!
//! The walk is a hierarchical DDA over the level's occupancy: cells of 4^g voxels for
//! g = top … 0, one bit each; an empty cell is crossed in one step, an occupied one is entered
//! and walked at the next finer granularity, down to the voxels, found in their brick's 64-bit
//! mask. The level is the footprint's (line 7), and changes to a coarser one only where the ray
//! crosses a plane that is also a plane of the coarser grid, as in the paper ("we switch to a
//! coarser LoD only at the boundary of the coarser voxels"). The face through which the ray
//! entered the first occupied voxel gives the ABV (lines 9–10).

use std::sync::Arc;

use glam::{IVec3, Vec3};

use super::level::{Brick, Level, ViewerAiv, Voxels, BRICK, MAX_GRANULARITY};
use super::{Cone, LodScene, PrimitiveKind, TraceSettings, VoxelHandle};
use crate::spatial::entry_axis;
use crate::spatial::entry_face;
use crate::spatial::AreaCase;
use crate::spatial::{box_interval, box_projected_area, truncated_entry, Dda};

/// A primitive the cone met.
#[derive(Clone)]
pub struct Hit<'s> {
    /// The voxel: its ABSDF and AIV.
    pub voxel: VoxelHandle<'s>,
    /// Ray parameter where the centre ray enters the primitive.
    pub t: f32,
    /// The coverage weight V̂(ω_o)·|A|_ω/|B|_ω of Eq. 30: the voxel's share of the cone;
    /// under [`TraceSettings::normalize`] (the default) attenuated by the surfaces in front
    /// ([`Occlusion`]).
    pub weight: f32,
    /// The exact |B|_ω of a primitive crossing its voxel where the walk computed it for
    /// [`Occlusion`] under [`Weights::Bound`] (along the pixel's centre ray for a pixel's
    /// shared walks, [`AreaCache`]), else 0: [`Hits::exact_factor`] reuses it.
    pub(crate) exact_area: f32,
}

/// The exact |B|_ω of the crossing primitives a pixel's shared walks met ([`Walk::fill`]'s
/// `pixel_dir`): all of a pixel's walks take |B|_ω along the pixel's centre ray, so a voxel
/// that several of them meet computes it once. The values are a function of the voxel and
/// that direction alone (what is kept only spares the work), so renders do not depend on it.
///
/// [`Walk::fill`]: super::shade::Walk::fill
pub(crate) struct AreaCache {
    /// The scene and the direction the entries are for.
    scene: usize,
    dir: Vec3,
    /// Entries of an older scene or direction are those of another generation.
    generation: u32,
    /// Direct-mapped: the voxel's level << 40 | index, its generation, and |B|_ω.
    keys: [u64; AREA_CACHE_SLOTS],
    generations: [u32; AREA_CACHE_SLOTS],
    areas: [f32; AREA_CACHE_SLOTS],
}

/// Entries of an [`AreaCache`]. A pixel's walks meet a few hundred crossing voxels where the
/// voxels are about a pixel wide: on the maple's 128³ bake at 256² and a 1M-triangle tree's
/// 64³ bake at 64², 64 entries kept 23–66% of the areas computed again, 512 entries 71–73%.
const AREA_CACHE_SLOTS: usize = 512;

impl AreaCache {
    pub(crate) fn new() -> Box<AreaCache> {
        Box::new(AreaCache {
            scene: 0,
            dir: Vec3::ZERO,
            generation: 1,
            keys: [0; AREA_CACHE_SLOTS],
            generations: [0; AREA_CACHE_SLOTS],
            areas: [0.0; AREA_CACHE_SLOTS],
        })
    }

    /// Keeps the entries if they are for scene `id` (its address) and `dir` (the same bits),
    /// else starts a new generation.
    pub(crate) fn aim(&mut self, id: usize, dir: Vec3) {
        let bits = |v: Vec3| v.to_array().map(f32::to_bits);
        if self.scene != id || bits(self.dir) != bits(dir) {
            self.scene = id;
            self.dir = dir;
            self.generation = self.generation.wrapping_add(1);
            if self.generation == 0 {
                // Wrapped: no entry may look current.
                self.generations = [0; AREA_CACHE_SLOTS];
                self.generation = 1;
            }
        }
    }

    /// |B|_ω along the cache's direction of voxel `idx` of level `li`, computed by `compute`
    /// the first time.
    #[inline]
    fn area(&mut self, li: usize, idx: u32, compute: impl FnOnce(Vec3) -> f32) -> f32 {
        let key = (li as u64) << 40 | idx as u64;
        let slot = (crate::math::rng::mix64(key) as usize) % AREA_CACHE_SLOTS;
        if self.keys[slot] != key || self.generations[slot] != self.generation {
            self.areas[slot] = compute(self.dir);
            self.keys[slot] = key;
            self.generations[slot] = self.generation;
        }
        self.areas[slot]
    }
}

/// The share of a cone the surfaces met so far may cover before the ones behind them are
/// attenuated ([`Occlusion`]).
pub const OCCLUSION_ONSET: f32 = 0.75;

/// Front-to-back occlusion of a cone's weights, part of [`TraceSettings::normalize`].
///
/// Eq. 30 adds the hits' weights V̂(ω_o)·|A|_ω/|B|_ω independently: V̂(ω_o), the AIV towards
/// the viewer, already holds the occlusion by everything in front, so a hit needs nothing
/// from the hits before it. The baked V̂ of a voxel hidden behind a solid is never quite 0,
/// though: a Monte Carlo estimate on a 32² map, blurred by the bandwidth and the wavelet
/// denoising, leaves it a few hundredths, and a cone through a solid prop meets many such
/// voxels, whose dark, unlit surfaces the normalisation then mixes into the visible one (on
/// the study's flat roofs 1–2% of the pixel; see the README's error budget). A cone's hits
/// therefore come attenuated by how much of it is still open: with S the sum of the weights
/// met so far, a hit's weight is scaled by
///
/// ```text
/// open(S) = clamp((1 − S) / (1 − OCCLUSION_ONSET), 0, 1)
/// ```
///
/// and the background's weight (the ABV) likewise at the end. Below the onset nothing
/// changes: a fence's or a lattice's front layer covering part of the cone leaves the layers
/// behind their own weights, which already count it. Once the surfaces met cover the whole
/// cone, nothing behind them counts and the walk stops. S counts the exact weights whichever
/// weights the walk yields, so that shading every hit and the reservoir's picks (which see
/// only bounds of |B|_ω, `Weights::Bound`) estimate the same attenuated sum; the exact |B|_ω
/// of a primitive crossing its voxel is the price.
///
/// Measured on the quality study's 40 assets (`aggtool eval ASSETS --res 32,64 --agg-dir`
/// on the same bakes, see the README): median of ours over ref@spp 2.66 → 2.50, 75 of the 80
/// rows better, geometric mean of the RMSE ratios 0.918; the fence 3–9% worse. Counting the
/// bounds with an onset of 1/2: 2.58 and 0.951 (the cube of `tests/runtime.rs`
/// `hidden_faces_stay_hidden` 0.0141 of red against 0.0036); exact with onset 0.7 / 0.85:
/// 0.916 / 0.923, the fence +9% / +4% at 32³; plain front-to-back compositing (onset 0,
/// bounds): 0.953, the fence +19–28%, the maple at 32³ +22%.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Occlusion {
    /// S: the sum of the attenuated weights met so far.
    covered: f32,
}

impl Occlusion {
    /// open(S): the factor the next hit's weight, or the background's, is scaled by.
    #[inline]
    pub fn open(&self) -> f32 {
        ((1.0 - self.covered) * (1.0 / (1.0 - OCCLUSION_ONSET))).clamp(0.0, 1.0)
    }

    /// The factor open(S) for the next hit, which is then counted in with `counted` (its
    /// weight) times that factor.
    #[inline]
    pub fn pass(&mut self, counted: f32) -> f32 {
        let a = self.open();
        self.covered += counted * a;
        a
    }

    /// The weight `w` of the next hit, attenuated by the ones before it; counted in.
    #[inline]
    pub fn attenuate(&mut self, w: f32) -> f32 {
        w * self.pass(w)
    }

    /// Whether nothing behind can count any more.
    #[inline]
    pub fn closed(&self) -> bool {
        self.covered >= 1.0
    }
}

/// How the walk weighs its hits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Weights {
    /// Eq. 30's weight with |B|_ω (the 64-point estimate where the ellipsoid crosses its
    /// voxel).
    Exact,
    /// The same with [`crate::spatial::TruncatedEllipsoid::projected_area_bound`] for |B|_ω:
    /// a lower bound of the weight, within a small factor, for choosing whom to shade; the
    /// chosen hit's weight is corrected by [`Hits::exact_factor`].
    Bound,
}

/// The walk of one cone: an iterator over the primitives it meets, in order.
pub struct Hits<'s> {
    scene: &'s LodScene,
    cone: Cone,
    inv: Vec3,
    settings: TraceSettings,
    /// Where the walk of the current level ends: the ray leaves its clip box, the cube or
    /// the cone's range.
    t_end: f32,
    /// Where the ray leaves the cube or the cone's range.
    t_far: f32,
    li: usize,
    level: Option<&'s Level<'s>>,
    /// One DDA per granularity, `g` the current one.
    ddas: [Dda; MAX_GRANULARITY],
    g: usize,
    /// The brick being walked when `g` is 0.
    brick: Option<Brick>,
    /// The prepared block of the last voxel tested (a cone's voxels are mostly in one).
    block: Option<Arc<Voxels>>,
    t: f32,
    entry_axis: usize,
    /// The ABV at the first occupied voxel, once met.
    vb: Option<f32>,
    /// That voxel and the face the cone entered it through (for [`Hits::entry`]).
    entry: (usize, IVec3, u8),
    primitives: u32,
    steps_left: u32,
    steps_max: u32,
    done: bool,
    weights: Weights,
    /// The front-to-back occlusion of the hits' weights (under `settings.normalize`).
    occlusion: Occlusion,
    /// The ray parameter from which the footprint asks for a coarser level than `li`.
    t_switch: f32,
    /// tan(θ/2) as the level choice reads it: times 2^(u − 1/2) for the cone's dither u under
    /// [`TraceSettings::continuous_lod`], and 2^bias for [`TraceSettings::lod_bias`].
    lod_tan: f32,
    /// Where the walk is one of a pixel's shared walks: the pixel's |B|_ω, taken along its
    /// centre ray ([`AreaCache`]); `None` takes |B|_ω along the cone's own direction.
    pub(crate) areas: Option<std::cell::RefCell<Box<AreaCache>>>,
}

/// tan(θ/2) of a cone's aperture θ: a pixel's cone is a few milliradians wide, where the
/// series x + x³/3 + 2x⁵/15 is exact to f32 precision (relative error below 2·10⁻⁷ for
/// x < 0.05; 2% of a cone's time went to `tanf` in the profile); `tan` above.
#[inline]
fn half_tan(aperture: f32) -> f32 {
    let x = 0.5 * aperture;
    if x.abs() < 0.05 {
        let x2 = x * x;
        x * (1.0 + x2 * (1.0 / 3.0 + x2 * (2.0 / 15.0)))
    } else {
        x.tan()
    }
}

impl LodScene {
    /// The primitives `cone` meets, in order (see [`Hit`]); once exhausted,
    /// [`Hits::transmittance`] is the background's weight.
    ///
    /// The level is the footprint's, ⌊log2(tan(θ/2)·t/s)⌋ (Algorithm 1, line 7); see
    /// [`LodScene::hits_dithered`] for the continuous choice [`LodScene::trace`] makes.
    pub fn hits(&self, cone: &Cone, settings: &TraceSettings) -> Hits<'_> {
        self.hits_weighted(cone, settings, Weights::Exact, None)
    }

    /// [`LodScene::hits`] with the level chosen stochastically between the footprint's two
    /// neighbours (continuous level of detail): with f = log2(tan(θ/2)·t/s) the walk takes
    /// level ⌊f + u − 1/2⌋ for the cone's dither `u` in [0, 1), so that a cone is at the
    /// finer of the two levels with probability 1 − frac(f + 1/2) and the mean over cones
    /// changes continuously with the distance, where ⌊f⌋ jumps a whole level at a threshold
    /// (a camera moving through it sees the aggregate "pop"). The 1/2 keeps the mean level
    /// where ⌊f⌋ has it on average. Ignored (the discrete choice) where
    /// [`TraceSettings::continuous_lod`] is off or a level is forced. [`LodScene::trace`] draws
    /// `u` as its sampler's first number: a host that walks and shades the hits itself matches
    /// it by doing the same.
    pub fn hits_dithered(&self, cone: &Cone, settings: &TraceSettings, u: f32) -> Hits<'_> {
        self.hits_weighted(cone, settings, Weights::Exact, Some(u))
    }

    /// [`LodScene::hits`] weighing hits with `weights` (built in place: the walk's state is a
    /// few hundred bytes, and moving it was 4% of a render).
    #[inline(always)]
    pub(crate) fn hits_weighted(
        &self,
        cone: &Cone,
        settings: &TraceSettings,
        weights: Weights,
        dither: Option<f32>,
    ) -> Hits<'_> {
        let mut h = Hits {
            scene: self,
            cone: *cone,
            inv: Vec3::ZERO,
            settings: *settings,
            t_end: 0.0,
            t_far: 0.0,
            li: 0,
            level: None,
            ddas: [Dda::IDLE; MAX_GRANULARITY],
            g: 0,
            brick: None,
            block: None,
            t: 0.0,
            entry_axis: 0,
            vb: None,
            entry: (0, IVec3::ZERO, 0),
            primitives: 0,
            steps_left: 0,
            steps_max: 0,
            done: true,
            weights,
            occlusion: Occlusion::default(),
            t_switch: f32::INFINITY,
            lod_tan: 0.0,
            areas: None,
        };
        self.restart_hits(&mut h, cone, settings, weights, dither);
        h
    }

    /// [`LodScene::hits_weighted`] into a walk's state `h` in place (its [`AreaCache`] kept):
    /// a pixel's walks reuse one state, and moving a new one into it was 2% of a render.
    #[inline(always)]
    pub(crate) fn restart_hits<'a>(
        &'a self,
        h: &mut Hits<'a>,
        cone: &Cone,
        settings: &TraceSettings,
        weights: Weights,
        dither: Option<f32>,
    ) {
        let inv = cone.dir.recip();
        let tan_half = half_tan(cone.aperture);
        let bias = settings.bias_levels();
        let lod_tan = match dither {
            Some(u) if super::shade::draws_dither(settings) && u.is_finite() => {
                tan_half * (u.clamp(0.0, 1.0) - 0.5 + bias).exp2()
            }
            _ if bias != 0.0 => tan_half * bias.exp2(),
            _ => tan_half,
        };
        h.scene = self;
        h.cone = *cone;
        h.inv = inv;
        h.settings = *settings;
        h.t_end = 0.0;
        h.t_far = 0.0;
        h.li = 0;
        h.level = None;
        h.ddas = [Dda::IDLE; MAX_GRANULARITY];
        h.g = 0;
        h.brick = None;
        h.block = None;
        h.t = 0.0;
        h.entry_axis = 0;
        h.vb = None;
        h.entry = (0, IVec3::ZERO, 0);
        h.primitives = 0;
        h.steps_left = 0;
        h.steps_max = 0;
        h.done = true;
        h.weights = weights;
        h.occlusion = Occlusion::default();
        h.t_switch = f32::INFINITY;
        h.lod_tan = lod_tan;
        let Some(g0) = self.grids.first().copied() else {
            return;
        };
        if !(cone.dir.is_finite() && cone.origin.is_finite() && cone.dir != Vec3::ZERO) {
            return;
        }
        let (lo, hi) = g0.bounds();
        let (c0, c1) = box_interval(lo, hi, cone.origin, inv);
        let (tmin, tmax) = (c0.max(cone.tmin), c1.min(cone.tmax));
        if !(tmin <= tmax) {
            return;
        }
        // The walk starts where the ray enters the level's clip box (the source's bounds on
        // its voxels), at the level the footprint asks for there.
        h.t_far = tmax;
        let mut li = h.pick(tmin);
        let mut span = self.clip_interval(li, cone, inv, tmin, tmax);
        if let Some((t0, _)) = span {
            let coarser = h.pick(t0);
            if coarser != li {
                li = coarser;
                span = self.clip_interval(li, cone, inv, tmin, tmax);
            }
        }
        let Some((t0, t1)) = span else {
            return;
        };
        h.t = t0;
        h.t_end = t1;
        h.entry_axis = if t0 > tmin {
            let (clo, chi) = self.clip[li];
            entry_axis(clo, chi, cone.origin, inv)
        } else {
            entry_axis(lo, hi, cone.origin, inv)
        };
        h.li = li;
        h.steps_left = 8 * g0.res + 64;
        h.steps_max = h.steps_left;
        h.done = !h.enter_level(None);
    }
}

impl LodScene {
    /// The part of [`t0`, `t1`] where the cone's ray is inside level `l`'s clip box.
    #[inline]
    fn clip_interval(
        &self,
        l: usize,
        cone: &Cone,
        inv: Vec3,
        t0: f32,
        t1: f32,
    ) -> Option<(f32, f32)> {
        let (lo, hi) = self.clip[l];
        let (a, b) = box_interval(lo, hi, cone.origin, inv);
        let (a, b) = (a.max(t0), b.min(t1));
        (a <= b).then_some((a, b))
    }
}

impl<'s> Hits<'s> {
    /// The cone walked.
    #[inline]
    pub fn cone(&self) -> Cone {
        self.cone
    }

    /// exact weight / bound weight of a hit yielded under [`Weights::Bound`].
    #[inline]
    pub(crate) fn exact_factor(&self, hit: &Hit) -> f32 {
        let (level, block, i) = (hit.voxel.data, &hit.voxel.block, hit.voxel.i);
        if self.settings.primitive != PrimitiveKind::TruncatedEllipsoid
            || block.hit[i as usize].area_case != Some(AreaCase::Crossing)
        {
            return 1.0;
        }
        let Some(p) = block.primitive(level, i) else {
            return 0.0;
        };
        let d = self.cone.dir;
        let exact = if hit.exact_area > 0.0 {
            hit.exact_area
        } else {
            p.projected_area(d)
        };
        if exact > 0.0 {
            p.projected_area_bound(d) / exact
        } else {
            0.0
        }
    }

    /// The level for parameter `t`: forced, or the footprint's.
    #[inline]
    fn pick(&self, t: f32) -> usize {
        let n = self.scene.grids.len();
        self.settings
            .level
            .unwrap_or_else(|| self.scene.level_for_tan(self.lod_tan, t))
            .min(n - 1)
    }

    /// Starts walking level `self.li`'s bricks at `self.t`, in brick `at` if given. False when
    /// the level cannot be prepared.
    fn enter_level(&mut self, at: Option<IVec3>) -> bool {
        let Some(level) = self.scene.level(self.li) else {
            return false;
        };
        self.level = Some(level);
        self.block = None;
        // Algorithm 1's line 7 asks for level li + 1 once tan(θ/2)·t/s ≥ 2^(li+1).
        self.t_switch = if self.settings.level.is_some() || self.li + 1 >= self.scene.grids.len() {
            f32::INFINITY
        } else {
            self.scene.base * (2u64 << self.li) as f32 / self.lod_tan
        };
        self.g = level.top;
        // A level of at most 4³ voxels is one brick, walked directly.
        self.brick = if level.top == 0 {
            level.brick(IVec3::ZERO)
        } else {
            None
        };
        self.ddas[self.g] = Dda::new(
            &level.grids[self.g],
            self.cone.origin,
            self.cone.dir,
            self.inv,
            self.t,
            at,
        );
        true
    }

    /// Primitives met so far.
    pub fn primitives(&self) -> u32 {
        self.primitives
    }

    /// The level, the first occupied voxel and the face (as [`entry_face`] numbers them) whose
    /// ABV [`Hits::abv`] is, once the cone met one (for the error budget's ABV oracles).
    pub fn entry(&self) -> Option<(usize, glam::UVec3, u8)> {
        self.vb
            .map(|_| (self.entry.0, self.entry.1.as_uvec3(), self.entry.2))
    }

    /// Traversal steps taken so far (bricks and voxels visited), for profiling.
    pub fn steps(&self) -> u32 {
        self.steps_max - self.steps_left
    }

    /// The background's weight: the ABV of the face where the cone entered the aggregate if it
    /// met any primitive (P⁺, Eq. 30), 1 otherwise; under [`TraceSettings::normalize`]
    /// attenuated by the surfaces met ([`Occlusion`]). Final once the iterator is exhausted.
    pub fn transmittance(&self) -> f32 {
        if self.primitives == 0 {
            return 1.0;
        }
        let abv = self.vb.unwrap_or(1.0);
        if self.settings.normalize {
            abv * self.occlusion.open()
        } else {
            abv
        }
    }

    /// The ABV of the face where the cone entered the aggregate (1 before it met a
    /// primitive): the background's weight as baked, with no occlusion applied.
    pub fn abv(&self) -> f32 {
        if self.primitives > 0 {
            self.vb.unwrap_or(1.0)
        } else {
            1.0
        }
    }

    /// The next primitive met (its level's data, level index, prepared block, index in the
    /// block and entry parameter), without its weight.
    ///
    /// The walk's hot state (the current granularity's DDA, the granularity, the ray
    /// parameter) lives in locals for the whole call and is written back once: kept in the
    /// struct and updated a field at a time, each step's reload of the voxel just stored
    /// stalled on store forwarding (8% of the walk's samples on one load).
    pub(crate) fn next_primitive(
        &mut self,
    ) -> Option<(&'s Level<'s>, usize, Arc<Voxels>, u32, f32, IVec3)> {
        if self.done {
            return None;
        }
        let mut level = self.level?;
        let mut g = self.g;
        let mut d = self.ddas[g];
        let mut t = self.t;
        let mut axis_in = self.entry_axis;
        let mut steps_left = self.steps_left;
        let t_end = self.t_end;
        let mut found = None;
        'walk: loop {
            if steps_left == 0 {
                self.done = true;
                break;
            }
            steps_left -= 1;
            let c = d.v;
            if g > 0 && level.occupied_at(g, c) {
                // Into the occupied cell: its children, from where the ray is.
                let child = g - 1;
                let cg = &level.grids[child];
                let lo = c * BRICK;
                let hi = (lo + IVec3::splat(BRICK - 1)).min(IVec3::splat(cg.res as i32 - 1));
                let p = self.cone.origin + self.cone.dir * t - cg.origin;
                let v = (p * (cg.res as f32 / cg.size)).as_ivec3().clamp(lo, hi);
                self.ddas[g] = d;
                d = d.child(v);
                if child == 0 {
                    self.brick = level.brick(c);
                }
                g = child;
                continue;
            }
            let t_exit = d.t_exit().min(t_end);
            if g == 0 {
                // A voxel of the current brick: test its primitive, then move on.
                let idx = self.brick.and_then(|b| Level::in_brick(&b, c));
                if let Some(idx) = idx {
                    if !self.block.as_ref().is_some_and(|b| b.holds(idx)) {
                        self.block = level.voxels(idx);
                    }
                }
                if let (Some(idx), Some(block)) = (idx, self.block.as_ref()) {
                    let i = idx - block.first;
                    let rec = &block.hit[i as usize];
                    if self.vb.is_none() {
                        let dir = entry_face(axis_in, d.step[axis_in]);
                        self.vb = Some(level.abv(c.as_uvec3(), dir, self.cone.dir));
                        self.entry = (self.li, c, dir);
                    }
                    let hit = match self.settings.primitive {
                        PrimitiveKind::TruncatedEllipsoid if rec.area_case.is_some() => {
                            truncated_entry(
                                rec.center,
                                rec.inv,
                                self.cone.origin,
                                self.cone.dir,
                                t - level.pad,
                                t_exit + level.pad,
                            )
                            .map(|th| th.max(t))
                        }
                        PrimitiveKind::TruncatedEllipsoid => None,
                        _ => Some(t),
                    };
                    if let Some(th) = hit {
                        self.primitives += 1;
                        found = Some((level, self.li, block.clone(), i, th, c));
                    }
                }
            }
            // Leave the cell (at `t_exit`): the next cell of the same granularity, or of a
            // coarser one where the ray leaves the parent too.
            if t_exit >= t_end {
                self.done = true;
                break;
            }
            let (axis, tc) = loop {
                let Some((axis, tc)) = d.advance() else {
                    self.done = true;
                    break 'walk;
                };
                // The cell was inside its parent: it left it if it crossed a multiple of 4.
                let x = d.v[axis] & 3;
                let left = if d.step[axis] > 0 { x == 0 } else { x == 3 };
                if left && g < level.top {
                    // Out of the parent cell: the parent crosses the same plane.
                    g += 1;
                    d = self.ddas[g];
                    continue;
                }
                break (axis, tc);
            };
            t = tc;
            axis_in = axis;
            if tc >= self.t_switch {
                // A coarser level where the footprint asks for one and the crossed plane
                // allows it: done on the struct, then the locals are read back.
                self.g = g;
                self.ddas[g] = d;
                self.t = t;
                self.entry_axis = axis_in;
                if !self.switch_level(axis, tc) {
                    self.done = true;
                    break;
                }
                match self.level {
                    Some(l) => level = l,
                    None => {
                        self.done = true;
                        break;
                    }
                }
                g = self.g;
                d = self.ddas[g];
            }
            if found.is_some() {
                break;
            }
        }
        self.g = g;
        self.ddas[g] = d;
        self.t = t;
        self.entry_axis = axis_in;
        self.steps_left = steps_left;
        found
    }

    /// Switches to a coarser level after the walk crossed a plane along `axis` at `tc` where
    /// the footprint asks for one (Algorithm 1, line 7), if that plane is also a plane of the
    /// coarser grid (the state is the struct's: [`Hits::next_primitive`] writes it back
    /// first). False when the coarser level cannot be prepared.
    #[inline(never)]
    fn switch_level(&mut self, axis: usize, tc: f32) -> bool {
        let want = self.pick(tc);
        if want <= self.li {
            return true;
        }
        let level = self.level.expect("a level while walking");
        let g = self.g;
        // The crossed plane, in voxels of the current level: a plane of level li + k too when
        // divisible by 2^k.
        let v = self.ddas[g].v;
        let step = self.ddas[g].step[axis];
        let b = (if step > 0 { v[axis] } else { v[axis] + 1 }) << (2 * g);
        let mut k = 0;
        while self.li + k < want && b % (1 << (k + 1)) == 0 {
            k += 1;
        }
        if k == 0 {
            return true;
        }
        // The voxel entered, at the current level (exact on the crossed axis).
        let s = level.voxel_size;
        let p = self.cone.origin + self.cone.dir * tc - level.grid.origin;
        let mut vox = (p / s)
            .as_ivec3()
            .clamp(IVec3::ZERO, IVec3::splat(level.grid.res as i32 - 1));
        vox[axis] = if step > 0 { b } else { b - 1 };
        self.li += k;
        let coarse = IVec3::new(vox.x >> k, vox.y >> k, vox.z >> k);
        let Some(next) = self.scene.level(self.li) else {
            return false;
        };
        let at = coarse >> (2 * next.top) as i32;
        // A coarser level's clip box holds the finer one's: the walk may now go further.
        if let Some((_, t1)) = self
            .scene
            .clip_interval(self.li, &self.cone, self.inv, tc, self.t_far)
        {
            self.t_end = self.t_end.max(t1);
        }
        self.enter_level(Some(at))
    }

    /// The coverage weight of voxel `idx` of `level` for this cone (with the walk's
    /// [`Weights`]), and the exact one where `exact` asks for it ([`Occlusion`] counts it),
    /// else the same.
    #[inline]
    fn weight(
        &self,
        level: &Level,
        li: usize,
        block: &Voxels,
        i: u32,
        exact: bool,
        vis: Option<&(Arc<Voxels>, u32)>,
    ) -> (f32, f32, f32) {
        // V̂(ω_o): the voxel's own, or at a visibility level its shading level's voxel's.
        let record = match vis {
            Some((b, j)) => &b.weight[*j as usize],
            None => &block.weight[i as usize],
        };
        let look = record.viewer_aiv(-self.cone.dir);
        if let ViewerAiv::Cell(_) = look {
            record.aiv.prefetch();
        }
        let (g, g_exact, area) = self.geometric_weight(level, li, block, i, exact);
        let vo = match look {
            ViewerAiv::Known(v) => v,
            ViewerAiv::Cell(cell) => record.keep_viewer_aiv(cell),
        };
        (vo * g, vo * g_exact, area)
    }

    /// The next primitive met (its voxel and ray parameter), with its geometric weight
    /// |A|·E|n·ω|/|B|_ω (Eq. 24's primitive coverage, without the V̂(ω_o) of the full weight
    /// and without occlusion), zero or not: the error budget ([`crate::eval::budget`])
    /// replaces the factors of the weight one at a time, and
    /// `tools/src/bin/cone_weights_probe.rs` sets them against the mesh.
    pub fn next_geometric(&mut self) -> Option<(VoxelHandle<'s>, f32, f32)> {
        let (level, li, block, i, t, c) = self.next_primitive()?;
        let g = crate::math::finite_or_zero(self.geometric_weight(level, li, &block, i, false).0);
        Some((
            VoxelHandle {
                data: level,
                block,
                i,
                level: li,
                vis: self.scene.visibility_voxel(li, c),
            },
            t,
            g,
        ))
    }

    /// [`Hits::weight`] without V̂(ω_o): with the walk's |B|_ω ([`Weights`]), and with the
    /// exact |B|_ω where `exact` asks for it under [`Weights::Bound`] (else the same value);
    /// and that exact |B|_ω where it was computed for a bound (else 0).
    #[inline]
    fn geometric_weight(
        &self,
        level: &Level,
        li: usize,
        block: &Voxels,
        i: u32,
        exact: bool,
    ) -> (f32, f32, f32) {
        let rec = &block.hit[i as usize];
        let w = &block.weight[i as usize];
        let d = self.cone.dir;
        let mut computed = 0.0;
        let (area_b, exact_b) = match (self.settings.primitive, rec.area_case) {
            (PrimitiveKind::TruncatedEllipsoid, Some(case)) => {
                let ellipsoid = std::f32::consts::PI * w.det * (rec.inv * d).length();
                let cube = box_projected_area(Vec3::splat(level.voxel_size + 2.0 * level.pad), d);
                let projected = || {
                    let exact = |w: Vec3| {
                        block
                            .primitive(level, i)
                            .map_or(0.0, |p| p.projected_area(w))
                    };
                    match &self.areas {
                        Some(cache) => cache.borrow_mut().area(li, block.first + i, exact),
                        None => exact(d),
                    }
                };
                match (case, self.weights) {
                    (AreaCase::EllipsoidInside, _) => (ellipsoid, ellipsoid),
                    (AreaCase::VoxelInside, _) => (cube, cube),
                    (AreaCase::Crossing, Weights::Bound) => {
                        let b = ellipsoid.min(cube);
                        if exact {
                            computed = projected();
                            (b, computed)
                        } else {
                            (b, b)
                        }
                    }
                    (AreaCase::Crossing, Weights::Exact) => {
                        let e = projected();
                        (e, e)
                    }
                }
            }
            (PrimitiveKind::TruncatedEllipsoid, None) => (0.0, 0.0),
            _ => {
                let cube = box_projected_area(Vec3::splat(level.voxel_size), d);
                (cube, cube)
            }
        };
        let a = rec.area * w.mean_cosine(d);
        let of = |b: f32| if b > 0.0 { a / b } else { 0.0 };
        (of(area_b), of(exact_b), computed)
    }
}

impl<'s> Iterator for Hits<'s> {
    type Item = Hit<'s>;

    fn next(&mut self) -> Option<Hit<'s>> {
        loop {
            let (level, li, block, i, t, c) = self.next_primitive()?;
            let occlude = self.settings.normalize;
            let vis = self.scene.visibility_voxel(li, c);
            let (w, exact, exact_area) = self.weight(level, li, &block, i, occlude, vis.as_ref());
            let mut weight = crate::math::finite_or_zero(w);
            if occlude && weight > 0.0 {
                weight *= self.occlusion.pass(crate::math::finite_or_zero(exact));
                if self.occlusion.closed() {
                    // Nothing behind can count: the walk ends here.
                    self.done = true;
                }
            }
            if weight > 0.0 {
                return Some(Hit {
                    voxel: VoxelHandle {
                        data: level,
                        block,
                        i,
                        level: li,
                        vis,
                    },
                    t,
                    weight,
                    exact_area,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Occlusion, OCCLUSION_ONSET};

    /// Weights pass unchanged until the onset, the rest is attenuated linearly, nothing passes
    /// once the cone is covered, and the sum of what passes stays near 1 however the cone is
    /// filled.
    #[test]
    fn occlusion_opens_and_closes() {
        let on = OCCLUSION_ONSET;
        assert!(on > 0.0 && on < 1.0);
        let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
        let mut o = Occlusion::default();
        assert_eq!(o.open(), 1.0);
        assert_eq!(o.attenuate(0.5 * on), 0.5 * on);
        assert!(close(o.attenuate(0.5 * on), 0.5 * on));
        assert!(!o.closed());
        // Covered up to the onset: still fully open.
        assert!(close(o.open(), 1.0), "{}", o.open());
        // Half of what is left after the onset: half open.
        let half = 0.5 * (1.0 - on);
        assert!(close(o.attenuate(half), half));
        assert!(close(o.open(), 0.5), "{}", o.open());
        // `pass` counts what it is given: a hit whose counted weight is larger.
        assert!(close(o.pass(2.0 * half), 0.5));
        assert!(o.closed() && o.open() == 0.0);
        assert_eq!(o.attenuate(0.7), 0.0);
        let mut big = Occlusion::default();
        assert_eq!(big.attenuate(1.3), 1.3);
        assert!(big.closed());
        // A long run of small weights covers the cone and no more.
        let mut many = Occlusion::default();
        let sum: f32 = (0..10_000).map(|_| many.attenuate(0.01)).sum();
        assert!(sum <= 1.0 + 1e-3 && sum > 0.99, "{sum}");
    }

    /// An area is computed once per voxel for one scene and direction, again for another
    /// direction or scene, and voxels that share a slot are told apart.
    #[test]
    fn area_cache_computes_each_area_once_per_direction() {
        use super::{AreaCache, AREA_CACHE_SLOTS};
        use glam::Vec3;
        let mut c = AreaCache::new();
        let calls = std::cell::Cell::new(0u32);
        let area = |c: &mut AreaCache, li: usize, idx: u32| {
            c.area(li, idx, |d: Vec3| {
                calls.set(calls.get() + 1);
                d.x + li as f32 + idx as f32 * 10.0
            })
        };
        let (a, b) = (Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.25, 0.0, 0.0));
        c.aim(1, a);
        // Three times as many voxels as slots: every value right, each computed when its slot
        // held another voxel, and twice in a row only once.
        let n = 3 * AREA_CACHE_SLOTS as u32;
        for idx in 0..n {
            assert_eq!(area(&mut c, 0, idx), 0.5 + idx as f32 * 10.0);
            assert_eq!(area(&mut c, 0, idx), 0.5 + idx as f32 * 10.0);
        }
        assert_eq!(calls.get(), n);
        // Another level's voxel of the same index is another voxel.
        assert_eq!(area(&mut c, 1, 7), 0.5 + 1.0 + 70.0);
        assert_eq!(calls.get(), n + 1);
        // The same scene and direction keep it; another direction or scene computes anew.
        c.aim(1, a);
        area(&mut c, 1, 7);
        assert_eq!(calls.get(), n + 1);
        c.aim(1, b);
        assert_eq!(area(&mut c, 1, 7), 0.25 + 1.0 + 70.0);
        c.aim(2, b);
        area(&mut c, 1, 7);
        assert_eq!(calls.get(), n + 3);
    }

    #[test]
    fn half_tan_matches_tan() {
        for i in 0..=2000 {
            let a = i as f32 * 1e-4 * std::f32::consts::PI;
            let (got, want) = (super::half_tan(a), (0.5 * a as f64).tan() as f32);
            assert!(
                (got - want).abs() <= 4e-7 * want.abs().max(1e-6),
                "{a}: {got} vs {want}"
            );
        }
    }
}
