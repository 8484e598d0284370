//! The LoD runtime: cone tracing through an `.agg` aggregate (paper §6.3, §7.3, Algorithm 1,
//! Eq. 30).
//!
//! [`LodScene::new`] prepares an opened [`Aggregate`] once (per voxel its ABSDF, primitive and
//! a zero-copy handle on its AIV tree; per level a hash from Morton key to voxel and from
//! (key, direction) to boundary face). After that, [`LodScene::trace`] is thread-safe and
//! allocates nothing: a host renderer calls it with a cone (origin, direction, aperture) and
//! the lights, and gets the radiance and the background's transmittance.
//!
//! Per cone, a 3D DDA walks the level whose voxel matches the cone's footprint (Algorithm 1,
//! line 7), switching to a coarser level only where the ray crosses a boundary of the coarser
//! grid. Every voxel whose truncated ellipsoid the centre ray meets adds (Eq. 30)
//!
//! ```text
//! L_o(ω_o) · V̂(ω_o) · |A|_ω / |B|_ω,     L_o(ω_o) = ∫ f̂(ω_i, ω_o) L(ω_i) V̂(ω_i) dω_i
//! ```
//!
//! with L_o estimated by `nee` light samples and `nee` ABSDF samples combined by MIS (splitting,
//! Algorithm 1 line 14), the AIV V̂ standing in for shadow rays, |A|_ω = coverage · area · E|n·ω|
//! from the voxel's normal distribution and |B|_ω the primitive's projected area. The
//! background is added through the ABV of the face where the ray entered the aggregate if the
//! ray met any primitive (P⁺), in full otherwise. The sum is order-independent.

pub mod primitive;
mod volume;

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use glam::{IVec3, Vec3};

use crate::absdf::Absdf;
use crate::bake::boundary_visibility::face_normal;
use crate::bake::voxelize::{morton3, Grid};
use crate::format::{fb, Aggregate, VoxelRef};
use crate::math::frame::Frame;
use crate::math::haar::{eval_tree, Node};
use crate::math::rng::Pcg32;
use crate::math::sampling::power_heuristic;
use crate::math::sggx::Sggx;
use crate::math::sphere_maps::{concentric_hemisphere_to_square, grid_cell};
use crate::render::lights::Lights;
use crate::tables::fit::m5_exact;
use crate::trace::Ray;
use primitive::{box_interval, box_projected_area, Primitive};

/// A hasher for Morton keys: one mixing step instead of SipHash in the traversal's inner loop.
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

/// Outgoing AIV below which a voxel's contribution is shaded only with probability
/// V̂(ω_o) / RR_VISIBILITY (and weighted up when it is).
const RR_VISIBILITY: f32 = 0.05;

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

/// Render-time options.
#[derive(Clone, Copy, Debug)]
pub struct TraceSettings {
    /// Light samples and ABSDF samples per primitive hit (MIS; Algorithm 1's m).
    pub nee: u32,
    /// Force this level (0 = finest) instead of choosing by footprint.
    pub level: Option<usize>,
    pub primitive: PrimitiveKind,
}

impl Default for TraceSettings {
    fn default() -> Self {
        TraceSettings {
            nee: 1,
            level: None,
            primitive: PrimitiveKind::TruncatedEllipsoid,
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
    /// The surfaces' radiance plus the background through `transmittance`; zero radiance if
    /// anything non-finite slipped through, so that no NaN or infinity leaves the runtime.
    fn compose(
        surfaces: Vec3,
        background: Vec3,
        transmittance: f32,
        primitives: u32,
        coverage: f32,
    ) -> ConeResult {
        let radiance = surfaces + background * transmittance;
        ConeResult {
            radiance: if radiance.is_finite() {
                radiance
            } else {
                Vec3::ZERO
            },
            transmittance,
            primitives,
            coverage,
        }
    }
}

/// A voxel ready for shading.
struct Voxel<'a> {
    absdf: Absdf<'static>,
    prim: Option<Primitive>,
    /// area · coverage.
    area: f32,
    /// (weight / mass, lobe) for E|n·ω| = Σ w_k σ_k(ω) / m5_k.
    lobes: [(f32, Sggx); 4],
    lobe_count: usize,
    /// 1 / exposure: the incident AIV counts exposed sides only (see `bake::visibility`).
    inv_exposure: f32,
    vref: VoxelRef<'a>,
}

/// A boundary face: its ABV tree, zero-copy.
#[derive(Clone, Copy)]
struct FaceRef<'a> {
    rec: &'a fb::Face,
    nodes: flatbuffers::Vector<'a, fb::HaarNode>,
}

struct Level<'a> {
    grid: Grid,
    voxels: Vec<Voxel<'a>>,
    by_key: FastMap<u32>,
    /// Key: Morton key · 8 + face direction.
    faces: FastMap<FaceRef<'a>>,
}

/// A 3D DDA (Amanatides–Woo) over one grid: the voxel the ray is in and the ray parameters at
/// which it crosses the next plane along each axis.
struct Dda {
    v: IVec3,
    step: IVec3,
    t_next: Vec3,
    delta: Vec3,
    res: i32,
}

impl Dda {
    /// Starts at parameter `t` (in voxel `v` if given, else the voxel holding the point).
    fn new(g: &Grid, origin: Vec3, dir: Vec3, inv: Vec3, t: f32, v: Option<IVec3>) -> Dda {
        let s = g.voxel_size();
        let res = g.res as i32;
        let step = IVec3::new(
            (dir.x > 0.0) as i32 - (dir.x < 0.0) as i32,
            (dir.y > 0.0) as i32 - (dir.y < 0.0) as i32,
            (dir.z > 0.0) as i32 - (dir.z < 0.0) as i32,
        );
        let v = v.unwrap_or_else(|| {
            ((origin + dir * t - g.origin) / s)
                .floor()
                .as_ivec3()
                .clamp(IVec3::ZERO, IVec3::splat(res - 1))
        });
        let next = |a: usize| -> f32 {
            if step[a] == 0 {
                return f32::INFINITY;
            }
            let b = g.origin[a] + (v[a] + (step[a] > 0) as i32) as f32 * s;
            (b - origin[a]) * inv[a]
        };
        Dda {
            v,
            step,
            t_next: Vec3::new(next(0), next(1), next(2)),
            delta: Vec3::select(
                step.cmpeq(IVec3::ZERO),
                Vec3::INFINITY,
                (Vec3::splat(s) * inv).abs(),
            ),
            res,
        }
    }

    /// Where the ray leaves the current voxel.
    #[inline]
    fn t_exit(&self) -> f32 {
        self.t_next.min_element()
    }

    /// Moves into the next voxel: the axis crossed and the parameter there, or None when the
    /// ray leaves the grid.
    #[inline]
    fn advance(&mut self) -> Option<(usize, f32)> {
        let n = self.t_next;
        let axis = if n.x <= n.y && n.x <= n.z {
            0
        } else if n.y <= n.z {
            1
        } else {
            2
        };
        let t = n[axis];
        self.v[axis] += self.step[axis];
        if self.v[axis] < 0 || self.v[axis] >= self.res {
            return None;
        }
        self.t_next[axis] += self.delta[axis];
        Some((axis, t))
    }
}

/// A prepared aggregate.
pub struct LodScene<'a> {
    levels: Vec<Level<'a>>,
    abv_res: u32,
    /// Finest voxel size.
    base: f32,
}

impl<'a> LodScene<'a> {
    /// Prepares every level of `agg` (in parallel).
    pub fn new(agg: &'a Aggregate) -> LodScene<'a> {
        use rayon::prelude::*;
        let tables = crate::tables::Tables::embedded();
        let abv_res = agg.index().settings().map_or(64, |s| s.abv_res());
        let levels: Vec<Level<'a>> = (0..agg.level_count())
            .map(|l| {
                let grid = agg.grid(l);
                let refs: Vec<VoxelRef<'a>> = agg.voxels(l).collect();
                let voxels: Vec<Voxel<'a>> = refs
                    .par_iter()
                    .map(|v| {
                        let app = v.appearance();
                        let e = v.ellipsoid();
                        let (lo, hi) = grid.voxel_bounds(v.coords());
                        let mut lobes = [(
                            0.0,
                            Sggx::from_frame_roughness(glam::Mat3::IDENTITY, glam::Vec2::ONE),
                        ); 4];
                        let lobe_count = app.lobes.len().min(4);
                        for (k, l) in app.lobes.iter().take(4).enumerate() {
                            let mass = m5_exact((l.alpha.x * l.alpha.y).sqrt()).max(1e-6);
                            lobes[k] = (
                                l.weight / mass,
                                Sggx::from_frame_roughness(l.frame, l.alpha),
                            );
                        }
                        Voxel {
                            absdf: Absdf::new(&app, tables),
                            prim: Primitive::new(e.center, e.axes, lo, hi),
                            area: v.rec.area() * v.rec.coverage(),
                            lobes,
                            lobe_count,
                            inv_exposure: 1.0 / v.exposure().clamp(1.0 / 16.0, 1.0),
                            vref: *v,
                        }
                    })
                    .collect();
                let by_key = refs
                    .iter()
                    .enumerate()
                    .map(|(i, v)| (v.key, i as u32))
                    .collect();
                let mut faces = FastMap::default();
                let lv = agg.index().levels().unwrap().get(l);
                for r in lv.face_blocks().into_iter().flatten() {
                    let block = agg.block(r);
                    let nodes = block.abv_nodes().unwrap();
                    for f in block.faces().unwrap() {
                        let key = morton3(glam::UVec3::new(f.x(), f.y(), f.z()));
                        faces.insert(key * 8 + f.dir() as u64, FaceRef { rec: f, nodes });
                    }
                }
                Level {
                    grid,
                    voxels,
                    by_key,
                    faces,
                }
            })
            .collect();
        let base = levels.first().map_or(1.0, |l| l.grid.voxel_size());
        LodScene {
            levels,
            abv_res,
            base,
        }
    }

    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// The level (0 = finest) whose voxel matches a cone of full aperture `aperture` at
    /// distance `t` (Algorithm 1, line 7: ⌊log2(tan(θ/2)·t / s)⌋, clamped).
    #[inline]
    pub fn level_for(&self, aperture: f32, t: f32) -> usize {
        self.level_for_tan((0.5 * aperture).tan(), t)
    }

    /// [`Self::level_for`] with tan(θ/2) precomputed.
    #[inline]
    fn level_for_tan(&self, tan_half: f32, t: f32) -> usize {
        let x = tan_half * t / self.base;
        if !(x >= 2.0) {
            return 0;
        }
        (x.log2().floor() as usize).min(self.levels.len().saturating_sub(1))
    }

    /// E|n·ω| of a voxel's surfaces, from its normal distribution.
    #[inline]
    fn mean_cosine(v: &Voxel, w: Vec3) -> f32 {
        let mut s = 0.0;
        for (k, s_k) in v.lobes[..v.lobe_count].iter() {
            s += k * s_k.sigma(w);
        }
        s.clamp(0.0, 1.0)
    }

    /// The AIV for light arriving from `wi`, corrected for the correlation of incident and
    /// outgoing visibility: min(1, V̂(ω_i)/η) (see `bake::visibility`).
    #[inline]
    fn incident_aiv(v: &Voxel, wi: Vec3) -> f32 {
        (v.vref.aiv(wi) * v.inv_exposure).min(1.0)
    }

    /// Reflected radiance of a voxel towards `wo` (Algorithm 1, lines 13–17).
    fn shade(&self, v: &Voxel, wo: Vec3, lights: &Lights, nee: u32, rng: &mut Pcg32) -> Vec3 {
        Self::shade_with(v, wo, lights, nee, rng, |w| Self::incident_aiv(v, w))
    }

    /// Reflected radiance of a voxel's ABSDF towards `wo` with `visibility(ω_i)` for the light:
    /// the sun, then `nee` environment samples and `nee` ABSDF samples combined by MIS.
    fn shade_with(
        v: &Voxel,
        wo: Vec3,
        lights: &Lights,
        nee: u32,
        rng: &mut Pcg32,
        mut visibility: impl FnMut(Vec3) -> f32,
    ) -> Vec3 {
        let mut l = Vec3::ZERO;
        if let Some(sun) = &lights.sun {
            let f = v.absdf.eval(sun.direction, wo);
            if f.max_element() > 0.0 {
                l += f * sun.irradiance * visibility(sun.direction);
            }
        }
        let env = &lights.environment;
        let m = nee.max(1);
        let mut acc = Vec3::ZERO;
        for _ in 0..m {
            if let Some(ls) = env.sample(rng.next_2d()) {
                if ls.pdf > 0.0 && ls.radiance.max_element() > 0.0 {
                    let (f, pdf_b) = v.absdf.eval_pdf(ls.wi, wo);
                    if f.max_element() > 0.0 {
                        acc += f
                            * ls.radiance
                            * (visibility(ls.wi) * power_heuristic(ls.pdf, pdf_b) / ls.pdf);
                    }
                }
            }
            let u_lobe = rng.next_f32();
            if let Some(bs) = v.absdf.sample(wo, u_lobe, rng.next_2d()) {
                let le = env.eval(bs.wi);
                if le.max_element() > 0.0 {
                    let pdf_l = env.pdf(bs.wi);
                    acc += bs.value
                        * le
                        * (visibility(bs.wi) * power_heuristic(bs.pdf, pdf_l) / bs.pdf);
                }
            }
        }
        l + acc / m as f32
    }

    /// The ABV of face (voxel key, dir) towards `d` (pointing into the aggregate).
    fn abv(&self, level: &Level, key: u64, dir: u8, d: Vec3) -> Option<f32> {
        let f = level.faces.get(&(key * 8 + dir as u64))?;
        let n = self.abv_res;
        let scaling = f.rec.abv_scaling();
        if f.rec.abv_count() == 0 {
            return Some(scaling / n as f32);
        }
        let local = Frame::from_z(-face_normal(dir)).to_local(d);
        if !(local.z > 0.0) {
            return Some(scaling / n as f32);
        }
        let cell = grid_cell(concentric_hemisphere_to_square(local), n);
        let start = f.rec.abv_start() as usize;
        let nodes = f.nodes;
        let v = eval_tree(
            n,
            scaling,
            f.rec.abv_count() as usize,
            |i| {
                let h = nodes.get(start + i);
                Node {
                    details: [h.h(), h.v(), h.d()],
                    children: h.children(),
                    subtree: h.subtree(),
                }
            },
            cell % n,
            cell / n,
        );
        Some(v.clamp(0.0, 1.0))
    }

    /// Traces one cone: centre ray `ray`, full aperture `aperture` (radians).
    pub fn trace(
        &self,
        ray: &Ray,
        aperture: f32,
        lights: &Lights,
        settings: &TraceSettings,
        rng: &mut Pcg32,
    ) -> ConeResult {
        let d = ray.dir;
        let background = lights.environment.eval(d);
        let miss = ConeResult {
            radiance: background,
            transmittance: 1.0,
            primitives: 0,
            coverage: 0.0,
        };
        let Some(first) = self.levels.first() else {
            return miss;
        };
        let g0 = first.grid;
        let inv = d.recip();
        let (c0, c1) = box_interval(g0.origin, g0.origin + Vec3::splat(g0.size), ray.origin, inv);
        let (tmin, tmax) = (c0.max(ray.tmin), c1.min(ray.tmax));
        if !(tmin <= tmax) {
            return miss;
        }
        let tan_half = (0.5 * aperture).tan();
        let pick = |t: f32| -> usize {
            settings
                .level
                .unwrap_or_else(|| self.level_for_tan(tan_half, t))
                .min(self.levels.len() - 1)
        };
        let mut li = pick(tmin);
        if settings.primitive == PrimitiveKind::Volume {
            return self.trace_volume(ray, li, lights, settings.nee, rng);
        }
        let mut dda = Dda::new(&self.levels[li].grid, ray.origin, d, inv, tmin, None);
        let mut t = tmin;
        // The axis through which the current voxel was entered (for boundary faces): at the
        // start, the axis of the cube face the ray entered by.
        let mut entry_axis = {
            let g = &g0;
            let (a, b) = (
                (g.origin - ray.origin) * inv,
                (g.origin + Vec3::splat(g.size) - ray.origin) * inv,
            );
            let near = a.min(b);
            if near.x >= near.y && near.x >= near.z {
                0
            } else if near.y >= near.z {
                1
            } else {
                2
            }
        };
        let mut result = Vec3::ZERO;
        let mut hits = 0u32;
        let mut coverage = 0.0f32;
        let mut vb: Option<f32> = None;
        let wo = -d;
        let max_steps = 3 * g0.res as usize + 8;
        for _ in 0..max_steps {
            let level = &self.levels[li];
            let t_exit = dda.t_exit().min(tmax);
            let key = morton3(dda.v.as_uvec3());
            if let Some(&idx) = level.by_key.get(&key) {
                let vox = &level.voxels[idx as usize];
                // The first occupied voxel: the ray entered the aggregate through its face.
                if vb.is_none() {
                    let dir = (2 * entry_axis + (dda.step[entry_axis] < 0) as usize) as u8;
                    vb = self.abv(level, key, dir, d).or(Some(1.0));
                }
                let (hit, area_b) = match settings.primitive {
                    PrimitiveKind::TruncatedEllipsoid => match &vox.prim {
                        Some(p) => (p.intersect(ray.origin, d, inv, t, t_exit).is_some(), 0.0),
                        None => (false, 0.0),
                    },
                    PrimitiveKind::Cube | PrimitiveKind::Volume => (
                        true,
                        box_projected_area(Vec3::splat(level.grid.voxel_size()), d),
                    ),
                };
                if hit {
                    hits += 1;
                    let vo = vox.vref.aiv(wo).clamp(0.0, 1.0);
                    // Voxels hidden from the viewer add little: Russian roulette below
                    // V̂(ω_o) = RR_VISIBILITY keeps the sum unbiased and skips most of the
                    // shading deep inside dense aggregates.
                    let keep = if vo >= RR_VISIBILITY {
                        1.0
                    } else if vo > 0.0 && rng.next_f32() * RR_VISIBILITY < vo {
                        vo / RR_VISIBILITY
                    } else {
                        0.0
                    };
                    let area_b = match (settings.primitive, &vox.prim) {
                        _ if keep == 0.0 => 0.0,
                        (PrimitiveKind::TruncatedEllipsoid, Some(p)) => p.projected_area(d),
                        _ => area_b,
                    };
                    if area_b > 0.0 {
                        let a_w = vox.area * Self::mean_cosine(vox, d);
                        let lo = self.shade(vox, wo, lights, settings.nee, rng);
                        let c = a_w / area_b;
                        let w = vo * c / keep;
                        let add = lo * w;
                        if add.is_finite() {
                            result += add;
                            coverage += w;
                        }
                    }
                }
            }
            if t_exit >= tmax {
                break;
            }
            let Some((axis, t_cross)) = dda.advance() else {
                break;
            };
            t = t_cross;
            entry_axis = axis;
            // A coarser level only where the crossed plane is also a plane of that level.
            let want = pick(t);
            if want > li {
                let v = dda.v;
                let b = if dda.step[axis] > 0 {
                    v[axis]
                } else {
                    v[axis] + 1
                };
                let mut k = 0;
                while li + k < want && b % (1 << (k + 1)) == 0 {
                    k += 1;
                }
                if k > 0 {
                    li += k;
                    let coarse = IVec3::new(v.x >> k, v.y >> k, v.z >> k);
                    dda = Dda::new(&self.levels[li].grid, ray.origin, d, inv, t, Some(coarse));
                }
            }
        }
        let vb = if hits > 0 { vb.unwrap_or(1.0) } else { 1.0 };
        ConeResult::compose(result, background, vb, hits, coverage)
    }

    /// The bounds of the finest level's cube, for framing views.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let g = self.levels.first()?.grid;
        Some((g.origin, g.origin + Vec3::splat(g.size)))
    }
}

/// Renders an image with the LoD runtime: `spp` cones per pixel, each of the pixel's aperture,
/// jittered over the pixel; deterministic for a seed.
pub fn render(
    scene: &LodScene,
    camera: &crate::render::Camera,
    lights: &Lights,
    spp: u32,
    seed: u64,
    settings: &TraceSettings,
    progress: bool,
) -> (crate::render::Image, f64) {
    use rayon::prelude::*;
    let start = std::time::Instant::now();
    let (w, h) = (camera.width, camera.height);
    let aperture = camera.pixel_angle();
    let bar = crate::render::reference::progress_bar(progress, h as u64, "LoD");
    let rows: Vec<Vec<Vec3>> = (0..h)
        .into_par_iter()
        .map(|y| {
            let row = (0..w)
                .map(|x| {
                    let mut rng = Pcg32::new(seed, (y as u64) * w as u64 + x as u64);
                    let mut sum = Vec3::ZERO;
                    for _ in 0..spp.max(1) {
                        let p = glam::Vec2::new(x as f32, y as f32) + rng.next_2d();
                        let ray = camera.ray(p);
                        sum += scene
                            .trace(&ray, aperture, lights, settings, &mut rng)
                            .radiance;
                    }
                    sum / spp.max(1) as f32
                })
                .collect();
            bar.inc(1);
            row
        })
        .collect();
    bar.finish_and_clear();
    let mut img = crate::render::Image::new(w, h);
    for (y, row) in rows.into_iter().enumerate() {
        img.pixels[y * w as usize..(y + 1) * w as usize].copy_from_slice(&row);
    }
    (img, start.elapsed().as_secs_f64())
}
