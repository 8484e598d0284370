//! Rate control: the user names the bytes (of the file or of its finest level) or the error,
//! and the bake spends the visibility wavelets' coefficients where the picture needs them.
//!
//! A bake with a target keeps, per visibility map, every Haar detail that survives the noise
//! shrinkage (the candidates), holds the levels until all are baked, and then keeps a detail
//! c of map m where its weighted energy w_m·c² reaches one Lagrange multiplier λ, chosen for
//! the whole file: the post-compression rate-distortion optimisation of JPEG 2000's code
//! blocks (Taubman 2000), applied to the AIV (Eq. 25) and ABV (Eq. 26) trees. The Haar basis
//! is orthonormal, so w_m·c² is exactly what dropping c adds to w_m times the map's summed
//! squared error, and every candidate costs about the same bytes (a node's detail, or a node):
//! keeping the details of largest w·c² first is the greedy solution of the rate-constrained
//! problem, and λ is searched until the bytes meet the budget.
//!
//! A voxel's directional material moments (Eq. 23) are one more candidate, of many details'
//! bytes: dropped, they become their mean ([`moment_candidate`]); it is kept where its
//! distortion per detail's bytes reaches λ, the greedy rule for candidates of unequal rates.
//!
//! The weight is what a map's error does to radiance, per unit of the level's surface:
//! - a voxel's AIV plays two parts. Towards the lights it scales the light its surfaces
//!   reflect (Eq. 25), an error weighing ρ²; towards the viewer it is also the voxel's share
//!   of a cone (Eq. 30), which decides how much of what lies behind shows through, whatever
//!   the albedo, an error weighing the contrast between the voxel and what is behind it
//!   ([`SHARE_CONTRAST`]). So w = a·(ρ² + C²) / (A·N²), with a the voxel's surface area
//!   after cut-outs, ρ its mean albedo (diffuse and specular, Eq. 13 and 17), C the
//!   contrast, N² the map's cells (the squared error per cell is the energy over N²);
//! - a boundary face's ABV scales the light that passes through it from behind; the faces
//!   are mostly the asset's outer shell, so that light is the environment's, taken as unit
//!   radiance: w = s² / (A·N²) with s the voxel's side. Measured on the maple's 64³ bake
//!   (64², 256 spp, against 4,096 spp; `aggtool rate` from one bake of every candidate):
//!   weighting the faces by the level's mean ρ² instead (the light the rest of the asset
//!   reflects) gave RMSE 0.0260 against 0.0215 at 5 MiB, and 0.0227 against 0.0236 at
//!   8.7 MiB, where both are within 5% of the per-map truncation's 0.0228;
//! - A is the level's total of both areas, so each level's distortion is the weighted mean
//!   squared visibility error over its surfaces. Its square root is the level's error
//!   estimate, which `--error` bounds and every bake with a target reports.

use rayon::prelude::*;

use super::BakeSettings;
use crate::absdf::{MaterialMoments, Moments};
use crate::format::encode::{self, ComponentBytes, Counts};
use crate::format::{compress_block, ALIGN};
use crate::format::{FaceData, VoxelData};
use crate::math::haar::SparseHaar;

/// What a bake's bytes or error must meet (`convert --size-mib`, `--level-mib`, `--error`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case", tag = "kind", content = "value")]
pub enum RateTarget {
    /// The whole file, in bytes.
    FileBytes(u64),
    /// The finest level's blocks, in bytes.
    LevelBytes(u64),
    /// The largest level error estimate (RMS visibility error, [`LevelWeights`]).
    Error(f64),
}

impl RateTarget {
    /// The target the settings name, if any (at most one does: [`BakeSettings::validate`]).
    pub fn of(s: &BakeSettings) -> Option<RateTarget> {
        let mib = |m: f64| (m * 1024.0 * 1024.0).round() as u64;
        if s.size_mib > 0.0 {
            Some(RateTarget::FileBytes(mib(s.size_mib)))
        } else if s.level_mib > 0.0 {
            Some(RateTarget::LevelBytes(mib(s.level_mib)))
        } else if s.error > 0.0 {
            Some(RateTarget::Error(s.error))
        } else {
            None
        }
    }

    /// "a 4.00 MiB file", "a 2.00 MiB finest level", "an error of 0.02".
    pub fn describe(&self) -> String {
        match *self {
            RateTarget::FileBytes(b) => format!("a {} file", mib_text(b)),
            RateTarget::LevelBytes(b) => format!("a {} finest level", mib_text(b)),
            RateTarget::Error(e) => format!("an error estimate of at most {e}"),
        }
    }
}

fn mib_text(b: u64) -> String {
    format!("{:.2} MiB", b as f64 / (1024.0 * 1024.0))
}

/// A level's blocks, held until the multiplier is chosen.
#[derive(Default)]
pub(crate) struct PendingLevel {
    /// Voxel blocks, in file order.
    pub voxels: Vec<Vec<VoxelData>>,
    /// Face blocks, in file order.
    pub faces: Vec<Vec<FaceData>>,
    /// The level's voxel side (world units).
    pub voxel_size: f32,
}

/// The radiance contrast, in units of the environment's, that an error in a voxel's share of
/// a cone (Eq. 30, its AIV towards the viewer) makes: what lies behind a voxel shows through
/// where the share is too small, and is hidden where it is too large. Taken as the
/// environment's unit radiance, as the faces' light is.
///
/// Weighted by ρ² alone (at least 0.04, a dielectric's reflectance at normal incidence), the
/// allocation took the AIV for the light the voxel reflects only: on the dark-leaved maple
/// (64³, one level's allocation at the per-map truncation's estimated error) it dropped
/// nearly every AIV detail (3.18 MB of AIV nodes to 0.13 MB) and the RMSE rose 13%, where
/// with the contrast it keeps 0.86× the bytes at 0.7% less RMSE; at equal bytes from one
/// bake of every candidate (`aggtool rate --size-mib`), 0.02208 against 0.02267 at 4.9 MB
/// and 0.02316 against 0.02494 at 3.6 MB; on the chandelier (metal, bright) 0.01085 against
/// 0.01094. The 40 shared assets' default files re-spent to 0.65 and 0.5 of their bytes:
/// median RMSE over the reference's at equal spp 3.01 → 2.97 and 4.69 → 4.14; the fence
/// and the barrel are 7–17% worse, as if what lies behind them showed less than a unit
/// contrast assumes (`docs/src/studies/2026-12-07-rate-control-tables.md`). It also keeps
/// a black material's maps (ρ = 0) weighing something: with weights of 0 a block had no
/// error to spend and kept every candidate.
pub const SHARE_CONTRAST: f64 = 1.0;

/// The mean albedo of a voxel's materials: diffuse plus specular reflectance (Eq. 13, 17),
/// averaged over colour channels and, for directional moments, over the grid's cells.
fn albedo(m: &Moments) -> f64 {
    let one = |m: &MaterialMoments| ((m.diffuse() + m.reflectance()).element_sum() / 3.0) as f64;
    match m {
        Moments::Constant(m) => one(m),
        Moments::Directional { diffuse, .. } => {
            diffuse.iter().map(one).sum::<f64>() / diffuse.len().max(1) as f64
        }
    }
}

/// The weights w of a level's maps ([module docs](self)): `voxels[b][i]` of voxel `i` of
/// voxel block `b`, `face` of every face.
#[derive(Clone, Debug)]
pub struct LevelWeights {
    /// Per voxel block, per voxel.
    pub voxels: Vec<Vec<f64>>,
    /// Every face's (one side s, one map resolution).
    pub face: f64,
    /// Per voxel block, per voxel: the weight of an error in its material moments, a / A
    /// times its mean interior visibility squared ([`moment_candidate`]).
    pub moments: Vec<Vec<f64>>,
}

impl LevelWeights {
    fn of(level: &PendingLevel) -> LevelWeights {
        let (flat, face) = map_weights(
            level.voxels.iter().flatten(),
            level.faces.iter().flatten(),
            level.voxel_size,
        );
        let mut flat = flat.into_iter();
        let faces: usize = level.faces.iter().map(Vec::len).sum();
        let total = level
            .voxels
            .iter()
            .flatten()
            .map(|v| surface(v))
            .sum::<f64>()
            + faces as f64 * (level.voxel_size as f64).powi(2);
        let norm = if total > 0.0 && total.is_finite() {
            1.0 / total
        } else {
            0.0
        };
        LevelWeights {
            voxels: level
                .voxels
                .iter()
                .map(|b| flat.by_ref().take(b.len()).collect())
                .collect(),
            face,
            moments: level
                .voxels
                .iter()
                .map(|b| {
                    b.iter()
                        .map(|v| {
                            let mean =
                                (v.aiv.scaling as f64 / v.aiv.n.max(1) as f64).clamp(0.0, 1.0);
                            surface(v) * norm * mean * mean
                        })
                        .collect()
                })
                .collect(),
        }
    }
}

/// A voxel's surface area after cut-outs.
fn surface(v: &VoxelData) -> f64 {
    (v.area * v.coverage.clamp(0.0, 1.0) as f64).max(0.0)
}

/// Bytes a candidate detail costs, for comparing other candidates with details: a quantized
/// Haar node holds three details in five bytes.
pub const DETAIL_BYTES: f64 = 5.0 / 3.0;

/// A voxel's directional material moments (Eq. 23) as a candidate: the constant moments
/// that would replace them (the mean of the diffuse kernel's cells), what that costs the
/// picture (weight `w` times the mean over both kernels' cells of the squared change of the
/// albedo, diffuse plus specular, per colour channel), and the bytes it saves in detail
/// units ([`DETAIL_BYTES`]). `None` for constant moments. On the maple's default 64³ bake
/// the directional moments are 13% of the file and `--moment-res 1` changed the RMSE of
/// neither the 64² nor the 256² view (0.022519 against 0.022517; 0.062686 against 0.062682).
pub fn moment_candidate(v: &VoxelData, w: f64) -> Option<(MaterialMoments, f64, u16)> {
    let Moments::Directional {
        diffuse, specular, ..
    } = &v.appearance.moments
    else {
        return None;
    };
    if diffuse.is_empty() {
        return None;
    }
    let flat = MaterialMoments::mean(diffuse);
    let rho = |m: &MaterialMoments| m.diffuse() + m.reflectance();
    let r0 = rho(&flat);
    let cells = diffuse.iter().chain(specular);
    let count = (diffuse.len() + specular.len()) as f64;
    let d = cells
        .map(|m| {
            let e = rho(m) - r0;
            (e.dot(e) / 3.0) as f64
        })
        .sum::<f64>()
        / count;
    let metal = diffuse
        .iter()
        .chain(specular)
        .any(|m| m.m > 0.0 || m.mc != glam::Vec3::ZERO);
    let set = if metal { 22.0 } else { 10.0 };
    let units = ((count - 1.0) * set / DETAIL_BYTES)
        .round()
        .clamp(1.0, u16::MAX as f64) as u16;
    Some((flat, w * d, units))
}

/// The weights w of a level's maps ([module docs](self)): one per voxel, in order, and the
/// one every boundary face shares (voxels of side `voxel_size`).
pub fn map_weights<'a>(
    voxels: impl Iterator<Item = &'a VoxelData> + Clone,
    faces: impl Iterator<Item = &'a FaceData> + Clone,
    voxel_size: f32,
) -> (Vec<f64>, f64) {
    let raw_voxel = |v: &VoxelData| {
        let cells = (v.aiv.n as f64).powi(2).max(1.0);
        let rho = albedo(&v.appearance.moments).clamp(0.0, 1.0);
        let a = surface(v);
        (a * (rho * rho + SHARE_CONTRAST * SHARE_CONTRAST) / cells, a)
    };
    let s2 = (voxel_size as f64).powi(2);
    let face_count = faces.clone().count();
    let face_cells = faces
        .clone()
        .next()
        .map_or(1.0, |f| (f.abv.n as f64).powi(2).max(1.0));
    let area = voxels.clone().map(|v| raw_voxel(v).1).sum::<f64>();
    let total = area + face_count as f64 * s2;
    let norm = if total > 0.0 && total.is_finite() {
        1.0 / total
    } else {
        0.0
    };
    (
        voxels.map(|v| raw_voxel(v).0 * norm).collect(),
        s2 / face_cells * norm,
    )
}

/// A candidate detail's weighted energy w·c²: it is kept when this reaches λ.
#[inline]
fn importance(w: f64, c: f32) -> f32 {
    (w * (c as f64) * (c as f64)) as f32
}

/// Where the candidates, ordered by decreasing importance, are cut: a detail is kept when its
/// importance exceeds λ, or equals it and the detail comes no later than `ord` in the bake's
/// order of details (level, voxel blocks then face blocks, map, preorder). Quantized
/// details take few distinct values, so a level's boundary faces (which share one weight)
/// tie by the thousand: the order splits a tie, so that every count of details is reachable.
#[derive(Clone, Copy, Debug)]
struct Cut {
    lambda: f32,
    ord: u64,
}

impl Cut {
    const NONE: Cut = Cut {
        lambda: f32::INFINITY,
        ord: 0,
    };

    #[inline]
    fn keeps(&self, importance: f32, ord: u64) -> bool {
        importance > self.lambda || (importance == self.lambda && ord <= self.ord)
    }
}

/// The tree with the details `cut` keeps; `ord` is the ordinal of its first candidate.
fn truncated(tree: &SparseHaar, w: f64, cut: Cut, ord: u64) -> SparseHaar {
    let next = std::cell::Cell::new(ord);
    tree.retain(|c, _| {
        let o = next.get();
        next.set(o + 1);
        cut.keeps(importance(w, c), o)
    })
}

/// What the rate control chose and met, for the report.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RateReport {
    /// The target.
    pub target: RateTarget,
    /// The multiplier chosen (a detail is kept where w·c² ≥ λ).
    pub lambda: f64,
    /// Whether the target was met (a size within 3% under the budget, or the error at most
    /// its bound); when not, the message says why.
    pub met: bool,
    /// Why the target was not met (empty when it was).
    pub message: String,
    /// The bytes the target counts (file or finest level) after the final encoding; 0 for an
    /// error target.
    pub bytes: u64,
    /// The bytes the search counted for the file (its final encoding plus the header and
    /// index), before the file was written.
    pub bytes_predicted: u64,
    /// Each level's error estimate, finest first (RMS visibility error, [`LevelWeights`]).
    pub level_errors: Vec<f64>,
    /// Candidate details (surviving the noise shrinkage) and those kept.
    pub candidates: u64,
    /// Details kept.
    pub kept: u64,
    /// Trial encodings of the search.
    pub trials: u32,
}

impl RateReport {
    /// Records the written file's size where the target counts it (the search predicted it):
    /// a file budget is met within [`TOLERANCE`] under it, or under it with every candidate
    /// kept.
    pub(crate) fn settle(&mut self, file_bytes: u64) {
        if let RateTarget::FileBytes(budget) = self.target {
            self.bytes_predicted = self.bytes;
            self.bytes = file_bytes;
            let under = file_bytes <= budget;
            let close = file_bytes as f64 >= (1.0 - TOLERANCE) * budget as f64;
            let met = under && (close || self.kept == self.candidates);
            if self.met && !met {
                self.message = format!(
                    "the file came out at {} bytes where the search counted {}",
                    file_bytes, self.bytes_predicted
                );
            }
            self.met = met;
        }
    }

    /// The report's line: "rate: met a 4.00 MiB file (3.93 MiB) at λ = 1.2e-9, kept 31% of
    /// 2.1 M candidate details, error estimate ≤ 0.021 (5 trial encodings)".
    pub fn line(&self) -> String {
        let worst = self.level_errors.iter().cloned().fold(0.0, f64::max);
        let got = match self.target {
            RateTarget::Error(_) => String::new(),
            _ => format!(" ({})", mib_text(self.bytes)),
        };
        let share = 100.0 * self.kept as f64 / self.candidates.max(1) as f64;
        let head = if self.met {
            format!("met {}{got}", self.target.describe())
        } else {
            format!(
                "did not meet {}{got}: {}",
                self.target.describe(),
                self.message
            )
        };
        format!(
            "{head} at λ = {:.3e}; kept {share:.0}% of {} candidates (visibility details and directional moments); error estimate at most {worst:.4} ({} trial encodings)",
            self.lambda, self.candidates, self.trials
        )
    }
}

/// One encoded block as the file stores it.
pub(crate) struct StoredBlock {
    /// The blob (compressed where that is smaller).
    pub blob: Vec<u8>,
    /// First and last key.
    pub keys: (u64, u64),
    /// Records.
    pub count: usize,
}

/// A level encoded at one λ.
pub(crate) struct EncodedLevel {
    pub voxel_blocks: Vec<StoredBlock>,
    pub face_blocks: Vec<StoredBlock>,
    pub counts: Counts,
    pub components: ComponentBytes,
}

impl EncodedLevel {
    /// Bytes in the file, with the alignment padding before each blob.
    fn bytes(&self) -> u64 {
        self.voxel_blocks
            .iter()
            .chain(&self.face_blocks)
            .map(|b| (b.blob.len() as u64).div_ceil(ALIGN) * ALIGN)
            .sum()
    }
}

/// A block's FlatBuffer (keys `keys`, `count` records) as stored at a Zstandard level.
fn stored(block: Vec<u8>, keys: (u64, u64), count: usize, level: i32) -> StoredBlock {
    let blob = match level {
        0 => block,
        _ => compress_block(&block, level).unwrap_or(block),
    };
    StoredBlock { blob, keys, count }
}

/// A voxel block with the candidates `cut` keeps (map weights `w`, moment weights `wm`, the
/// block's first ordinal `base`).
fn cut_voxels(block: &[VoxelData], w: &[f64], wm: &[f64], base: u64, cut: Cut) -> Vec<VoxelData> {
    let mut ord = base;
    block
        .iter()
        .zip(w)
        .zip(wm)
        .map(|((v, &w), &wm)| {
            let aiv = truncated(&v.aiv, w, cut, ord);
            ord += v.aiv.details().count() as u64;
            let mut out = VoxelData { aiv, ..v.clone() };
            if let Some((flat, d, units)) = moment_candidate(v, wm) {
                if !cut.keeps(moment_importance(d, units), ord) {
                    out.appearance.moments = Moments::Constant(flat);
                }
                ord += 1;
            }
            out
        })
        .collect()
}

/// A face block with the details `cut` keeps (the faces' weight `w`).
fn cut_faces(block: &[FaceData], w: f64, base: u64, cut: Cut) -> Vec<FaceData> {
    let mut ord = base;
    block
        .iter()
        .map(|f| {
            let abv = truncated(&f.abv, w, cut, ord);
            ord += f.abv.details().count() as u64;
            FaceData { face: f.face, abv }
        })
        .collect()
}

/// The squared-detail energy that the per-map truncation (`keep`, `energy`:
/// [`crate::math::haar::truncate`]) would drop from a candidate tree.
fn truncation_loss(tree: &SparseHaar, keep: f32, energy: f32) -> f64 {
    let n2 = (tree.n as usize).pow(2);
    let mut d = vec![[0f32; 3]; n2.saturating_sub(1) / 3];
    for (i, c) in tree.details().enumerate() {
        if let Some(slot) = d.get_mut(i / 3) {
            slot[i % 3] = c;
        }
    }
    let energy_of = |d: &[[f32; 3]]| d.iter().flatten().map(|&c| (c as f64).powi(2)).sum::<f64>();
    let before = energy_of(&d);
    crate::math::haar::truncate(tree.scaling, &mut d, keep, energy);
    (before - energy_of(&d)).max(0.0)
}

/// One block's rate allocation at the per-map truncation's error (`convert
/// --block-allocation`): the block's candidates (every detail that survived the noise
/// shrinkage, and the voxels' directional moments) are kept by decreasing importance, as the
/// rate control keeps them ([`allocate`]), until what is dropped reaches the weighted squared
/// error that truncating each map to `keep` / `energy` would have dropped. The same estimated
/// error, in the fewest candidates: details move from maps whose small details the per-map
/// rule keeps (flat maps, dark or small voxels) to maps where they weigh more, and directional
/// moments that change the albedo less than a detail's worth go. Within one block, so that
/// the bake still streams block by block, shards included, and the bytes do not depend on
/// threads. A block holds voxels or faces (the other list empty).
pub(crate) fn equal_error_block(
    voxels: Vec<VoxelData>,
    faces: Vec<FaceData>,
    voxel_size: f32,
    keep: f32,
    energy: f32,
) -> (Vec<VoxelData>, Vec<FaceData>) {
    let level = PendingLevel {
        voxels: vec![voxels],
        faces: vec![faces],
        voxel_size,
    };
    let mut out = equal_error(level, keep, energy);
    (
        out.voxels.pop().unwrap_or_default(),
        out.faces.pop().unwrap_or_default(),
    )
}

/// `level`'s blocks with the candidates kept that drop at most the weighted squared error of
/// the per-map truncation ([`equal_error_block`]); one multiplier for all of them.
fn equal_error(level: PendingLevel, keep: f32, energy: f32) -> PendingLevel {
    let weights = LevelWeights::of(&level);
    let voxels: f64 = (level.voxels.iter().flatten())
        .zip(weights.voxels.iter().flatten())
        .map(|(v, &w)| w * truncation_loss(&v.aiv, keep, energy))
        .sum();
    let faces: f64 = (level.faces.iter().flatten())
        .map(|f| weights.face * truncation_loss(&f.abv, keep, energy))
        .sum();
    let (mut imp, bases) = candidates(std::slice::from_ref(&level), std::slice::from_ref(&weights));
    imp.sort_unstable_by(|a, b| {
        b.importance
            .total_cmp(&a.importance)
            .then(a.ord.cmp(&b.ord))
    });
    // The least important go first, while what they drop stays within the budget; nothing
    // to spend (`--keep 1 --energy 1`) keeps every candidate, as the per-map rule does.
    let budget = voxels + faces;
    let (mut dropped, mut k) = (0f64, imp.len());
    while k > 0 && budget > 0.0 {
        let x = imp[k - 1].distortion();
        if dropped + x > budget {
            break;
        }
        dropped += x;
        k -= 1;
    }
    let cut = match k {
        0 => Cut::NONE,
        _ => Cut {
            lambda: imp[k - 1].importance,
            ord: imp[k - 1].ord,
        },
    };
    let b = &bases[0];
    PendingLevel {
        voxels: (level
            .voxels
            .iter()
            .zip(&weights.voxels)
            .zip(&weights.moments))
        .zip(&b.voxels)
        .map(|(((block, w), wm), &base)| cut_voxels(block, w, wm, base, cut))
        .collect(),
        faces: (level.faces.iter().zip(&b.faces))
            .map(|(block, &base)| cut_faces(block, weights.face, base, cut))
            .collect(),
        voxel_size: level.voxel_size,
    }
}

/// Level `li` encoded with the details `cut` keeps, compressed at `zstd` (blocks in
/// parallel; the result does not depend on the thread count). `bases` are the ordinals of
/// the blocks' first candidates.
#[allow(clippy::too_many_arguments)]
fn encode_level(
    li: usize,
    level: &PendingLevel,
    weights: &LevelWeights,
    bases: &BlockBases,
    cut_at: Cut,
    settings: &BakeSettings,
    zstd: i32,
) -> EncodedLevel {
    let voxel: Vec<(StoredBlock, Counts, ComponentBytes)> = level
        .voxels
        .par_iter()
        .zip(&weights.voxels)
        .zip(&weights.moments)
        .zip(&bases.voxels)
        .map(|(((block, w), wm), &base)| {
            let cut = cut_voxels(block, w, wm, base, cut_at);
            let (mut c, mut b) = (Counts::default(), ComponentBytes::default());
            let blob = encode::voxel_block(
                li as u32,
                &cut,
                settings.keep_all_effects,
                settings.lossless,
                &mut c,
                &mut b,
            );
            let keys = (cut[0].key, cut[cut.len() - 1].key);
            (stored(blob, keys, cut.len(), zstd), c, b)
        })
        .collect();
    let face: Vec<(StoredBlock, Counts, ComponentBytes)> = level
        .faces
        .par_iter()
        .zip(&bases.faces)
        .map(|(block, &base)| {
            let cut = cut_faces(block, weights.face, base, cut_at);
            let (mut c, mut b) = (Counts::default(), ComponentBytes::default());
            let blob = encode::face_block(li as u32, &cut, settings.lossless, &mut c, &mut b);
            let keys = (
                encode::face_key(&cut[0]),
                encode::face_key(&cut[cut.len() - 1]),
            );
            (stored(blob, keys, cut.len(), zstd), c, b)
        })
        .collect();
    let mut out = EncodedLevel {
        voxel_blocks: Vec::with_capacity(voxel.len()),
        face_blocks: Vec::with_capacity(face.len()),
        counts: Counts::default(),
        components: ComponentBytes::default(),
    };
    for (s, c, b) in voxel {
        out.counts.add(&c);
        out.components.add(&b);
        out.voxel_blocks.push(s);
    }
    for (s, c, b) in face {
        out.counts.add(&c);
        out.components.add(&b);
        out.face_blocks.push(s);
    }
    out
}

/// The ordinal of the first candidate detail of each block of a level.
#[derive(Default)]
struct BlockBases {
    voxels: Vec<u64>,
    faces: Vec<u64>,
}

/// A candidate: its importance (distortion per detail's bytes), the detail-equivalents it
/// costs (1 for a detail), level and ordinal ([`Cut`]).
#[derive(Clone, Copy)]
struct Candidate {
    importance: f32,
    level: u16,
    units: u16,
    ord: u64,
}

impl Candidate {
    /// What dropping it adds to its level's squared error.
    fn distortion(&self) -> f64 {
        self.importance as f64 * self.units as f64
    }
}

/// The importance of a moment candidate (its distortion per detail unit).
fn moment_importance(distortion: f64, units: u16) -> f32 {
    (distortion / units as f64) as f32
}

/// Every candidate detail, in the bake's order, and each block's first ordinal.
fn candidates(
    levels: &[PendingLevel],
    weights: &[LevelWeights],
) -> (Vec<Candidate>, Vec<BlockBases>) {
    let mut out = Vec::new();
    let mut bases = Vec::with_capacity(levels.len());
    for (li, (level, w)) in levels.iter().zip(weights).enumerate() {
        let mut b = BlockBases::default();
        let push = |out: &mut Vec<Candidate>, w: f64, t: &SparseHaar| {
            for c in t.details() {
                let ord = out.len() as u64;
                out.push(Candidate {
                    importance: importance(w, c),
                    level: li as u16,
                    units: 1,
                    ord,
                });
            }
        };
        for ((block, wb), wm) in level.voxels.iter().zip(&w.voxels).zip(&w.moments) {
            b.voxels.push(out.len() as u64);
            for ((v, &w), &wm) in block.iter().zip(wb).zip(wm) {
                push(&mut out, w, &v.aiv);
                if let Some((_, d, units)) = moment_candidate(v, wm) {
                    let ord = out.len() as u64;
                    out.push(Candidate {
                        importance: moment_importance(d, units),
                        level: li as u16,
                        units,
                        ord,
                    });
                }
            }
        }
        for block in &level.faces {
            b.faces.push(out.len() as u64);
            for f in block {
                push(&mut out, w.face, &f.abv);
            }
        }
        bases.push(b);
    }
    (out, bases)
}

/// Each level's error estimate when only the first `k` of the ordered candidates are kept.
fn level_errors(ordered: &[Candidate], levels: usize, k: usize) -> Vec<f64> {
    let mut d = vec![0f64; levels];
    for c in &ordered[k..] {
        d[c.level as usize] += c.distortion();
    }
    d.into_iter().map(f64::sqrt).collect()
}

/// The Zstandard level of the search's trial encodings: fast, with the final level's bytes
/// predicted from it by a ratio measured on the final encodings.
const TRIAL_ZSTD: i32 = 3;
/// A size target is met when the bytes land in [1 − TOLERANCE, 1] × the budget.
pub const TOLERANCE: f64 = 0.03;

/// Chooses λ for `target` over the held levels and encodes them at it, at the settings'
/// compression. `fixed` gives the file's bytes outside the levels' blocks (header, index)
/// for the levels' counts (FlatBuffers leaves a zero count out of the index).
pub(crate) fn allocate(
    levels: &[PendingLevel],
    settings: &BakeSettings,
    target: RateTarget,
    fixed: &dyn Fn(&[Counts]) -> u64,
) -> (Vec<EncodedLevel>, RateReport) {
    let weights: Vec<LevelWeights> = levels.iter().map(LevelWeights::of).collect();
    let (mut imp, bases) = candidates(levels, &weights);
    let candidates = imp.len() as u64;
    // Descending importance; ties in the bake's order.
    imp.par_sort_unstable_by(|a, b| {
        b.importance
            .total_cmp(&a.importance)
            .then(a.ord.cmp(&b.ord))
    });
    let cut_at = |k: usize| {
        if k == 0 {
            Cut::NONE
        } else {
            Cut {
                lambda: imp[k - 1].importance,
                ord: imp[k - 1].ord,
            }
        }
    };
    let encode_all = |k: usize, zstd: i32| -> Vec<EncodedLevel> {
        levels
            .iter()
            .zip(&weights)
            .zip(&bases)
            .enumerate()
            .map(|(li, ((l, w), b))| encode_level(li, l, w, b, cut_at(k), settings, zstd))
            .collect()
    };
    let counted = |enc: &[EncodedLevel]| -> u64 {
        match target {
            RateTarget::LevelBytes(_) => enc.first().map_or(0, EncodedLevel::bytes),
            _ => {
                let counts: Vec<Counts> = enc.iter().map(|e| e.counts).collect();
                fixed(&counts) + enc.iter().map(EncodedLevel::bytes).sum::<u64>()
            }
        }
    };
    let trials = std::cell::Cell::new(0u32);
    let report = |k: usize, met: bool, message: String, bytes: u64| RateReport {
        target,
        // Nothing kept: the smallest λ above every candidate (never infinite).
        lambda: match k {
            0 => imp
                .first()
                .map_or(0.0, |c| f32::from_bits(c.importance.to_bits() + 1) as f64),
            _ => cut_at(k).lambda as f64,
        },
        met,
        message,
        bytes,
        bytes_predicted: bytes,
        level_errors: level_errors(&imp, levels.len(), k),
        candidates,
        kept: k as u64,
        trials: trials.get(),
    };
    let budget = match target {
        RateTarget::Error(e) => {
            // The largest λ whose every level's error is within e: the dropped energy grows
            // as λ does, so walk the candidates from the least important up.
            let mut d = vec![0f64; levels.len()];
            let bound = e * e;
            let mut k = imp.len();
            while k > 0 {
                let c = imp[k - 1];
                let x = c.distortion();
                if d[c.level as usize] + x > bound {
                    break;
                }
                d[c.level as usize] += x;
                k -= 1;
            }
            let enc = encode_all(k, settings.compression);
            trials.set(1);
            let r = report(k, true, String::new(), 0);
            return (enc, r);
        }
        RateTarget::FileBytes(b) | RateTarget::LevelBytes(b) => b as f64,
    };
    let trial_zstd = if settings.compression > 0 {
        settings.compression.min(TRIAL_ZSTD)
    } else {
        0
    };
    let trial = |k: usize| {
        trials.set(trials.get() + 1);
        counted(&encode_all(k, trial_zstd)) as f64
    };
    // Bytes at both ends: nothing kept, every candidate kept.
    let (lo_bytes, hi_bytes) = (trial(0), trial(imp.len()));
    let mut best: Option<(usize, Vec<EncodedLevel>, u64)>;
    let finish = |k: usize| {
        trials.set(trials.get() + 1);
        let enc = encode_all(k, settings.compression);
        let b = counted(&enc);
        (enc, b)
    };
    // Everything fits, or nothing does: the ends are the answer.
    let mut ratio = {
        let (enc, b) = finish(imp.len());
        if b as f64 <= budget {
            let msg = if (b as f64) < (1.0 - TOLERANCE) * budget {
                format!(
                    "every candidate detail fits in {}; the file is smaller than the budget",
                    mib_text(b)
                )
            } else {
                String::new()
            };
            let r = report(imp.len(), true, msg, b);
            return (enc, r);
        }
        // Final bytes over trial bytes, measured here and after each round.
        b as f64 / hi_bytes.max(1.0)
    };
    {
        let (enc, b) = finish(0);
        if b as f64 > budget {
            let msg = format!(
                "without any visibility detail or directional moments the bake takes {}; lower --max-res, or raise the budget",
                mib_text(b)
            );
            let r = report(0, false, msg, b);
            return (enc, r);
        }
        best = Some((0, enc, b));
    }
    // Per round: a search on the trial bytes, scaled by the measured ratio of final to
    // trial bytes, for the largest count of details whose prediction lands in the upper
    // half of the tolerance band (interpolation steps alternating with bisection, so the
    // bracket always shrinks); then one final encoding checks the real bytes and corrects
    // the ratio. Trial bytes are remembered, so a later round repeats no encoding.
    let memo = std::cell::RefCell::new(std::collections::BTreeMap::new());
    memo.borrow_mut().insert(0usize, lo_bytes);
    memo.borrow_mut().insert(imp.len(), hi_bytes);
    let trial_at = |k: usize| {
        if let Some(&b) = memo.borrow().get(&k) {
            return b;
        }
        let b = trial(k);
        memo.borrow_mut().insert(k, b);
        b
    };
    let goal = (1.0 - TOLERANCE / 4.0) * budget;
    let near = (1.0 - 3.0 * TOLERANCE / 4.0) * budget;
    for _round in 0..4 {
        let (mut a, mut b) = (0usize, imp.len());
        let (mut fa, mut fb) = (trial_at(a) * ratio, trial_at(b) * ratio);
        let mut step = 0u32;
        while b - a > 1 && fa < near {
            step += 1;
            let m = if step % 2 == 1 && fb > fa {
                a + ((goal - fa) / (fb - fa) * (b - a) as f64) as usize
            } else {
                a + (b - a) / 2
            }
            .clamp(a + 1, b - 1);
            let fm = trial_at(m) * ratio;
            if fm <= goal {
                (a, fa) = (m, fm);
            } else {
                (b, fb) = (m, fm);
            }
        }
        let k = a;
        let (enc, bytes) = finish(k);
        let ok = bytes as f64 <= budget;
        if ok && best.as_ref().is_none_or(|x| bytes > x.2) {
            best = Some((k, enc, bytes));
        }
        if ok && bytes as f64 >= (1.0 - TOLERANCE) * budget {
            break;
        }
        ratio = bytes as f64 / trial_at(k).max(1.0);
    }
    let (k, enc, bytes) = best.expect("the empty allocation fits");
    let met = bytes as f64 >= (1.0 - TOLERANCE) * budget;
    let msg = if met {
        String::new()
    } else {
        format!(
            "the search stopped at {}, more than {:.0}% under the budget",
            mib_text(bytes),
            100.0 * TOLERANCE
        )
    };
    let r = report(k, met, msg, bytes);
    (enc, r)
}
