//! Where a view's LoD transmittance goes wrong: for the camera cones of a view that meet a
//! primitive, the parts of Eq. 30's weights against the mesh.
//!
//! ```sh
//! cargo run --release -p aggtool-tools --bin cone_weights_probe -- ASSET ASSET.agg VIEW.json [N] [RES]
//! ```
//!
//! N × N cones a pixel (4), each walked with the runtime's default settings, or at the level
//! of resolution RES³ when RES is given (the "finest" level below is then that one: a coarse
//! level's factors against its own voxels' samples). Prints, as means
//! over the cones that meet a primitive:
//! - **background**: the runtime's normalised background weight T / (T + Σw), the ray's own
//!   escape through the mesh, and the share of rays escaping the mesh from that cone's entry
//!   face (the error budget's oracle, [`abv_over_part`]: 16 rays from the face's points a
//!   cone could enter by, in the cone's direction, P⁺ only: what the face's ABV map
//!   estimates, Eq. 26) beside the baked ABV;
//! - **surfaces**: Σ V̂(ω_o)·c over the hits (un-normalised, Eq. 30), the same with V̂ traced
//!   from 32 samples of each voxel's real surface (the budget's oracle), and 1 − the ray's own
//!   escape, which both estimate;
//! - **geometry**: Σ c (Eq. 24's |A|_ω·E|n·ω|/|B|_ω, without V̂) over the hits against the
//!   number of surfaces the ray crosses, which it estimates;
//! - the ABV baked and the face's escape by the cosine of the cone with the face's inward
//!   normal (four bins);
//! - V̂(ω_o) baked and traced by the hit's order along the cone;
//! - c's factors at the finest level's hits (means over hits): the lobes' E|n·ω| (the SGGX
//!   mixture's projected area, the runtime's own `VoxelHandle::mean_cosine`) against 64
//!   fresh samples' Σ w|n_g·ω| / Σ w, and the stored area after cut-outs against the voxel's
//!   pieces' area times those samples' coverage.
//!
//! The sums walk every primitive the centre ray meets, without the runtime's front-to-back
//! occlusion (which only the normalised background sees). A voxel without oracle samples, or
//! of a coarser level, keeps its baked V̂ in the traced sum.

use aggtool::bake::sampling::{pieces_by_voxel, sample_voxel};
use aggtool::eval::budget::{abv_over_part, Oracles, Truth};
use aggtool::math::rng::Pcg32;
use aggtool::render::View;
use aggtool::runtime::{Cone, LodScene, TraceSettings};
use aggtool::trace::{Accel, Ray};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use std::collections::HashMap;

/// Sums over cones (and, for `by_hit`, over the k-th hit of each).
#[derive(Clone, Default)]
struct Sums {
    cones: f64,
    normalised: f64,
    own: f64,
    face: f64,
    face_cones: f64,
    baked_abv_face: f64,
    baked_abv: f64,
    s_baked: f64,
    s_traced: f64,
    g: f64,
    crossings: f64,
    by_hit: [(f64, f64, f64); 8],
    /// Finest-level hits: count, lobes' E|n·ω|, samples' E|n·ω|, stored area, pieces' area.
    factors: [f64; 5],
    /// By the cosine of the cone's direction with the entry face's inward normal, in four
    /// bins of width 1/4: cones, baked ABV, the face's escape.
    by_cosine: [(f64, f64, f64); 4],
}

impl Sums {
    fn add(mut self, o: Sums) -> Sums {
        self.cones += o.cones;
        self.normalised += o.normalised;
        self.own += o.own;
        self.face += o.face;
        self.face_cones += o.face_cones;
        self.baked_abv_face += o.baked_abv_face;
        self.baked_abv += o.baked_abv;
        self.s_baked += o.s_baked;
        self.s_traced += o.s_traced;
        self.g += o.g;
        self.crossings += o.crossings;
        for (a, b) in self.by_cosine.iter_mut().zip(o.by_cosine) {
            a.0 += b.0;
            a.1 += b.1;
            a.2 += b.2;
        }
        for (a, b) in self.factors.iter_mut().zip(o.factors) {
            *a += b;
        }
        for (a, b) in self.by_hit.iter_mut().zip(o.by_hit) {
            a.0 += b.0;
            a.1 += b.1;
            a.2 += b.2;
        }
        self
    }
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 4 {
        anyhow::bail!("usage: cone_weights_probe ASSET ASSET.agg VIEW.json [N] [RES]");
    }
    let scene = aggtool::import::load(std::path::Path::new(&a[1]), Default::default())?;
    let lod = LodScene::open(std::path::Path::new(&a[2]))?;
    let view = View::load(std::path::Path::new(&a[3]))?;
    let n: u32 = a.get(4).map_or(Ok(4), |s| s.parse())?;
    let accel = Accel::build(&scene);
    let cam = view.camera();
    let want: Option<u32> = a.get(5).map(|s| s.parse()).transpose()?;
    let Some(finest) = (0..lod.level_count())
        .filter(|&l| want.map_or(true, |r| lod.grid(l).res == r))
        .max_by_key(|&l| lod.grid(l).res)
    else {
        anyhow::bail!("{}: no {}³ level", a[2], want.unwrap_or(0));
    };
    let truth = Truth::new(&accel, lod.grid(finest), finest, 32);
    // Per voxel of the finest level: 64 fresh samples' (geometric normal, weight) and the
    // pieces' area; the stored area after cut-outs.
    let pieces: Vec<_> = pieces_by_voxel(&scene, &lod.grid(finest))
        .into_iter()
        .collect();
    let fresh: HashMap<u64, (Vec<(Vec3, f32)>, f64)> = pieces
        .par_iter()
        .map(|(key, p)| {
            let s = sample_voxel(&scene, p, 64, (*key as u32) ^ 0x5eed_c0e5);
            let s = s
                .iter()
                .map(|x| (x.geometric_normal.normalize_or_zero(), x.surface.weight));
            (*key, (s.collect(), p.iter().map(|q| q.area).sum()))
        })
        .collect();
    // The stored area after cut-outs.
    let stored: HashMap<u64, f64> = aggtool::format::Aggregate::open(std::path::Path::new(&a[2]))?
        .read_level(finest)
        .voxels
        .iter()
        .map(|v| (v.key, v.area * v.coverage as f64))
        .collect();
    let forced = want.map(|_| finest);
    let raw = TraceSettings {
        normalize: false,
        level: forced,
        ..TraceSettings::default()
    };
    let normalised = TraceSettings {
        level: forced,
        ..TraceSettings::default()
    };
    // The budget's oracle of the entry face's ABV: its reachable points, the cone's direction.
    let face = Oracles {
        abv_part: 1,
        abv_reachable: true,
        ..Default::default()
    };
    let sums = (0..cam.height)
        .into_par_iter()
        .map(|y| {
            let mut s = Sums::default();
            let mut rng = Pcg32::new(y as u64, 0xc0e5);
            for x in 0..cam.width {
                for k in 0..n * n {
                    let p = Vec2::new(
                        x as f32 + ((k % n) as f32 + 0.5) / n as f32,
                        y as f32 + ((k / n) as f32 + 0.5) / n as f32,
                    );
                    let (o, d) = cam.ray(p);
                    let cone = Cone::new(o, d, cam.pixel_angle());
                    let mut hits = lod.hits(&cone, &raw);
                    let (mut s_b, mut s_t, mut g) = (0f64, 0f64, 0f64);
                    let mut i = 0;
                    while let Some((voxel, _, c)) = hits.next_geometric() {
                        let (c, vb) = (c as f64, voxel.aiv(-d) as f64);
                        s_b += vb * c;
                        g += c;
                        if let (true, Some((fs, area)), Some(st)) = (
                            voxel.level() == finest,
                            fresh.get(&voxel.key()),
                            stored.get(&voxel.key()),
                        ) {
                            let w: f64 = fs.iter().map(|x| x.1 as f64).sum();
                            if w > 0.0 {
                                let mc = fs
                                    .iter()
                                    .map(|x| x.1 as f64 * x.0.dot(d).abs() as f64)
                                    .sum::<f64>()
                                    / w;
                                s.factors[0] += 1.0;
                                s.factors[1] += voxel.mean_cosine(d) as f64;
                                s.factors[2] += mc;
                                s.factors[3] += *st;
                                s.factors[4] += area * w;
                            }
                        }
                        let traced = (voxel.level() == finest)
                            .then(|| truth.traced(voxel.key(), -d))
                            .flatten();
                        match traced {
                            Some(vt) => {
                                s_t += c * vt as f64;
                                let e = &mut s.by_hit[i.min(7)];
                                e.0 += 1.0;
                                e.1 += vb;
                                e.2 += vt as f64;
                            }
                            None => s_t += vb * c,
                        }
                        i += 1;
                    }
                    if hits.primitives() == 0 {
                        continue;
                    }
                    let abv = hits.transmittance() as f64;
                    let mut nh = lod.hits(&cone, &normalised);
                    let w: f64 = nh.by_ref().map(|h| h.weight as f64).sum();
                    let t = nh.transmittance() as f64;
                    let own = !accel.occluded(&Ray::new(o, d)) as u32 as f64;
                    let mut r = Ray::new(o, d);
                    let mut crossings = 0u32;
                    while let Some(hit) = accel.intersect(&r) {
                        crossings += 1;
                        r.tmin = hit.t * (1.0 + 1e-5) + 1e-6;
                        if crossings > 10_000 {
                            break;
                        }
                    }
                    s.cones += 1.0;
                    s.normalised += if t + w > 0.0 { t / (t + w) } else { 0.0 };
                    s.own += own;
                    s.baked_abv += abv;
                    s.s_baked += s_b;
                    s.s_traced += s_t;
                    s.g += g;
                    s.crossings += crossings as f64;
                    if let Some(entry) = hits.entry() {
                        if let Some(f) = abv_over_part(&lod, &truth, entry, &cone, face, &mut rng) {
                            let f = f as f64;
                            s.face += f;
                            s.face_cones += 1.0;
                            s.baked_abv_face += abv;
                            let inward = -aggtool::spatial::face_normal(entry.2);
                            let bin = ((inward.dot(d).clamp(0.0, 1.0) * 4.0) as usize).min(3);
                            let e = &mut s.by_cosine[bin];
                            e.0 += 1.0;
                            e.1 += abv;
                            e.2 += f;
                        }
                    }
                }
            }
            s
        })
        .reduce(Sums::default, Sums::add);
    let m = |x: f64| x / sums.cones.max(1.0);
    let f = |x: f64| x / sums.face_cones.max(1.0);
    println!(
        "{} cones meet a primitive ({} × {} a pixel, {}×{} pixels)",
        sums.cones, n, n, cam.width, cam.height
    );
    println!(
        "background: normalised T/(T+Σw) {:.4}, the ray's own escape {:.4}",
        m(sums.normalised),
        m(sums.own)
    );
    println!(
        "ABV: baked {:.4}, the entry face's escape in the ray's direction {:.4} (over {} cones whose face has P⁺ rays; baked over the same {:.4})",
        m(sums.baked_abv),
        f(sums.face),
        sums.face_cones,
        f(sums.baked_abv_face)
    );
    println!(
        "surfaces: Σ V̂·c baked {:.4}, with V̂ traced {:.4}, 1 − own escape {:.4}",
        m(sums.s_baked),
        m(sums.s_traced),
        1.0 - m(sums.own)
    );
    println!(
        "geometry: Σ c {:.4}, surfaces crossed {:.4}",
        m(sums.g),
        m(sums.crossings)
    );
    for (i, e) in sums.by_cosine.iter().enumerate() {
        if e.0 > 0.0 {
            println!(
                "ABV at cos(cone, inward normal) in [{:.2}, {:.2}): {} cones, baked {:.4}, face {:.4}",
                i as f64 / 4.0,
                (i + 1) as f64 / 4.0,
                e.0,
                e.1 / e.0,
                e.2 / e.0
            );
        }
    }
    let fc = &sums.factors;
    let h = fc[0].max(1.0);
    println!(
        "c's factors over {} finest hits: E|n·ω| lobes {:.4}, samples {:.4}; area after cut-outs stored {:.4e}, pieces × samples' coverage {:.4e}",
        fc[0],
        fc[1] / h,
        fc[2] / h,
        fc[3] / h,
        fc[4] / h
    );
    for (i, e) in sums.by_hit.iter().enumerate() {
        if e.0 > 0.0 {
            println!(
                "hit {}{}: {} hits, V̂(ω_o) baked {:.4}, traced {:.4}",
                i + 1,
                if i == 7 { " and after" } else { "" },
                e.0,
                e.1 / e.0,
                e.2 / e.0
            );
        }
    }
    Ok(())
}
