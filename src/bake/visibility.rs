//! Aggregated interior visibility (paper Eq. 25): the average over a voxel's surfaces of the
//! visibility through the whole scene, per direction, on a `res × res` Clarberg equal-area map.
//! Rays leave every surface sample in directions spread over the sphere by a scrambled Sobol
//! sequence (shared across the voxel's samples, so the cells fill evenly), and each cell
//! averages the visibility of the rays that fall in it. Cut-outs are honoured by the ray tracer.
//!
//! **Projected-area weighting** (format 1.2, `AivWeighting::ProjectedArea`). Eq. 25 weights
//! every point of A equally; we weight it by |n·ω|:
//!
//! ```text
//! V̂(ω) = ∫_A V(x, ω) |n(x)·ω| dA / ∫_A |n(x)·ω| dA
//! ```
//!
//! Eq. 30's coverage V̂(ω_o)·|A|·E|n·ω_o| is then exactly the voxel's visible projected area;
//! with equal weights it assumes visibility independent of |n·ω|, which fails on bumpy closed
//! surfaces (the facets that face the viewer are the visible ones). Measured with
//! `tools/src/bin/transmittance_probe.rs` (coverage + background transmittance, 1 when consistent):
//! displaced sphere 0.88 → 0.97, mcap coral at 64³ 0.74 → 0.83, building-small-a 0.86 → 0.91,
//! lattice 1.00 → 0.97. For any convex solid the weighted V̂ is exactly 1/2 in every direction
//! (tested on a cube, where the area-weighted one is not).
//!
//! **Exposure.** Eq. 25 averages V(x, ω) over all of A, and Eq. 6 then multiplies the averages
//! for ω_i and ω_o, as if the visibility towards the light and towards the viewer were
//! independent. They are not: a side of a surface that sees the sky in one direction tends to
//! see it in others, and the inner side of a solid's wall sees nothing at all. For a sphere V̂ is
//! exactly 1/2 in every direction, so V̂(ω_i)·V̂(ω_o) = 1/4 where the lit, seen outer side has
//! visibility 1 both ways: closed geometry rendered about 2× too dark (measured: the lattice
//! hard case at 57% of the reference radiance). The runtime therefore uses min(1, V̂(ω_i)/η) for
//! incident light, η in [1/16, 1] the voxel's *exposure*, and V̂(ω_o) unchanged for the coverage,
//! whose product with |A|_ω is exact either way.
//!
//! η is fitted to what the incident visibility is for: the light reaching the points the viewer
//! sees. A point's side is seen from about as many directions as it sees out of, so each AIV ray
//! is weighted by its side's escape fraction e (the side's other rays, leave-one-out, so that a
//! ray does not predict itself), and η minimises
//!
//! ```text
//! Σ_rays  w · e · (min(1, V̂'(ω)/η) − v)²      over η = 2^(−k/4), k = 0..16
//! ```
//!
//! V̂' the map of the other fold of samples (as the bandwidth's cross-validation builds it), v
//! the ray's visibility. Only the exposed sides count, so a solid's inner walls (e = 0) do not:
//! a whole sphere in one voxel gets η ≤ 1/2, an incident visibility of 1 in every direction
//! (V̂ = 1/2, and every exposed ray escapes; light from behind a point is the ABSDF's to
//! refuse, Eq. 3 pairs only directions on one side), a piece of a wall η ≈ 1 (V̂ is already
//! its outer side's visibility: a partly shaded wall keeps its shadow), and a blurred horizon
//! is lifted back towards the 1 of the exposed side. The
//! scalar it replaces, E\[v\]²/E\[v²\] over (sample, side) pairs, gave every wall 1/2 and so twice
//! the light in its partial shadows: grass-trees-tall 64³ 0.0210 → 0.0169 RMSE with this fit,
//! building-small-a 0.0244 either way (`tools/src/bin/shading_noise.rs`, see the README).

use glam::Vec2;

use super::sampling::PointSample;
use crate::math::lowdiscrepancy::sobol_2d;
use crate::math::sphere_maps::{
    cap_averages, equal_area_square_to_sphere, grid_cell, BlockPyramid,
};
use crate::trace::{offset_origin, Accel, Ray};

/// The smallest exposure stored: the incident AIV is never scaled up more than this allows.
pub const MIN_EXPOSURE: f32 = 1.0 / 16.0;

/// A voxel's AIV estimate ([`aiv_map`]).
#[derive(Clone, Debug, PartialEq)]
pub struct AivEstimate {
    /// Row-major `res × res`, values in [0, 1].
    pub map: Vec<f32>,
    /// Rays traced.
    pub rays: u64,
    /// η in [MIN_EXPOSURE, 1] (see the module notes).
    pub exposure: f32,
    /// How a cell's estimate gathers its rays: a block of the `min_rays` asked for, or the
    /// bandwidth cross-validation chose among [`AIV_BANDWIDTHS`] when asked for 0.
    pub bandwidth: Bandwidth,
    /// The multiple of the noise σ ([`map_noise_sigma`]) the wavelet shrinkage should use:
    /// chosen by cross-validation among [`AIV_DENOISE_CANDIDATES`] when denoising, else 0.
    pub denoise: f32,
    /// Per surface sample (in the order given), the fraction of its rays that escaped: how
    /// exposed the sample is, the weight of its ABSDF statistics ([`exposed_weight`]).
    pub sample_escape: Vec<f32>,
}

/// The weight factor of a surface sample in the voxel's ABSDF statistics: its AIV escape
/// fraction, floored at 10⁻³ so that a voxel whose every sample is buried still has statistics.
///
/// Eq. 3 averages the BSDF over all of the voxel's surfaces, and Eq. 6 multiplies it by the
/// averaged visibilities, as if what a surface is made of and how much of it sees out were
/// independent. In a solid prop they are not: the inner faces of a wall, the underside of a
/// plank and the floor under a barrel have their own normals and materials, and none of it is
/// lit or seen. Weighting each sample by the fraction of the scene it sees out into (its AIV
/// rays, already traced) lets the exposed surfaces set the lobes, the roughness and the
/// albedo moments, which is Eq. 3 with the visibility of Eq. 6 moved inside the integral for
/// the part of it that belongs to the sample rather than to the direction. Coverage, the
/// ellipsoid and the AIV itself keep the plain area weights. Measured at 64³ with
/// `tools/src/bin/shading_noise.rs` (RMSE of the default render): mill 0.0116 → 0.0102, barrel
/// 0.0081 → 0.0072, building-garage 0.0253 → 0.0236 (see the README).
pub fn exposed_weight(escape: f32) -> f32 {
    escape.clamp(1e-3, 1.0)
}

/// The standard deviation of one cell of a visibility map estimated from `rays_per_cell`
/// binary rays around a map mean of `mean`: the scale of the wavelet shrinkage's threshold
/// ([`crate::math::haar::shrink`]), for AIV and ABV maps alike. Fewer rays than cells (an ABV
/// whose blocks of cells share rays): the fill makes blocks of cells share one estimate, whose
/// noise reaches the Haar details of the block's size with the amplitude of white noise of
/// 1/rays_per_cell per cell, so σ grows past that of a single ray.
pub fn map_noise_sigma(mean: f32, rays_per_cell: f32) -> f32 {
    (mean * (1.0 - mean)).max(0.0).sqrt() / rays_per_cell.max(1.0 / 1024.0).sqrt()
}

/// The multiples of [`map_noise_sigma`] [`aiv_map`] tries for the shrinkage when denoising.
pub const AIV_DENOISE_CANDIDATES: [f32; 4] = [0.0, 0.25, 0.5, 1.0];

/// The AIV map of a voxel, the number of rays traced, the exposure and the bandwidth the
/// estimate used ([`AivEstimate`]). A cell's value is the
/// average of the smallest enclosing block of cells (itself first) that at least `min_rays`
/// rays reached; `min_rays` 0 chooses per voxel, by cross-validation, among such blocks and
/// spherical caps (`cross_validated_bandwidth`, [`AIV_BANDWIDTHS`]), and `denoise` the shrinkage's strength
/// likewise (`cross_validated_denoise`). With 1, cells no ray reached still take
/// the average of the smallest enclosing block that some ray reached: a finest-level voxel
/// traces 16 samples × 16 rays = 256 rays over 32² cells, and filling the other 3/4 with the
/// voxel's mean over the whole sphere pulled every outward-facing cell of a wall from 1 towards
/// 1/2 (a 64³ level of the buildings hard case rendered at 0.91 coverage and 0.81 of the
/// reference radiance, against 1.02 and 0.96 at 32³).
pub fn aiv_map(
    accel: &Accel,
    samples: &[PointSample],
    res: u32,
    rays_per_sample: u32,
    min_rays: u32,
    denoise: bool,
    seed: u32,
) -> AivEstimate {
    let mut rays: Vec<AivRay> = Vec::with_capacity(samples.len() * rays_per_sample as usize);
    let mut sample_escape = Vec::with_capacity(samples.len());
    let mut index = 0u32;
    for (j, s) in samples.iter().enumerate() {
        // Per side (front = along the geometric normal): rays traced, rays escaped.
        let mut side = [[0u32; 2]; 2];
        let first = rays.len();
        for _ in 0..rays_per_sample {
            let u: Vec2 = sobol_2d(index, seed);
            index = index.wrapping_add(1);
            let d = equal_area_square_to_sphere(u);
            let ray = Ray::new(offset_origin(s.position, s.geometric_normal, d), d);
            let cos = d.dot(s.geometric_normal);
            let k = (cos < 0.0) as usize;
            side[k][0] += 1;
            let seen = !accel.occluded(&ray);
            side[k][1] += seen as u32;
            rays.push(AivRay {
                cell: grid_cell(u, res),
                // Projected-area weighting (format 1.2, see the module notes).
                weight: s.surface.weight as f64 * cos.abs() as f64,
                seen,
                fold: (j & 1) as u8,
                side: k as u8,
                // Set below, once the side's counts are known.
                escape: 0.0,
            });
        }
        let traced = side[0][0] + side[1][0];
        let escaped = side[0][1] + side[1][1];
        sample_escape.push(if traced > 0 {
            escaped as f32 / traced as f32
        } else {
            0.0
        });
        for r in &mut rays[first..] {
            let [t, e] = side[r.side as usize];
            r.escape = if t >= 2 {
                (e - r.seen as u32) as f32 / (t - 1) as f32
            } else {
                0.0
            };
        }
    }
    let all = cell_sums(&rays, res, None);
    let total_w: f64 = all.weight.iter().sum();
    let mean = if total_w > 0.0 {
        (all.vis.iter().sum::<f64>() / total_w) as f32
    } else {
        1.0
    };
    let bandwidth = if min_rays == 0 {
        cross_validated_bandwidth(&rays, res, mean)
    } else {
        Bandwidth {
            min_rays,
            cap: false,
        }
    };
    let map = estimate(&all, &[bandwidth], res, mean).remove(0);
    let folds = fold_maps(&rays, res, bandwidth, mean);
    let exposure = fitted_exposure(&rays, &folds);
    let denoise = if denoise {
        cross_validated_denoise(&rays, res, &folds)
    } else {
        0.0
    };
    AivEstimate {
        map,
        rays: rays.len() as u64,
        exposure,
        bandwidth,
        denoise,
        sample_escape,
    }
}

/// One AIV ray: its map cell, its projected-area weight, whether it escaped, and the fold of
/// its surface sample (samples alternate between folds 0 and 1).
#[derive(Clone, Copy)]
struct AivRay {
    cell: u32,
    weight: f64,
    seen: bool,
    fold: u8,
    /// 0 along the sample's geometric normal, 1 against it.
    side: u8,
    /// The escape fraction of the ray's side from its sample's other rays on that side (0 when
    /// it has none): the exposure fit's weight.
    escape: f32,
}

/// Per fold of samples, its map at `bandwidth` and the rays it rests on: what the exposure fit
/// and the shrinkage's cross-validation predict the other fold's rays with.
fn fold_maps(rays: &[AivRay], res: u32, bandwidth: Bandwidth, mean: f32) -> [(Vec<f32>, u64); 2] {
    [0u8, 1].map(|f| {
        let c = cell_sums(rays, res, Some(f));
        let map = estimate(&c, &[bandwidth], res, mean).remove(0);
        (map, c.count.iter().map(|&n| n as u64).sum())
    })
}

/// The exposure η fitted to the exposed sides' rays (see the module notes): of η = 2^(−k/4),
/// k = 0..16, the one whose min(1, V̂'(ω)/η) from the other fold's map ([`fold_maps`]) best
/// predicts the rays weighted by w·e (ties to the larger η; 1 when no ray has an exposed side).
fn fitted_exposure(rays: &[AivRay], folds: &[(Vec<f32>, u64); 2]) -> f32 {
    let mut best = (f64::INFINITY, 1.0f32);
    for k in 0..=16 {
        let scale = 2f32.powf(k as f32 / 4.0);
        let mut err = 0f64;
        for r in rays.iter().filter(|r| r.escape > 0.0) {
            let p = (scale * folds[1 - r.fold as usize].0[r.cell as usize]).min(1.0);
            let d = p as f64 - r.seen as u32 as f64;
            err += r.weight * r.escape as f64 * d * d;
        }
        if err < best.0 - 1e-12 {
            best = (err, scale);
        }
    }
    (1.0 / best.1).clamp(MIN_EXPOSURE, 1.0)
}

/// The map of `sums` at each of `bandwidths`: blocks from one [`BlockPyramid`], caps from one
/// walk of [`cap_averages`] (blocks where the map's resolution has no [`CapOrder`]).
///
/// [`BlockPyramid`]: crate::math::sphere_maps::BlockPyramid
/// [`CapOrder`]: crate::math::sphere_maps::CapOrder
fn estimate(sums: &CellSums, bandwidths: &[Bandwidth], res: u32, mean: f32) -> Vec<Vec<f32>> {
    let (vis, weight, count) = (&sums.vis, &sums.weight, &sums.count);
    // The caps in the order given (ascending in every caller), walked once.
    let caps: Vec<u32> = bandwidths
        .iter()
        .filter(|b| b.cap)
        .map(|b| b.min_rays)
        .collect();
    let mut cap_maps = (!caps.is_empty())
        .then(|| cap_averages(vis, weight, count, &caps, res, mean))
        .flatten()
        .map(Vec::into_iter);
    let pyramid = std::cell::OnceCell::new();
    bandwidths
        .iter()
        .map(
            |b| match cap_maps.as_mut().filter(|_| b.cap).and_then(Iterator::next) {
                Some(map) => map,
                None => pyramid
                    .get_or_init(|| BlockPyramid::new(vis, weight, count, res))
                    .map(b.min_rays, mean),
            },
        )
        .collect()
}

/// Per-cell sums of a map: Σ w·v, Σ w, and the ray count.
struct CellSums {
    vis: Vec<f64>,
    weight: Vec<f64>,
    count: Vec<u32>,
}

/// The sums of the rays of `fold` (all rays for `None`).
fn cell_sums(rays: &[AivRay], res: u32, fold: Option<u8>) -> CellSums {
    let cells = (res * res) as usize;
    let mut s = CellSums {
        vis: vec![0.0; cells],
        weight: vec![0.0; cells],
        count: vec![0; cells],
    };
    for r in rays.iter().filter(|r| fold.is_none_or(|f| r.fold == f)) {
        let c = r.cell as usize;
        s.vis[c] += if r.seen { r.weight } else { 0.0 };
        s.weight[c] += r.weight;
        s.count[c] += 1;
    }
    s
}

/// How a visibility map's cell gathers the rays it rests on: at least `min_rays` of them, from
/// the smallest enclosing 2^k × 2^k block of the map's square ([`BlockPyramid`], `cap` false)
/// or from a neighbourhood centred on the cell (`cap` true): for the AIV's sphere map the
/// spherical cap of the nearest cells ([`cap_averages`]), for the ABV's hemisphere map a
/// centred window ([`CentredWindows`]).
///
/// [`BlockPyramid`]: crate::math::sphere_maps::BlockPyramid
/// [`CentredWindows`]: crate::math::sphere_maps::CentredWindows
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bandwidth {
    /// Fewest rays a cell's estimate rests on.
    pub min_rays: u32,
    /// Gather from a neighbourhood centred on the cell rather than an enclosing block.
    pub cap: bool,
}

impl Bandwidth {
    /// Blocks of at least each of `blocks` rays, then caps (windows) of each of `caps` rays:
    /// the candidate lists of [`AIV_BANDWIDTHS`] and the ABV's.
    pub const fn list<const N: usize>(blocks: &[u32], caps: &[u32]) -> [Bandwidth; N] {
        assert!(blocks.len() + caps.len() == N, "candidate count");
        let mut out = [Bandwidth {
            min_rays: 0,
            cap: false,
        }; N];
        let mut i = 0;
        while i < N {
            out[i] = if i < blocks.len() {
                Bandwidth {
                    min_rays: blocks[i],
                    cap: false,
                }
            } else {
                Bandwidth {
                    min_rays: caps[i - blocks.len()],
                    cap: true,
                }
            };
            i += 1;
        }
        out
    }
}

impl std::fmt::Display for Bandwidth {
    /// "4 rays" (a block), "cap of 8 rays".
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let rays = ray_count(self.min_rays);
        if self.cap {
            write!(f, "cap of {rays}")
        } else {
            write!(f, "{rays}")
        }
    }
}

/// "1 ray", "4 rays": how the bake's `stats:` lines name a bandwidth's ray count.
pub fn ray_count(k: u32) -> String {
    if k == 1 {
        "1 ray".into()
    } else {
        format!("{k} rays")
    }
}

/// The bandwidths [`aiv_map`] chooses among when its `min_rays` is 0
/// (`BakeSettings::aiv_min_rays`): blocks first (a fixed `min_rays` is a block of that many),
/// then caps.
///
/// A block has the direction it estimates anywhere inside it, so on a smooth visibility its
/// bias is of first order in its size; a cap is centred on it (second order). Blocks win where
/// a solid's horizon runs along their edges: the Clarberg square's quadtree has the planes x = 0
/// and y = 0 on its edges at every level, the horizons of axis-aligned walls. Measured with
/// `tools/src/bin/shading_noise.rs` on 64³ bakes (RMSE of the default render; blocks only → caps only
/// → the choice among both): mill 0.0102 → 0.0092 → 0.0090, barrel 0.0070 → 0.0065 → 0.0064,
/// spiral staircase 0.0155 → 0.0146 → 0.0143, grass-trees-tall 0.0160 → 0.0154 → 0.0149,
/// fantasy_house_01 0.0075 → 0.0073 → 0.0074, building-small-b 0.0196 → 0.0201 → 0.0196.
pub const AIV_BANDWIDTHS: [Bandwidth; 11] =
    Bandwidth::list(&[1, 2, 4, 8, 16], &[1, 2, 4, 8, 16, 32]);

/// The bandwidth of a voxel's AIV estimate, chosen by two-fold cross-validation over its
/// surface samples: for each candidate of [`AIV_BANDWIDTHS`], the map built from one fold's
/// rays ([`estimate`]) predicts the other fold's rays, and the candidate with the least
/// weighted squared error Σ w (v − V̂(cell))² over both ways wins (ties to the earlier). A
/// finest-level voxel traces 16 × 32 rays over 32² cells: where visibility varies little over
/// directions (thin, scattered geometry: the lattice, foliage) a cell should pool the rays of
/// its neighbours; where it jumps (the horizon of a solid's wall) pooling blurs the jump, and
/// the map should stay fine. Measured with `tools/src/bin/aiv_probe.rs` (RMS of baked − traced V̂ over
/// 20,000 voxel-direction pairs at 64³, blocks only): lattice 0.238 (1 ray a cell) → 0.158
/// (8 rays) / 0.165 (chosen), displaced sphere 0.217 → 0.271 / 0.222.
fn cross_validated_bandwidth(rays: &[AivRay], res: u32, mean: f32) -> Bandwidth {
    let folds = [cell_sums(rays, res, Some(0)), cell_sums(rays, res, Some(1))];
    let maps = folds
        .each_ref()
        .map(|s| estimate(s, &AIV_BANDWIDTHS, res, mean));
    let mut best = (f64::INFINITY, AIV_BANDWIDTHS[0]);
    for (c, b) in AIV_BANDWIDTHS.into_iter().enumerate() {
        let mut score = 0f64;
        for (f, m) in maps.iter().enumerate() {
            score += held_out_error(rays, 1 - f as u8, &m[c]);
        }
        if score < best.0 - 1e-12 {
            best = (score, b);
        }
    }
    best.1
}

/// Σ w (v − m(cell))² over the rays of `fold`.
fn held_out_error(rays: &[AivRay], fold: u8, m: &[f32]) -> f64 {
    rays.iter()
        .filter(|r| r.fold == fold)
        .map(|r| {
            let e = r.seen as u32 as f64 - m[r.cell as usize].clamp(0.0, 1.0) as f64;
            r.weight * e * e
        })
        .sum()
}

/// Rays per cell of an AIV map as its shrinkage counts them ([`map_noise_sigma`]): a
/// finest-level voxel traces fewer rays than its map has cells (16 × 16 over 32²), but its
/// noise is taken as a ray's per cell at least: with the true 1/4 the chandelier's 64³ level
/// lost 3.3 of its 11 MiB and rendered 6% worse (RMSE 0.0297 against 0.0279).
pub fn aiv_rays_per_cell(rays: u64, res: u32) -> f32 {
    (rays as f32 / (res * res) as f32).max(1.0)
}

/// The strength of the wavelet shrinkage of a voxel's AIV map, chosen by two-fold
/// cross-validation as [`cross_validated_bandwidth`] chooses the bandwidth (with the bandwidth
/// fixed): each fold's map, shrunk with each candidate multiple of its own noise σ, predicts
/// the other fold's rays; the least weighted squared error wins (ties to the weaker). The
/// universal threshold σ·√(2 ln N²) assumes every cell a binomial of the map's mean; on a
/// solid's map, 0 below the horizon and 1 above without noise, it erases the horizon's
/// details (`aiv_probe --estimators`, tools/src/bin/aiv_probe.rs, displaced sphere at 32³ from 256 samples ×
/// 16 rays: RMS 0.095 raw, 0.152 shrunk).
fn cross_validated_denoise(rays: &[AivRay], res: u32, folds: &[(Vec<f32>, u64); 2]) -> f32 {
    use crate::math::haar::{forward, inverse, shrink};
    let n = res as usize;
    // Per fold ([`fold_maps`]): the map, its Haar transform and its noise σ.
    let folds = folds.each_ref().map(|(map, traced)| {
        let map_mean = (map.iter().map(|&v| v as f64).sum::<f64>() / map.len() as f64) as f32;
        let (c, d) = forward(map, n);
        let sigma = map_noise_sigma(map_mean, aiv_rays_per_cell(*traced, res));
        (map, c, d, sigma)
    });
    let mut best = (f64::INFINITY, AIV_DENOISE_CANDIDATES[0]);
    for scale in AIV_DENOISE_CANDIDATES {
        let mut score = 0f64;
        for (f, (map, c, d, sigma)) in folds.iter().enumerate() {
            let held_out = 1 - f as u8;
            score += if scale > 0.0 {
                let mut d = d.clone();
                shrink(&mut d, scale * sigma, n);
                held_out_error(rays, held_out, &inverse(*c, &d, n))
            } else {
                held_out_error(rays, held_out, map.as_slice())
            };
        }
        if score < best.0 - 1e-12 {
            best = (score, scale);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::absdf::estimate::SurfaceSample;
    use crate::gen::glb::{MaterialData, SceneData};
    use crate::gen::shapes;
    use crate::math::sphere_maps::equal_area_sphere_to_square;
    use crate::scene::SurfaceParams;
    use glam::Vec3;

    /// A convex sphere, alone: from its surface, a direction is visible exactly when it leaves
    /// the tangent plane outwards, so the AIV is 1/2 in every direction. 2048 samples × 64 rays
    /// put ~128 rays in each of the 1024 cells (standard error ~0.05 with projected-area weights):
    /// every cell within 0.25, the mean within 0.01.
    #[test]
    fn sphere_aiv_is_one_half() {
        let scene = SceneData::single(
            shapes::sphere(Vec3::ZERO, 0.5, 96, |_| 0.0),
            MaterialData::new("white", [1.0; 3], 0.0, 1.0),
        )
        .to_scene();
        let accel = Accel::build(&scene);
        // Samples on the sphere (radius 0.5), uniform by area.
        let samples: Vec<PointSample> = (0..2048)
            .map(|i| {
                let n = crate::math::sampling::square_to_uniform_sphere(sobol_2d(i, 3));
                // Project onto the tessellated surface: the nearest hit along the normal.
                let hit = accel
                    .intersect(&Ray::new(Vec3::ZERO, n))
                    .expect("inside the sphere");
                let p = n * hit.t;
                PointSample {
                    position: p,
                    geometric_normal: accel.surface(&Ray::new(Vec3::ZERO, n), &hit).ng,
                    surface: SurfaceSample {
                        normal: n,
                        params: SurfaceParams::lambertian(Vec3::ONE),
                        weight: 1.0 / 2048.0,
                    },
                }
            })
            .collect();
        let AivEstimate {
            map,
            rays: traced,
            exposure,
            ..
        } = aiv_map(&accel, &samples, 32, 64, 0, true, 7);
        assert_eq!(traced, 2048 * 64);
        // A solid: only the outer side is ever visible, and from it every direction the ray
        // leaves by: the incident visibility min(1, V̂/η) is 1 in every cell (η at most 1/2;
        // the fit is indifferent to anything smaller, every prediction already being 1).
        assert!(exposure <= 0.51, "exposure {exposure}");
        for (i, v) in map.iter().enumerate() {
            assert_eq!((v / exposure).min(1.0), 1.0, "cell {i}: {v}, η {exposure}");
        }
        let mean = map.iter().sum::<f32>() / map.len() as f32;
        assert!((mean - 0.5).abs() < 0.01, "mean {mean}");
        // Projected-area weights leave fewer effective rays per cell than equal weights.
        for (i, v) in map.iter().enumerate() {
            assert!((v - 0.5).abs() < 0.25, "cell {i}: {v}");
        }
        // Format 1.4 stores the tree in fixed point (math::haar::QNode): truncated as the bake
        // truncates, quantized and decoded, the map is still 1/2 (mean within 0.01, every
        // cell within 0.25) and within 3 · 5 / (2 · 254) = 0.03 of the float tree.
        let (c, mut d) = crate::math::haar::forward(&map, 32);
        crate::math::haar::truncate(c, &mut d, 0.10, 0.95);
        let t = crate::math::haar::SparseHaar::new(c, &d, 32);
        let q = crate::math::haar::quantize_tree(&t).expect("a 32² tree fits");
        let back = crate::math::haar::dequantize_tree(32, c, &q);
        let mut sum = 0.0;
        for y in 0..32 {
            for x in 0..32 {
                let (v, f) = (back.eval(x, y), t.eval(x, y));
                assert!((v - f).abs() <= 0.03, "({x}, {y}): {v} vs {f}");
                assert!((v - 0.5).abs() < 0.25, "({x}, {y}): {v}");
                sum += v;
            }
        }
        let mean = sum / 1024.0;
        assert!((mean - 0.5).abs() < 0.01, "quantized mean {mean}");
    }

    /// The exposure fit: samples on the top of a closed box (its inner side sees nothing)
    /// under an awning over half the sky. The top's outer side is all the viewer sees, and V̂
    /// towards the sky is already that side's visibility, so η ≈ 1 and the awning's shadow
    /// stays dark; E[v]²/E[v²] over the two sides gave 1/2 here, min(1, 2V̂): the shadow at
    /// twice its light. The whole sphere's 1/2 is in `sphere_aiv_is_one_half`.
    #[test]
    fn a_partly_shaded_wall_keeps_its_shadow() {
        let mut mesh = shapes::cuboid(Vec3::ZERO, Vec3::new(1.0, 1.0, 0.5), 1);
        mesh.append(&shapes::quad(
            Vec3::new(0.0, -50.0, 1.5),
            Vec3::new(50.0, 0.0, 0.0),
            Vec3::new(0.0, 100.0, 0.0),
            1,
        ));
        let scene =
            SceneData::single(mesh, MaterialData::new("white", [1.0; 3], 0.0, 1.0)).to_scene();
        let accel = Accel::build(&scene);
        let samples: Vec<PointSample> = (0..64)
            .map(|i| {
                let u = sobol_2d(i, 5);
                PointSample {
                    position: Vec3::new(u.x - 0.5, u.y - 0.5, 0.5),
                    geometric_normal: Vec3::Z,
                    surface: SurfaceSample {
                        normal: Vec3::Z,
                        params: SurfaceParams::lambertian(Vec3::ONE),
                        weight: 1.0 / 64.0,
                    },
                }
            })
            .collect();
        let est = aiv_map(&accel, &samples, 32, 32, 0, true, 7);
        // 1 or the next step of the fit's grid, 2^(−1/4) (measured: 0.84).
        assert!(est.exposure >= 0.8, "exposure {}", est.exposure);
        // Towards the open sky the top sees out, under the awning it does not.
        let at = |d: Vec3| est.map[grid_cell(equal_area_sphere_to_square(d), 32) as usize];
        assert!(at(Vec3::new(-0.6, 0.0, 0.8)) > 0.9);
        assert!(at(Vec3::new(0.6, 0.0, 0.8)) < 0.1);
    }

    /// Projected-area weighting: for any convex solid, ∫⟨n·ω⟩dA = ∫⟨−n·ω⟩dA, so V̂ is exactly
    /// 1/2 in every direction and V̂·|A|·E|n·ω| is the silhouette's area. A regular tetrahedron
    /// tells the two weightings apart: towards a face's normal only that face (a quarter of the
    /// area) sees out, so Eq. 25's equal weights give 1/4 there.
    #[test]
    fn convex_solid_aiv_is_one_half_projected() {
        let v = [
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(1.0, -1.0, -1.0),
            Vec3::new(-1.0, 1.0, -1.0),
            Vec3::new(-1.0, -1.0, 1.0),
        ]
        .map(|p| p * 0.4);
        let mut mesh = crate::gen::glb::MeshData::default();
        let mut faces = Vec::new();
        for f in [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]] {
            let [mut a, mut b, c] = f.map(|k| v[k]);
            let mut n = (b - a).cross(c - a).normalize();
            if n.dot(a + b + c) < 0.0 {
                std::mem::swap(&mut a, &mut b);
                n = -n;
            }
            let base = mesh.positions.len() as u32;
            for p in [a, b, c] {
                mesh.positions.push(p);
                mesh.normals.push(n);
                mesh.uvs.push(glam::Vec2::ZERO);
            }
            mesh.indices.extend([base, base + 1, base + 2]);
            faces.push(([a, b, c], n));
        }
        let scene =
            SceneData::single(mesh, MaterialData::new("white", [1.0; 3], 0.0, 1.0)).to_scene();
        let accel = Accel::build(&scene);
        // Equal-area faces: the same number of uniform samples on each.
        let per_face = 1024u32;
        let mut samples = Vec::new();
        for (fi, ([a, b, c], n)) in faces.iter().enumerate() {
            for i in 0..per_face {
                let u = sobol_2d(i, 11 + fi as u32);
                let (su, sv) = if u.x + u.y > 1.0 {
                    (1.0 - u.x, 1.0 - u.y)
                } else {
                    (u.x, u.y)
                };
                samples.push(PointSample {
                    position: *a + (*b - *a) * su + (*c - *a) * sv,
                    geometric_normal: *n,
                    surface: SurfaceSample {
                        normal: *n,
                        params: SurfaceParams::lambertian(Vec3::ONE),
                        weight: 1.0 / (4 * per_face) as f32,
                    },
                });
            }
        }
        let res = 16;
        let map = aiv_map(&accel, &samples, res, 64, 1, false, 5).map;
        // ~1000 rays per cell: every cell is 1/2 up to Monte Carlo noise.
        for (i, m) in map.iter().enumerate() {
            assert!((m - 0.5).abs() < 0.12, "cell {i}: {m}");
        }
        for (_, n) in &faces {
            let cell = grid_cell(
                crate::math::sphere_maps::equal_area_sphere_to_square(*n),
                res,
            ) as usize;
            assert!((map[cell] - 0.5).abs() < 0.08, "towards {n}: {}", map[cell]);
        }
    }

    /// 256 rays over a 32² map, one per cell of a stratified 16² pattern (as a finest-level
    /// voxel traces them), with visibility `v(x, y, j)` for the ray of cell (x, y), j its index.
    fn synthetic(mut v: impl FnMut(u32, u32, u32) -> bool) -> Vec<AivRay> {
        (0..256u32)
            .map(|j| {
                let (x, y) = (2 * (j % 16) + (j / 16) % 2, 2 * (j / 16) + (j % 2));
                AivRay {
                    cell: y * 32 + x,
                    weight: 1.0,
                    seen: v(x, y, j),
                    fold: (j & 1) as u8,
                    side: 0,
                    escape: 1.0,
                }
            })
            .collect()
    }

    #[test]
    fn cross_validation_pools_noise_and_keeps_edges() {
        // Visibility 1/2 in every direction, drawn at random: the best estimate pools widely.
        let mut rng = crate::math::rng::Pcg32::new(3, 0);
        let noisy = synthetic(|_, _, _| rng.next_f32() < 0.5);
        assert!(cross_validated_bandwidth(&noisy, 32, 0.5).min_rays >= 8);
        // A sharp horizon (a solid's wall): pooling would blur it, the map stays fine (the
        // ray of the cell or its nearest neighbour's: 256 rays over 1024 cells).
        let edge = synthetic(|x, y, _| x + y < 32);
        let b = cross_validated_bandwidth(&edge, 32, 0.5);
        assert!(b.min_rays <= 2, "{b}");
        // ... and the horizon stays sharp: every cell more than three cells off the diagonal
        // keeps its side's value exactly (a cap of 2 rays, at a quarter of a ray a cell in
        // each fold, reaches across up to three), but near the square's corners (the −z pole,
        // where the four corners meet on the sphere and this synthetic step is no horizon).
        let map = estimate(&cell_sums(&edge, 32, None), &[b], 32, 0.5).remove(0);
        for (i, v) in map.iter().enumerate() {
            let (x, y) = (i as i32 % 32, i as i32 / 32);
            let off = x + y - 31;
            let corner = x.min(31 - x).max(y.min(31 - y)) < 4;
            if off.abs() > 3 && !corner {
                assert_eq!(*v, (off < 0) as u32 as f32, "cell ({x}, {y}) with {b}");
            }
        }
        // Everything visible: every candidate is exact, the first (one ray, a block) wins the
        // tie.
        assert_eq!(
            cross_validated_bandwidth(&synthetic(|_, _, _| true), 32, 1.0),
            AIV_BANDWIDTHS[0]
        );
    }

    /// A visibility that varies smoothly with direction (probability (1 + ω_z)/2 that a ray
    /// escapes, many voxels' worth of noise averaged out): at the same bandwidth the cap,
    /// centred on each direction, is closer to the truth than the block, which has it anywhere
    /// inside; and cross-validation prefers the caps.
    #[test]
    fn caps_are_centred_where_blocks_are_not() {
        let truth = |cell: u32| {
            let (x, y) = ((cell % 32) as f32 + 0.5, (cell / 32) as f32 + 0.5);
            0.5 * (1.0 + equal_area_square_to_sphere(Vec2::new(x, y) / 32.0).z)
        };
        let mut rng = crate::math::rng::Pcg32::new(5, 0);
        let (mut err_block, mut err_cap, mut cap_chosen) = (0f64, 0f64, 0);
        for _ in 0..40 {
            let rays = synthetic(|x, y, _| rng.next_f32() < truth(y * 32 + x));
            let all = cell_sums(&rays, 32, None);
            let bw = |cap| Bandwidth { min_rays: 16, cap };
            let maps = estimate(&all, &[bw(false), bw(true)], 32, 0.5);
            for c in 0..1024u32 {
                err_block += ((maps[0][c as usize] - truth(c)) as f64).powi(2);
                err_cap += ((maps[1][c as usize] - truth(c)) as f64).powi(2);
            }
            cap_chosen += cross_validated_bandwidth(&rays, 32, 0.5).cap as u32;
        }
        assert!(
            err_cap < 0.8 * err_block,
            "cap {err_cap}, block {err_block}"
        );
        assert!(cap_chosen >= 25, "caps chosen for {cap_chosen} of 40");
    }

    #[test]
    fn cross_validation_shrinks_noise_and_keeps_horizons() {
        // Noise around 1/2 everywhere: the shrinkage should remove it.
        let mut rng = crate::math::rng::Pcg32::new(3, 0);
        let noisy = synthetic(|_, _, _| rng.next_f32() < 0.5);
        assert!(
            cross_validated_denoise(&noisy, 32, &fold_maps(&noisy, 32, AIV_BANDWIDTHS[0], 0.5))
                >= 0.5
        );
        // A solid's horizon, noiseless: the universal threshold would erase its details.
        let edge = synthetic(|x, y, _| x + y < 32);
        assert!(
            cross_validated_denoise(&edge, 32, &fold_maps(&edge, 32, AIV_BANDWIDTHS[0], 0.5)) < 1.0
        );
        // Everything visible: nothing to shrink, the weakest wins the tie.
        let all = synthetic(|_, _, _| true);
        assert_eq!(
            cross_validated_denoise(&all, 32, &fold_maps(&all, 32, AIV_BANDWIDTHS[0], 1.0)),
            0.0
        );
    }
}
