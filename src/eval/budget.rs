//! The error budget by oracle substitution (`aggtool eval --budget`): on one bake and one view,
//! the LoD image rendered again and again with one of its approximations at a time replaced by
//! its ground truth, computed at render time from the original mesh and the voxel's real
//! surfaces, so that each term's share of the LoD's error against the reference is measured
//! instead of guessed.
//!
//! Per voxel k met by a camera ray, Algorithm 1 adds g_k · ∫ F_k(ω_i, ω_o) L(ω_i) dω_i, where
//! the baked model has
//!
//! ```text
//! g_k = 1[ray meets B_k] · |A|_ω/|B|_ω                (primitive hit and coverage, Eq. 24)
//! F_k = f̂(ω_i, ω_o) · V̂(ω_o) · min(1, V̂(ω_i)/η)      (Eq. 6, 25, the AIV, the exposure η)
//! ```
//!
//! and the background is weighted by the ABV of the entry face (Eq. 26, 30). The oracles, each
//! from `samples` fresh area-uniform points x_j of the real surface in the voxel (weights w_j,
//! shading normals n_j, base BSDF f_j, as the bake draws them but from another sequence), and
//! rays traced through the original mesh:
//!
//! - **coverage**: g_k becomes the number of triangles the ray crosses inside voxel k (its
//!   expectation over the pixel is Σ_k |P_k⁺|/|P| · c_k exactly), found by tracing the ray
//!   through the mesh; the voxels are those crossed, not those whose primitive the ray meets;
//! - **AIV→viewer**: V̂(ω_o) = Σ w_j |n_j·ω_o| V(x_j, ω_o) / Σ w_j |n_j·ω_o| (the bake's
//!   projected-area weighting), traced from the x_j;
//! - **AIV→light**: the same for V̂(ω_i), towards each light and ABSDF sample (η kept);
//! - **ABV**: the background's weight becomes 1[the ray misses the mesh] for a ray in P⁺ (whose
//!   average over P⁺ is Eq. 26 exactly);
//! - **ABSDF**: f̂ becomes Eq. 3 without visibility integrated over the x_j
//!   ([`crate::absdf::ground_truth`]); sampling stays the factored ABSDF's (its density is only
//!   a MIS weight and a proposal, so the estimate stays unbiased);
//! - **split**: the visibility split of Eq. 6 and 25 (and the exposure correction) replaced by
//!   the joint J = Σ w_j f_j |n_j·ω_i||n_j·ω_o| V(x_j,ω_i)V(x_j,ω_o) / Σ w_j|n_j·ω_o|: F is
//!   multiplied by J / S, S the split product of the same traced quantities, with η off;
//! - **normalised** rows (the default, as the runtime renders; `--no-normalize` for the rows
//!   as baked): each ray's sum divided by the sum of its weights, g_k·V̂(ω_o) over the hits
//!   (V̂(ω_o) over the crossings with the coverage oracle) plus the background's, after the
//!   runtime's front-to-back occlusion ([`crate::runtime::Occlusion`]) where V̂(ω_o) is the
//!   baked one (the traced V̂ already holds the occlusion);
//! - **all** of them at once: F = J per crossing and the background 1\[miss\]: what remains
//!   against the reference is the LoD's own spatial averaging (a voxel's surfaces averaged over
//!   the voxel where the pixel sees part of it) and Monte Carlo noise: if it were large, the
//!   budget would have a hole.
//!
//! Every configuration draws its cones from the same pixel streams as the runtime and the
//! reference ([`crate::film::render_image`]); the "baked" row (no oracle) is the runtime's
//! estimator rewritten on the traversal layer, and the table shows the runtime's own figure
//! beside it as a check.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use std::time::Instant;

use anyhow::{Context, Result};
use glam::{UVec3, Vec2, Vec3};

use crate::math::sphere_maps::{concentric_hemisphere_to_square, concentric_square_to_hemisphere};
use serde::Serialize;

use crate::bake::sampling::{pieces_by_voxel, sample_voxel, PointSample};
use crate::bake::{bake_to_file, BakeSettings};
use crate::bsdf::{BaseBsdf, Bsdf};
use crate::film::Image;
use crate::format::Aggregate;
use crate::lights::Lights;
use crate::math::frame::Frame;
use crate::math::rng::Pcg32;
use crate::math::sampling::{power_heuristic, Sampler};
use crate::render::compare::compare;
use crate::render::View;
use crate::runtime::{Cone, LodScene, Occlusion, TraceSettings, VoxelHandle};
use crate::scene::Scene;
use crate::spatial::{morton3, Grid};
use crate::trace::{offset_origin, Accel, Ray};
use crate::util::Progress;

/// Rays of the sub-face ABV oracle ([`Oracles::abv_part`]) per camera ray.
pub const ABV_PART_RAYS: u32 = 16;

/// Most oracle samples per voxel (their visibilities live in fixed arrays on the stack).
pub const MAX_SAMPLES: usize = 64;

/// Which approximations are replaced by their ground truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Oracles {
    /// Primitive hit and coverage |A|_ω/|B|_ω (Eq. 24) → crossings of the real surfaces.
    pub coverage: bool,
    /// V̂(ω_o) (Eq. 25) → traced from the voxel's surface samples.
    pub aiv_view: bool,
    /// V̂(ω_i) (Eq. 25) → traced from the voxel's surface samples.
    pub aiv_light: bool,
    /// The ABV of the entry face (Eq. 26) → the ray's own visibility through the mesh.
    pub abv: bool,
    /// The factored ABSDF (Eq. 7–23) → Eq. 3 over the surface samples.
    pub absdf: bool,
    /// The visibility split (Eq. 6, 25) and the exposure correction → the joint visibility.
    pub split: bool,
    /// The ABV of the entry face → for n > 0, the share of the P⁺ rays from the 1/n × 1/n part
    /// of the entry face that holds the ray's entry point, in the ray's own direction, that
    /// escape the mesh ([`ABV_PART_RAYS`] rays; n = 1: the face's average of Eq. 26 without its
    /// direction cells). Against the exact ABV it measures what a face's spatial average costs
    /// and what sub-face maps would buy. Ignored under `abv`.
    pub abv_part: u8,
    /// With `abv_part`: the oracle's rays take directions uniform over the ray's cell of a
    /// `abv_cell × abv_cell` concentric map of the face's inward hemisphere (the baked map's
    /// cells) instead of the ray's own: what the map's direction cells cost. 0: off.
    pub abv_cell: u16,
    /// With `abv_part`: only points of the face from which the ray, followed backwards, meets
    /// no occupied voxel of the level (the points where a cone can enter the aggregate in that
    /// direction, as the runtime's queries do).
    pub abv_reachable: bool,
    /// Not an oracle but a candidate fix: each cone's surfaces and background divided by the
    /// sum of their weights Σ V̂(ω_o)|A|_ω/|B|_ω + V̂_b, which is 1 for a consistent aggregate.
    pub normalize: bool,
}

impl Oracles {
    /// Every oracle.
    pub const ALL: Oracles = Oracles {
        coverage: true,
        aiv_view: true,
        aiv_light: true,
        abv: true,
        absdf: true,
        split: true,
        abv_part: 0,
        abv_cell: 0,
        abv_reachable: false,
        normalize: false,
    };

    /// The budget's rows: the baked model, each oracle alone, all of them.
    pub fn rows() -> Vec<(&'static str, Oracles)> {
        let none = Oracles::default();
        vec![
            ("baked", none),
            (
                "coverage + hit (Eq. 24)",
                Oracles {
                    coverage: true,
                    ..none
                },
            ),
            (
                "AIV to viewer (Eq. 25)",
                Oracles {
                    aiv_view: true,
                    ..none
                },
            ),
            (
                "AIV to lights (Eq. 25)",
                Oracles {
                    aiv_light: true,
                    ..none
                },
            ),
            ("ABV (Eq. 26)", Oracles { abv: true, ..none }),
            (
                "ABSDF (Eq. 3 vs 7-23)",
                Oracles {
                    absdf: true,
                    ..none
                },
            ),
            (
                "visibility split (Eq. 6, 25, η)",
                Oracles {
                    split: true,
                    ..none
                },
            ),
            ("all", Oracles::ALL),
            (
                "baked, normalised (candidate fix)",
                Oracles {
                    normalize: true,
                    ..none
                },
            ),
        ]
    }

    /// Every oracle but one, for each (the leave-one-out rows: the terms interact, so a term's
    /// share is also measured as the bias it brings back when it alone is baked).
    pub fn leave_one_out() -> Vec<(String, Oracles)> {
        Oracles::rows()
            .into_iter()
            .filter(|(n, o)| *n != "baked" && *o != Oracles::ALL && !o.normalize)
            .map(|(n, o)| {
                let name = format!("all but {}", n.split(" (").next().unwrap_or(n));
                let a = Oracles::ALL;
                (
                    name,
                    Oracles {
                        coverage: a.coverage && !o.coverage,
                        aiv_view: a.aiv_view && !o.aiv_view,
                        aiv_light: a.aiv_light && !o.aiv_light,
                        abv: a.abv && !o.abv,
                        absdf: a.absdf && !o.absdf,
                        split: a.split && !o.split,
                        abv_part: 0,
                        abv_cell: 0,
                        abv_reachable: false,
                        normalize: false,
                    },
                )
            })
            .collect()
    }

    /// The ABV rows of `--abv-parts`: the baked model, the exact ABV, every oracle and every
    /// oracle but the ABV, then for each n of `parts` the ABV over 1/n of the face
    /// ([`Oracles::abv_part`]) alone and with every other oracle.
    pub fn abv_part_rows(parts: &[u8], cells: &[u16]) -> Vec<(String, Oracles)> {
        let none = Oracles::default();
        let all_but_abv = Oracles {
            abv: false,
            ..Oracles::ALL
        };
        let mut rows = vec![
            ("baked".to_string(), none),
            ("ABV (Eq. 26)".to_string(), Oracles { abv: true, ..none }),
            ("all".to_string(), Oracles::ALL),
            ("all but ABV".to_string(), all_but_abv),
        ];
        for &c in cells.iter().filter(|&&c| c > 0) {
            rows.push((
                format!("ABV over the face, directions over the {c}² cell"),
                Oracles {
                    abv_part: 1,
                    abv_cell: c,
                    ..none
                },
            ));
        }
        rows.push((
            "ABV over the face's reachable points".to_string(),
            Oracles {
                abv_part: 1,
                abv_reachable: true,
                ..none
            },
        ));
        for &n in parts.iter().filter(|&&n| n > 0) {
            let part = if n == 1 {
                "the face".to_string()
            } else {
                format!("1/{n} × 1/{n} of the face")
            };
            rows.push((
                format!("ABV over {part}"),
                Oracles {
                    abv_part: n,
                    ..none
                },
            ));
            rows.push((
                format!("all, ABV over {part}"),
                Oracles {
                    abv_part: n,
                    ..all_but_abv
                },
            ));
        }
        rows
    }

    fn traces_view(&self) -> bool {
        self.aiv_view || self.split
    }

    fn traces_light(&self) -> bool {
        self.aiv_light || self.split
    }
}

/// One oracle sample: a point of the voxel's real surface.
struct TruthSample {
    position: Vec3,
    geometric_normal: Vec3,
    normal: Vec3,
    bsdf: BaseBsdf,
    weight: f32,
}

/// The real surfaces of one level's voxels, and the mesh to trace them against.
pub struct Truth<'a> {
    accel: &'a Accel<'a>,
    grid: Grid,
    level: usize,
    samples: HashMap<u64, Vec<TruthSample>>,
}

impl<'a> Truth<'a> {
    /// Samples `n` (at most [`MAX_SAMPLES`]) points of the real surface in every voxel of
    /// `grid` (level `level` of the aggregate), from a sequence other than the bake's.
    pub fn new(accel: &'a Accel<'a>, grid: Grid, level: usize, n: u32) -> Truth<'a> {
        use rayon::prelude::*;
        let scene = accel.scene();
        let n = n.clamp(1, MAX_SAMPLES as u32);
        let pieces: Vec<_> = pieces_by_voxel(scene, &grid).into_iter().collect();
        let samples = pieces
            .par_iter()
            .map(|(key, p)| {
                let seed = crate::bake::level::voxel_seed(*key) ^ 0x5bd1_e995;
                let s: Vec<TruthSample> = sample_voxel(scene, p, n, seed)
                    .into_iter()
                    .map(|s: PointSample| TruthSample {
                        position: s.position,
                        geometric_normal: s.geometric_normal,
                        normal: s.surface.normal.normalize_or(s.geometric_normal),
                        bsdf: BaseBsdf::new(s.surface.params),
                        weight: s.surface.weight,
                    })
                    .collect();
                (*key, s)
            })
            .collect();
        Truth {
            accel,
            grid,
            level,
            samples,
        }
    }

    /// The key of the voxel holding point `p`.
    fn key_of(&self, p: Vec3) -> u64 {
        let v = ((p - self.grid.origin) / self.grid.voxel_size()).floor();
        let m = (self.grid.res - 1) as f32;
        morton3(UVec3::new(
            v.x.clamp(0.0, m) as u32,
            v.y.clamp(0.0, m) as u32,
            v.z.clamp(0.0, m) as u32,
        ))
    }

    /// V(x_j, ω) for every sample, into `out`; returns how many.
    fn visibility(&self, s: &[TruthSample], w: Vec3, out: &mut [f32; MAX_SAMPLES]) {
        for (o, x) in out.iter_mut().zip(s) {
            let r = Ray::new(offset_origin(x.position, x.geometric_normal, w), w);
            *o = if self.accel.occluded(&r) { 0.0 } else { 1.0 };
        }
    }
}

impl Truth<'_> {
    /// The traced V̂(ω) of voxel `key` (the bake's projected-area weighting), `None` for a voxel
    /// without samples.
    pub fn traced(&self, key: u64, w: Vec3) -> Option<f32> {
        let s = self.samples.get(&key).filter(|s| !s.is_empty())?;
        let mut v = [0.0f32; MAX_SAMPLES];
        self.visibility(s, w, &mut v);
        Some(weighted_visibility(s, w, &v))
    }
}

/// Σ w |n·ω| v / Σ w |n·ω| over the samples (the bake's projected-area weighting); 1 without
/// projected area.
fn weighted_visibility(s: &[TruthSample], w: Vec3, v: &[f32; MAX_SAMPLES]) -> f32 {
    let (mut num, mut den) = (0.0f32, 0.0f32);
    for (x, v) in s.iter().zip(v) {
        let a = x.weight * x.normal.dot(w).abs();
        num += a * v;
        den += a;
    }
    if den > 0.0 {
        num / den
    } else {
        1.0
    }
}

/// Eq. 3 over the samples without visibility (f̂), and with the joint visibility
/// V(x_j,ω_i)V(x_j,ω_o) (J); `vi`/`vo` may be `None` (visibility 1).
fn absdf_truth(
    s: &[TruthSample],
    wi: Vec3,
    wo: Vec3,
    vi: Option<&[f32; MAX_SAMPLES]>,
    vo: Option<&[f32; MAX_SAMPLES]>,
) -> (Vec3, Vec3) {
    let (mut f, mut j, mut den) = (Vec3::ZERO, Vec3::ZERO, 0.0f32);
    for (k, x) in s.iter().enumerate() {
        let co = x.normal.dot(wo);
        den += x.weight * co.abs();
        let ci = x.normal.dot(wi);
        if ci * co <= 0.0 {
            continue;
        }
        let n = if co < 0.0 { -x.normal } else { x.normal };
        let frame = Frame::from_z(n);
        let v = x.bsdf.eval(frame.to_local(wi), frame.to_local(wo)) * (x.weight * (ci * co).abs());
        f += v;
        let vis = vi.map_or(1.0, |a| a[k]) * vo.map_or(1.0, |a| a[k]);
        j += v * vis;
    }
    if den > 0.0 {
        (
            crate::math::finite_vec_or_zero(f / den),
            crate::math::finite_vec_or_zero(j / den),
        )
    } else {
        (Vec3::ZERO, Vec3::ZERO)
    }
}

/// One voxel met by a ray, ready to shade: the integrand F(ω_i) of the module notes.
struct Shaded<'t, 's> {
    voxel: VoxelHandle<'s>,
    samples: &'t [TruthSample],
    truth: &'t Truth<'t>,
    oracles: Oracles,
    wo: Vec3,
    vo: [f32; MAX_SAMPLES],
    /// V̂(ω_o): baked or traced.
    view: f32,
    /// The traced V̂(ω_o) (for the split's S).
    view_traced: f32,
}

impl<'t, 's> Shaded<'t, 's> {
    fn new(
        voxel: VoxelHandle<'s>,
        truth: &'t Truth<'t>,
        oracles: Oracles,
        wo: Vec3,
    ) -> Shaded<'t, 's> {
        let samples: &[TruthSample] = truth
            .samples
            .get(&voxel.key())
            .map_or(&[], |v| v.as_slice());
        let mut vo = [1.0f32; MAX_SAMPLES];
        let mut view_traced = 1.0;
        if oracles.traces_view() && !samples.is_empty() {
            truth.visibility(samples, wo, &mut vo);
            view_traced = weighted_visibility(samples, wo, &vo);
        }
        let view = if oracles.aiv_view && !samples.is_empty() {
            view_traced
        } else {
            voxel.aiv(wo)
        };
        Shaded {
            voxel,
            samples,
            truth,
            oracles,
            wo,
            vo,
            view,
            view_traced,
        }
    }

    /// F(ω_i): the ABSDF times the visibilities, per the oracles.
    fn integrand(&self, wi: Vec3) -> Vec3 {
        let o = &self.oracles;
        let s = self.samples;
        let have = !s.is_empty();
        let mut vi = [1.0f32; MAX_SAMPLES];
        let mut light_traced = 1.0;
        if o.traces_light() && have {
            self.truth.visibility(s, wi, &mut vi);
            light_traced = weighted_visibility(s, wi, &vi);
        }
        let need_truth = (o.absdf || o.split) && have;
        let (f_true, joint) = if need_truth {
            absdf_truth(s, wi, self.wo, Some(&vi), Some(&self.vo))
        } else {
            (Vec3::ZERO, Vec3::ZERO)
        };
        let f = if o.absdf && have {
            f_true
        } else {
            self.voxel.eval(wi, self.wo)
        };
        let light = if o.aiv_light && have {
            light_traced
        } else {
            self.voxel.aiv(wi)
        };
        if o.split && have {
            // J / S per channel, S the split product of the same traced quantities.
            let split = f_true * (light_traced * self.view_traced);
            let r = Vec3::select(
                split.cmpgt(Vec3::ZERO),
                joint / split.max(Vec3::splat(f32::MIN_POSITIVE)),
                Vec3::ZERO,
            );
            f * (self.view * light) * r
        } else {
            f * (self.view * (light / self.voxel.exposure()).min(1.0))
        }
    }

    /// ∫ F(ω_i) L(ω_i) dω_i: the sun, one environment sample and one ABSDF sample (from the
    /// factored ABSDF) combined by MIS, as the runtime's shading with `nee` = 1. F carries the
    /// factor V̂(ω_o): where it is zero nothing is drawn (as the runtime skips such hits).
    fn radiance<S: Sampler>(&self, lights: &Lights, sampler: &mut S) -> Vec3 {
        let mut l = Vec3::ZERO;
        if !(self.view > 0.0) {
            return l;
        }
        if let Some(sun) = &lights.sun {
            l += self.integrand(sun.direction) * sun.irradiance;
        }
        let env = &lights.environment;
        if let Some(ls) = env.sample(sampler.next_2d()) {
            if ls.pdf > 0.0 && ls.radiance.max_element() > 0.0 {
                let pdf_b = self.voxel.pdf(ls.wi, self.wo);
                l +=
                    self.integrand(ls.wi) * ls.radiance * (power_heuristic(ls.pdf, pdf_b) / ls.pdf);
            }
        }
        let u_lobe = sampler.next_1d();
        if let Some(bs) = self.voxel.sample(self.wo, u_lobe, sampler.next_2d()) {
            let le = env.eval(bs.wi);
            if le.max_element() > 0.0 && bs.pdf > 0.0 {
                let pdf_l = env.pdf(bs.wi);
                l += self.integrand(bs.wi) * le * (power_heuristic(bs.pdf, pdf_l) / bs.pdf);
            }
        }
        l
    }
}

/// Radiance along one camera cone with these oracles (the module notes).
pub fn radiance(
    lod: &LodScene,
    truth: &Truth,
    oracles: Oracles,
    cone: &Cone,
    lights: &Lights,
    rng: &mut Pcg32,
) -> Vec3 {
    // The walk's own weights and ABV as baked. Normalised rows apply the runtime's occlusion
    // here, to whichever weights the row uses, where V̂(ω_o) is the baked one: the occlusion
    // stands in for the baked V̂'s floor behind solids, which the traced V̂ does not have (it
    // already holds the occlusion, and attenuating it again would count it twice).
    let settings = TraceSettings {
        level: Some(truth.level),
        normalize: false,
        ..Default::default()
    };
    let occlude = oracles.normalize && !oracles.aiv_view;
    let mut occlusion = Occlusion::default();
    let mut attenuate = |w: f32| {
        if occlude {
            occlusion.attenuate(w)
        } else {
            w
        }
    };
    let wo = -cone.dir;
    let background = lights.environment.eval(cone.dir);
    let mut sum = Vec3::ZERO;
    // The mesh crossings along the ray (for the coverage and ABV oracles).
    let mut crossings = 0u32;
    let mut wsum = 0.0f32;
    if oracles.coverage || oracles.abv {
        let eps = 1e-4 * truth.grid.voxel_size();
        let mut ray = Ray::new(cone.origin, cone.dir);
        for _ in 0..4096 {
            let Some(h) = truth.accel.intersect(&ray) else {
                break;
            };
            crossings += 1;
            if oracles.coverage {
                let p = truth.accel.surface(&ray, &h).p;
                if let Some(v) = lod.voxel(truth.level, truth.key_of(p)) {
                    let s = Shaded::new(v, truth, oracles, wo);
                    let w = attenuate(s.view);
                    if w > 0.0 {
                        wsum += w;
                        sum += s.radiance(lights, rng) * (w / s.view);
                    }
                }
            }
            ray.tmin = h.t + eps;
            if !oracles.coverage {
                break;
            }
        }
    }
    let mut hits = lod.hits(cone, &settings);
    if !oracles.coverage {
        while let Some((voxel, _t, g)) = hits.next_geometric() {
            if g > 0.0 {
                let s = Shaded::new(voxel, truth, oracles, wo);
                let w = attenuate(g * s.view);
                if w > 0.0 {
                    wsum += w;
                    sum += s.radiance(lights, rng) * (w / s.view);
                }
            }
        }
    } else {
        for _ in &mut hits {}
    }
    let part = match hits.entry() {
        Some(entry) if oracles.abv_part > 0 && !oracles.abv && hits.primitives() > 0 => {
            abv_over_part(lod, truth, entry, cone, oracles, rng)
        }
        _ => None,
    };
    let tb = match (oracles.abv, oracles.coverage) {
        (false, _) => part.unwrap_or_else(|| hits.transmittance()),
        (true, true) => (crossings == 0) as u32 as f32,
        (true, false) => {
            if hits.primitives() > 0 {
                (crossings == 0) as u32 as f32
            } else {
                1.0
            }
        }
    };
    let tb = if occlude { tb * occlusion.open() } else { tb };
    if oracles.normalize && wsum + tb > 0.0 {
        return (sum + background * tb) / (wsum + tb);
    }
    sum + background * tb
}

/// The sub-face ABV oracle ([`Oracles::abv_part`]): of [`ABV_PART_RAYS`] rays along the
/// cone's direction from uniform points of the 1/n × 1/n part of `entry`'s face holding the
/// cone's entry point, the share of those meeting a primitive of the level (P⁺) that miss the
/// mesh; `None` when none meets a primitive. `entry` is the walk's ([`crate::runtime::Hits::entry`]);
/// `tools/src/bin/cone_weights_probe.rs` calls it too.
pub fn abv_over_part(
    lod: &LodScene,
    truth: &Truth,
    (level, voxel, face): (usize, UVec3, u8),
    cone: &Cone,
    oracles: Oracles,
    rng: &mut Pcg32,
) -> Option<f32> {
    let n = oracles.abv_part.max(1);
    let grid = lod.grid(level);
    let (lo, hi) = grid.voxel_bounds(voxel);
    let (axis, d) = ((face / 2) as usize % 3, cone.dir);
    if d[axis].abs() < 1e-12 {
        return None;
    }
    let plane = if face % 2 == 0 { lo[axis] } else { hi[axis] };
    let p = cone.origin + d * ((plane - cone.origin[axis]) / d[axis]);
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let cell = (hi[u] - lo[u]) / n as f32;
    let index = |a: usize| ((p[a] - lo[a]) / cell).floor().clamp(0.0, (n - 1) as f32);
    let (iu, iv) = (index(u), index(v));
    let back = 1e-3 * cell;
    let settings = TraceSettings {
        level: Some(level),
        normalize: false,
        ..Default::default()
    };
    let inward = Frame::from_z(-crate::spatial::face_normal(face));
    let res = oracles.abv_cell as f32;
    let dir_cell = (oracles.abv_cell > 0).then(|| {
        let sq = concentric_hemisphere_to_square(inward.to_local(d));
        (sq * res).floor().clamp(Vec2::ZERO, Vec2::splat(res - 1.0))
    });
    let (mut met, mut escaped) = (0u32, 0u32);
    let mut tries = 0;
    let mut rays = 0;
    while rays < ABV_PART_RAYS && tries < 8 * ABV_PART_RAYS {
        tries += 1;
        let d = match dir_cell {
            Some(c) => inward
                .to_world(concentric_square_to_hemisphere((c + rng.next_2d()) / res))
                .normalize(),
            None => d,
        };
        let mut q = Vec3::ZERO;
        q[axis] = plane;
        q[u] = lo[u] + (iu + rng.next_f32()) * cell;
        q[v] = lo[v] + (iv + rng.next_f32()) * cell;
        let o = q - cone.dir * back;
        if oracles.abv_reachable {
            let mut out = lod.hits(&Cone::new(o, -d, 0.0), &settings);
            for _ in &mut out {}
            if out.entry().is_some() {
                continue;
            }
        }
        rays += 1;
        let mut walk = lod.hits(&Cone::new(o, d, 0.0), &settings);
        for _ in &mut walk {}
        if walk.primitives() == 0 {
            continue;
        }
        met += 1;
        escaped += !truth.accel.occluded(&Ray::new(o, d)) as u32;
    }
    (met > 0).then(|| escaped as f32 / met as f32)
}

/// Settings of the budget study.
#[derive(Clone, Debug)]
pub struct BudgetSettings {
    /// The LoD resolution: the level of that resolution is used, and the image is res² pixels
    /// unless `image` says otherwise.
    pub res: u32,
    /// The image's side in pixels (`aggtool eval --budget --image`); `None`: `res`.
    pub image: Option<u32>,
    /// Samples per pixel of every row.
    pub spp: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// Oracle surface samples per voxel (at most [`MAX_SAMPLES`]).
    pub samples: u32,
    /// Bake settings (`max_res` is replaced by `res`: the budget studies a bake's finest
    /// level, as the quality study does, not a coarse level of a finer bake, which has more
    /// samples per voxel).
    pub bake: BakeSettings,
    /// Every row normalised as the runtime renders by default ([`TraceSettings::normalize`]:
    /// each cone's surfaces and background divided by the sum of their weights), so that a
    /// term's share is that of the image a user gets; `false` (`--no-normalize`): the rows
    /// as baked, with the normalisation as a candidate-fix row of its own. With the coverage
    /// oracle the weights summed are the crossings' V̂(ω_o).
    pub normalize: bool,
    /// Instead of the budget's rows, the ABV rows of [`Oracles::abv_part_rows`] for these
    /// parts of a face (`aggtool eval --budget --abv-parts 1,2,4`); empty: the budget.
    pub abv_parts: Vec<u8>,
    /// With `abv_parts`, rows of [`Oracles::abv_cell`] for these map resolutions.
    pub abv_cells: Vec<u16>,
}

impl Default for BudgetSettings {
    fn default() -> Self {
        BudgetSettings {
            res: 64,
            image: None,
            spp: 64,
            reference_spp: 1024,
            samples: 32,
            bake: BakeSettings::default(),
            normalize: true,
            abv_parts: Vec::new(),
            abv_cells: Vec::new(),
        }
    }
}

/// One row of a scene's budget.
#[derive(Clone, Debug, Serialize)]
pub struct BudgetRow {
    /// The approximation this row replaces by its ground truth (or "baked", "all").
    pub term: String,
    /// Which approximations the row replaces by oracles.
    pub oracles: Oracles,
    /// RMSE against the reference of the image at 2 × spp (two renders of `spp`, seeds 1, 2).
    pub rmse: f64,
    /// The bias: √max(0, MSE − σ²), σ² the image's own noise variance, estimated from the
    /// two renders (MSE between them / 4) and removed, so that noisier estimators (crossing
    /// counts, traced visibility) are not mistaken for worse ones.
    pub bias: f64,
    /// The bias over the reference's mean radiance.
    pub rel_bias: f64,
    /// (bias of the baked row − this bias) / (bias of the baked row − bias of "all"): the
    /// share of the gap this row closes (a leave-one-out row: 100% minus the share its term
    /// reopens).
    pub gap_closed: f64,
    /// Mean radiance over the reference's (1 = no brightness bias).
    pub mean_ratio: f64,
    /// Wall-clock seconds of the row's renders.
    pub seconds: f64,
}

/// A scene's budget.
#[derive(Clone, Debug, Serialize)]
pub struct BudgetResult {
    /// The scene's name.
    pub scene: String,
    /// The LoD resolution.
    pub res: u32,
    /// The image's side in pixels.
    pub image: u32,
    /// Samples per pixel of every row.
    pub spp: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// Oracle surface samples per voxel.
    pub samples: u32,
    /// Whether the rows are normalised ([`BudgetSettings::normalize`]).
    pub normalized: bool,
    /// The runtime's own render at `spp` (the "baked" row must agree with it).
    pub runtime_rmse: f64,
    /// The runtime's default render (reservoir shading) at `spp`: [as baked, normalised].
    pub runtime_default_rmse: [f64; 2],
    /// The reference renderer at `spp`: the noise floor.
    pub reference_at_spp_rmse: f64,
    /// One row per term, baked first.
    pub rows: Vec<BudgetRow>,
    /// The picture of the rows' images and differences.
    pub picture: PathBuf,
}

fn mean(img: &Image) -> f64 {
    let n = img.pixels.len().max(1) as f64;
    img.pixels
        .iter()
        .map(|p| (p.x + p.y + p.z) as f64 / 3.0)
        .sum::<f64>()
        / n
}

/// Renders the reference and every row of [`Oracles::rows`] on the bake at `agg_path` (baked
/// there first when missing), writes a picture into `dir`, and returns the figures.
pub fn budget_scene(
    name: &str,
    scene: &Scene,
    agg_path: &Path,
    settings: &BudgetSettings,
    dir: &Path,
    progress: Progress,
) -> Result<BudgetResult> {
    std::fs::create_dir_all(dir)?;
    if !agg_path.exists() {
        let bake = BakeSettings {
            max_res: settings.res,
            ..settings.bake.clone()
        };
        bake_to_file(scene, name, &bake, agg_path, progress)
            .with_context(|| format!("baking {name}"))?;
    }
    let lod = LodScene::new(Aggregate::open(agg_path)?);
    let Some(level) = (0..lod.level_count()).find(|&l| lod.grid(l).res == settings.res) else {
        anyhow::bail!("{}: no {}³ level", agg_path.display(), settings.res);
    };
    let accel = Accel::build(scene);
    let image = settings.image.unwrap_or(settings.res);
    let view: View = super::study_view(scene, image, settings.spp);
    let lights = view.lights()?;
    let camera = view.camera();
    let (truth_img, _) = super::reference_render(&accel, &view, settings.reference_spp, 7)?;
    let (ref_spp, _) = super::reference_render(&accel, &view, settings.spp, 1)?;
    let (runtime_img, _) = super::lod_render(
        &lod,
        &view,
        settings.spp,
        1,
        &TraceSettings {
            level: Some(level),
            shading: crate::runtime::Shading::Every,
            normalize: settings.normalize,
            ..Default::default()
        },
    )?;
    // The runtime as a renderer runs it (reservoir shading), without and with normalising.
    let mut runtime_default = [0.0; 2];
    for (r, normalize) in runtime_default.iter_mut().zip([false, true]) {
        let (img, _) = super::lod_render(
            &lod,
            &view,
            settings.spp,
            1,
            &TraceSettings {
                level: Some(level),
                normalize,
                ..Default::default()
            },
        )?;
        *r = compare(&img, &truth_img).expect("same size").rmse;
    }
    let cmp = |img: &Image| compare(img, &truth_img).expect("same size").rmse;
    let truth = Truth::new(&accel, lod.grid(level), level, settings.samples);
    let ref_mean = mean(&truth_img);
    let mut rows = Vec::new();
    let mut images = Vec::new();
    let rows_asked: Vec<(String, Oracles)> = if settings.abv_parts.is_empty() {
        Oracles::rows()
            .into_iter()
            .map(|(n, o)| (n.to_string(), o))
            .chain(Oracles::leave_one_out())
            .collect()
    } else {
        Oracles::abv_part_rows(&settings.abv_parts, &settings.abv_cells)
    };
    let all_rows: Vec<(String, Oracles)> = rows_asked
        .into_iter()
        // Normalised rows: the candidate-fix row is the "baked" one.
        .filter(|(_, o)| !(settings.normalize && o.normalize))
        .collect();
    for (term, oracles) in &all_rows {
        let (term, oracles) = (term.as_str(), *oracles);
        let t = Instant::now();
        let rendered = Oracles {
            normalize: oracles.normalize || settings.normalize,
            ..oracles
        };
        let render = |seed: u64| {
            crate::film::render_image(&camera, settings.spp, seed, term, progress, |s| {
                radiance(&lod, &truth, rendered, &Cone::of_sample(&s), &lights, s.rng)
            })
            .0
        };
        let (a, b) = (render(1), render(2));
        let noise = compare(&a, &b).expect("same size").rmse.powi(2) / 4.0;
        let mut img = a;
        for (p, q) in img.pixels.iter_mut().zip(&b.pixels) {
            *p = 0.5 * (*p + *q);
        }
        let rmse = cmp(&img);
        let bias = (rmse * rmse - noise).max(0.0).sqrt();
        rows.push(BudgetRow {
            term: term.to_string(),
            oracles,
            rmse,
            bias,
            rel_bias: bias / ref_mean.max(1e-12),
            gap_closed: 0.0,
            mean_ratio: mean(&img) / ref_mean.max(1e-12),
            seconds: t.elapsed().as_secs_f64() / 2.0,
        });
        if !term.starts_with("all but") {
            images.push((term.to_string(), img));
        }
    }
    let all = rows
        .iter()
        .find(|r| r.oracles == Oracles::ALL)
        .map_or(0.0, |r| r.bias);
    let base = rows[0].bias;
    for r in &mut rows {
        r.gap_closed = if base - all > 0.0 {
            (base - r.bias) / (base - all)
        } else {
            0.0
        };
    }
    let picture = if image == settings.res {
        dir.join(format!("{name}-budget-{}.png", settings.res))
    } else {
        dir.join(format!("{name}-budget-{}-{image}px.png", settings.res))
    };
    budget_picture(&picture, &truth_img, &images, image)?;
    Ok(BudgetResult {
        scene: name.to_string(),
        res: settings.res,
        image,
        spp: settings.spp,
        reference_spp: settings.reference_spp,
        samples: settings.samples,
        normalized: settings.normalize,
        runtime_rmse: cmp(&runtime_img),
        runtime_default_rmse: runtime_default,
        reference_at_spp_rmse: cmp(&ref_spp),
        rows,
        picture,
    })
}

/// The reference and each row's image over its difference from the reference, captioned.
fn budget_picture(path: &Path, truth: &Image, images: &[(String, Image)], res: u32) -> Result<()> {
    use crate::render::compare::difference_image;
    use crate::render::label::{line_height, with_caption};
    let k = (192 / res).max(1);
    let side = res * k;
    let scale_px = 1;
    let (_, scale) = difference_image(&images[0].1, truth, None);
    let cap = |img: &[u8], lines: &[&str]| with_caption(img, side, side, lines, scale_px).0;
    let mut top = vec![cap(
        &super::enlarge(&truth.to_srgb8(0.0), res, res, k),
        &["reference", ""],
    )];
    let mut bottom = vec![cap(
        &vec![0u8; (side * side * 3) as usize],
        &["difference", &format!("white = {scale:.3}")],
    )];
    for (name, img) in images {
        let short: String = name.split(" (").next().unwrap_or(name).to_string();
        let r = compare(img, truth).map(|c| c.rmse).unwrap_or(f64::NAN);
        top.push(cap(
            &super::enlarge(&img.to_srgb8(0.0), res, res, k),
            &[&short, &format!("rmse {r:.4}")],
        ));
        let (d, _) = difference_image(img, truth, Some(scale));
        bottom.push(cap(
            &super::enlarge(&d.to_srgb8(0.0), res, res, k),
            &[&short, ""],
        ));
    }
    let tile_h = side + 2 * line_height(scale_px) + 4 * scale_px;
    super::tile_png(path, &[top, bottom], side, tile_h)
}

/// The budgets as one Markdown table per scene.
pub fn budget_table(results: &[BudgetResult]) -> String {
    let mut s = String::new();
    for r in results {
        s += &format!(
            "### {} ({}³ at {}², 2 × {} spp, {} oracle samples per voxel; reference {} spp; rows {})\n\n",
            r.scene,
            r.res,
            r.image,
            r.spp,
            r.samples,
            r.reference_spp,
            if r.normalized {
                "normalised as the runtime renders"
            } else {
                "as baked"
            }
        );
        s += &format!(
            "runtime's own render: RMSE {:.4}; reference renderer at {} spp (noise floor): {:.4}\n\n",
            r.runtime_rmse, r.spp, r.reference_at_spp_rmse
        );
        s += &format!(
            "runtime's default render (reservoir shading): RMSE {:.4} as baked, {:.4} normalised\n\n",
            r.runtime_default_rmse[0], r.runtime_default_rmse[1]
        );
        s += "| exact term | RMSE | bias | rel. bias | gap closed | mean / ref | s |\n|---|---|---|---|---|---|---|\n";
        for row in &r.rows {
            s += &format!(
                "| {} | {:.4} | {:.4} | {:.3} | {:+.0}% | {:.3} | {:.1} |\n",
                row.term,
                row.rmse,
                row.bias,
                row.rel_bias,
                100.0 * row.gap_closed,
                row.mean_ratio,
                row.seconds
            );
        }
        s += "\n";
    }
    s
}

/// The baked AIV against its oracle, voxel by voxel: for `n` (voxel, direction) pairs drawn
/// from `seed` over the voxels of the truth's level, the baked V̂(ω) and the traced one (the
/// bake's projected-area weighting). A probe of where the AIV term of the budget comes from.
pub fn aiv_pairs(lod: &LodScene, truth: &Truth, n: usize, seed: u64) -> Vec<(u64, Vec3, f32, f32)> {
    let mut keys: Vec<u64> = truth.samples.keys().copied().collect();
    keys.sort_unstable();
    let mut rng = Pcg32::new(seed, 0);
    let mut out = Vec::with_capacity(n);
    let mut vis = [0.0f32; MAX_SAMPLES];
    while out.len() < n && !keys.is_empty() {
        let key = keys[(rng.next_u32() as usize) % keys.len()];
        let Some(v) = lod.voxel(truth.level, key) else {
            continue;
        };
        let s = &truth.samples[&key];
        if s.is_empty() {
            continue;
        }
        let d = crate::math::sampling::square_to_uniform_sphere(rng.next_2d());
        truth.visibility(s, d, &mut vis);
        out.push((key, d, v.aiv(d), weighted_visibility(s, d, &vis)));
    }
    out
}
