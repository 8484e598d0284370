//! The traversal layer: a cone's walk through the aggregate, as an iterator of [`Hit`]s
//! (Algorithm 1, lines 6–12, 19).
//!
//! A DDA over the 4³ bricks of the current level skips empty bricks by one bit each; inside an
//! occupied brick a voxel DDA finds the voxels by the brick's 64-bit mask. The level is the
//! footprint's (line 7), and changes to a coarser one only where the ray crosses a brick plane
//! that is also a plane of the coarser grid, as in the paper ("we switch to a coarser LoD only
//! at the boundary of the coarser voxels"). The face through which the ray entered the first
//! occupied voxel gives the ABV (lines 9–10).

use glam::{IVec3, Vec3};

use super::level::{Brick, Level, BRICK};
use super::{Cone, LodScene, PrimitiveKind, TraceSettings, VoxelHandle};
use crate::spatial::dda::entry_axis;
use crate::spatial::ellipsoid::AreaCase;
use crate::spatial::face::entry_face;
use crate::spatial::{box_interval, box_projected_area, truncated_entry, Dda, Grid};

/// A primitive the cone met.
#[derive(Clone, Copy)]
pub struct Hit<'s> {
    /// The voxel: its ABSDF and AIV.
    pub voxel: VoxelHandle<'s>,
    /// Ray parameter where the centre ray enters the primitive.
    pub t: f32,
    /// The coverage weight V̂(ω_o)·|A|_ω/|B|_ω of Eq. 30: the voxel's share of the cone.
    pub weight: f32,
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

/// The voxel walk inside one occupied brick.
#[derive(Clone, Copy)]
struct InBrick {
    dda: Dda,
    brick: Brick,
    /// The brick's coordinates.
    c: IVec3,
    /// Where the ray leaves the brick.
    t_exit: f32,
}

/// The walk of one cone: an iterator over the primitives it meets, in order.
pub struct Hits<'s> {
    scene: &'s LodScene,
    cone: Cone,
    inv: Vec3,
    tan_half: f32,
    settings: TraceSettings,
    t_end: f32,
    li: usize,
    level: Option<&'s Level<'s>>,
    bricks: Dda,
    inner: Option<InBrick>,
    t: f32,
    entry_axis: usize,
    /// The ABV at the first occupied voxel, once met.
    vb: Option<f32>,
    primitives: u32,
    steps_left: u32,
    steps_max: u32,
    done: bool,
    weights: Weights,
}

/// The grid of a level's bricks (it may overhang the level's cube when res < 4).
#[inline]
fn brick_grid(g: &Grid, brick_res: i32) -> Grid {
    Grid {
        origin: g.origin,
        size: g.voxel_size() * (brick_res * BRICK) as f32,
        res: brick_res as u32,
    }
}

impl LodScene {
    /// The primitives `cone` meets, in order (see [`Hit`]); once exhausted,
    /// [`Hits::transmittance`] is the background's weight.
    pub fn hits(&self, cone: &Cone, settings: &TraceSettings) -> Hits<'_> {
        let inv = cone.dir.recip();
        let mut h = Hits {
            scene: self,
            cone: *cone,
            inv,
            tan_half: (0.5 * cone.aperture).tan(),
            settings: *settings,
            t_end: 0.0,
            li: 0,
            level: None,
            bricks: Dda::new(
                &Grid {
                    origin: Vec3::ZERO,
                    size: 1.0,
                    res: 1,
                },
                Vec3::ZERO,
                Vec3::X,
                Vec3::X,
                0.0,
                Some(IVec3::ZERO),
            ),
            inner: None,
            t: 0.0,
            entry_axis: 0,
            vb: None,
            primitives: 0,
            steps_left: 0,
            steps_max: 0,
            done: true,
            weights: Weights::Exact,
        };
        let Some(g0) = self.grids.first().copied() else {
            return h;
        };
        if !(cone.dir.is_finite() && cone.origin.is_finite() && cone.dir != Vec3::ZERO) {
            return h;
        }
        let (lo, hi) = g0.bounds();
        let (c0, c1) = box_interval(lo, hi, cone.origin, inv);
        let (tmin, tmax) = (c0.max(cone.tmin), c1.min(cone.tmax));
        if !(tmin <= tmax) {
            return h;
        }
        h.t = tmin;
        h.t_end = tmax;
        h.entry_axis = entry_axis(lo, hi, cone.origin, inv);
        h.li = h.pick(tmin);
        h.steps_left = 6 * g0.res + 64;
        h.steps_max = h.steps_left;
        h.done = !h.enter_level(None);
        h
    }
}

impl<'s> Hits<'s> {
    /// Weighs hits this way from now on.
    pub(crate) fn with_weights(mut self, w: Weights) -> Self {
        self.weights = w;
        self
    }

    /// exact weight / bound weight of a hit yielded under [`Weights::Bound`].
    #[inline]
    pub(crate) fn exact_factor(&self, hit: &Hit) -> f32 {
        let (level, idx) = (hit.voxel.data, hit.voxel.idx);
        if self.settings.primitive != PrimitiveKind::TruncatedEllipsoid
            || level.hit[idx as usize].area_case != Some(AreaCase::Crossing)
        {
            return 1.0;
        }
        let Some(p) = level.primitive(idx) else {
            return 0.0;
        };
        let d = self.cone.dir;
        let exact = p.projected_area(d);
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
            .unwrap_or_else(|| self.scene.level_for_tan(self.tan_half, t))
            .min(n - 1)
    }

    /// Starts walking level `self.li`'s bricks at `self.t`, in brick `at` if given. False when
    /// the level cannot be prepared.
    fn enter_level(&mut self, at: Option<IVec3>) -> bool {
        let Some(level) = self.scene.level(self.li) else {
            return false;
        };
        self.level = Some(level);
        let bg = brick_grid(&level.grid, level.brick_res);
        self.bricks = Dda::new(&bg, self.cone.origin, self.cone.dir, self.inv, self.t, at);
        self.inner = None;
        true
    }

    /// Primitives met so far.
    pub fn primitives(&self) -> u32 {
        self.primitives
    }

    /// Traversal steps taken so far (bricks and voxels visited), for profiling.
    pub fn steps(&self) -> u32 {
        self.steps_max - self.steps_left
    }

    /// The background's weight: the ABV of the face where the cone entered the aggregate if it
    /// met any primitive (P⁺, Eq. 30), 1 otherwise. Final once the iterator is exhausted.
    pub fn transmittance(&self) -> f32 {
        if self.primitives > 0 {
            self.vb.unwrap_or(1.0)
        } else {
            1.0
        }
    }

    /// The next primitive met (its level's data, level index, voxel index and entry
    /// parameter), without its weight.
    pub(crate) fn next_primitive(&mut self) -> Option<(&'s Level<'s>, usize, u32, f32)> {
        while !self.done {
            if self.steps_left == 0 {
                self.done = true;
                break;
            }
            self.steps_left -= 1;
            let level = self.level.expect("a level while walking");
            let li = self.li;
            if let Some(mut ib) = self.inner {
                // Inside an occupied brick: this voxel, then the next.
                let v = ib.dda.v;
                let t_exit = ib.dda.t_exit().min(ib.t_exit).min(self.t_end);
                let mut found = None;
                if let Some(idx) = Level::in_brick(&ib.brick, v) {
                    let rec = &level.hit[idx as usize];
                    if self.vb.is_none() {
                        let a = self.entry_axis;
                        let dir = entry_face(a, ib.dda.step[a]);
                        self.vb = Some(
                            level
                                .face(v.as_uvec3(), dir)
                                .map_or(1.0, |f| f.abv(self.cone.dir)),
                        );
                    }
                    let hit = match self.settings.primitive {
                        PrimitiveKind::TruncatedEllipsoid if rec.area_case.is_some() => {
                            truncated_entry(
                                rec.center,
                                rec.inv,
                                self.cone.origin,
                                self.cone.dir,
                                self.t - level.pad,
                                t_exit + level.pad,
                            )
                            .map(|t| t.max(self.t))
                        }
                        PrimitiveKind::TruncatedEllipsoid => None,
                        _ => Some(self.t),
                    };
                    if let Some(th) = hit {
                        self.primitives += 1;
                        found = Some((idx, th));
                    }
                }
                // Advance within the brick, or leave it.
                if t_exit >= ib.t_exit.min(self.t_end) {
                    self.inner = None;
                    self.t = ib.t_exit;
                    if ib.t_exit >= self.t_end {
                        self.done = true;
                    } else {
                        self.advance_brick();
                    }
                } else {
                    match ib.dda.advance() {
                        Some((axis, tc)) if (ib.dda.v >> 2) == ib.c => {
                            self.t = tc;
                            self.entry_axis = axis;
                            self.inner = Some(ib);
                        }
                        _ => {
                            self.inner = None;
                            self.t = ib.t_exit;
                            self.advance_brick();
                        }
                    }
                }
                if let Some((idx, th)) = found {
                    return Some((level, li, idx, th));
                }
                continue;
            }
            // Between bricks.
            let c = self.bricks.v;
            let t_exit = self.bricks.t_exit().min(self.t_end);
            if level.brick_occupied(c) {
                if let Some(brick) = level.brick(c) {
                    let s = level.grid.voxel_size();
                    let p = self.cone.origin + self.cone.dir * self.t;
                    let lo = c * BRICK;
                    let v = ((p - level.grid.origin) / s)
                        .floor()
                        .as_ivec3()
                        .clamp(lo, lo + IVec3::splat(BRICK - 1));
                    let dda = Dda::new(
                        &level.grid,
                        self.cone.origin,
                        self.cone.dir,
                        self.inv,
                        self.t,
                        Some(v),
                    );
                    self.inner = Some(InBrick {
                        dda,
                        brick,
                        c,
                        t_exit,
                    });
                    continue;
                }
            }
            if t_exit >= self.t_end {
                self.done = true;
                break;
            }
            self.advance_brick();
        }
        None
    }

    /// Moves to the next brick (and to a coarser level where the footprint asks for one and
    /// the crossed plane allows it).
    fn advance_brick(&mut self) {
        let Some((axis, tc)) = self.bricks.advance() else {
            self.done = true;
            return;
        };
        self.t = tc;
        self.entry_axis = axis;
        let want = self.pick(tc);
        if want <= self.li {
            return;
        }
        // The crossed plane, in voxels of the current level.
        let c = self.bricks.v;
        let b = if self.bricks.step[axis] > 0 {
            c[axis]
        } else {
            c[axis] + 1
        } * BRICK;
        let mut k = 0;
        while self.li + k < want && b % (1 << (k + 1)) == 0 {
            k += 1;
        }
        if k == 0 {
            return;
        }
        let level = self.level.expect("a level while walking");
        let s = level.grid.voxel_size();
        let p = self.cone.origin + self.cone.dir * tc;
        let lo = c * BRICK;
        let mut v = ((p - level.grid.origin) / s)
            .floor()
            .as_ivec3()
            .clamp(lo, lo + IVec3::splat(BRICK - 1));
        v[axis] = if self.bricks.step[axis] > 0 { b } else { b - 1 };
        self.li += k;
        let coarse = IVec3::new(v.x >> k, v.y >> k, v.z >> k);
        if !self.enter_level(Some(coarse >> 2)) {
            self.done = true;
        }
    }

    /// The coverage weight of voxel `idx` of `level` for this cone.
    #[inline]
    fn weight(&self, level: &Level, idx: u32) -> f32 {
        let rec = &level.hit[idx as usize];
        let w = &level.weight[idx as usize];
        let d = self.cone.dir;
        let area_b = match (self.settings.primitive, rec.area_case) {
            (PrimitiveKind::TruncatedEllipsoid, Some(case)) => {
                let ellipsoid = std::f32::consts::PI * w.det * (rec.inv * d).length();
                let cube = box_projected_area(Vec3::splat(level.voxel_size + 2.0 * level.pad), d);
                match (case, self.weights) {
                    (AreaCase::EllipsoidInside, _) => ellipsoid,
                    (AreaCase::VoxelInside, _) => cube,
                    (AreaCase::Crossing, Weights::Bound) => ellipsoid.min(cube),
                    (AreaCase::Crossing, Weights::Exact) => {
                        level.primitive(idx).map_or(0.0, |p| p.projected_area(d))
                    }
                }
            }
            (PrimitiveKind::TruncatedEllipsoid, None) => 0.0,
            _ => box_projected_area(Vec3::splat(level.voxel_size), d),
        };
        if !(area_b > 0.0) {
            return 0.0;
        }
        let vo = w.vref.aiv(-d);
        vo * rec.area * w.mean_cosine(d) / area_b
    }
}

impl<'s> Iterator for Hits<'s> {
    type Item = Hit<'s>;

    fn next(&mut self) -> Option<Hit<'s>> {
        loop {
            let (level, li, idx, t) = self.next_primitive()?;
            let weight = crate::math::finite_or_zero(self.weight(level, idx));
            if weight > 0.0 {
                return Some(Hit {
                    voxel: VoxelHandle {
                        data: level,
                        idx,
                        level: li,
                    },
                    t,
                    weight,
                });
            }
        }
    }
}
