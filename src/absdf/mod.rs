//! The factorized Aggregated BSDF (paper §3–§5 and Fig. 3): the far-field appearance of all
//! surfaces inside a voxel, evaluated in closed form from the voxel's statistics, with
//! importance sampling (§7.3). Knows nothing of the bake that produces the statistics.
//!
//! Conventions. Surfaces are double-sided. The surface normal distribution is a mixture of
//! unit SGGX lobes (double-sided GGX, Eq. 8) with weights summing to one; the common scale of
//! the true distribution cancels between Eq. 7's numerator and its normalisation by the
//! projected area, which is therefore σ_N(ω_o) = Σ w_k σ_k(ω_o). The ABSDF includes both
//! foreshortening factors (Eq. 3): L_o(ω_o) = ∫ f̂(ω_i, ω_o) L_i(ω_i) dω_i, no extra cosine.
//!
//! ```text
//! f̂(ω_i, ω_o) = [ diffuse + specular ] / σ_N(ω_o)
//! diffuse  = (E[β^c] − E[β^m β^c]) / π · Σ_k w_k ∫⟨n·ω_i⟩⟨n·ω_o⟩ D_k(n) dn             Eq. 13
//!            (the lobe integral in closed form instead of Eq. 14's SG convolution: see
//!            `diffuse_numerator`)
//! specular = ¼ [(1 − F_c) E[R] + F_c E[W90]] · Σ_k Σ_j w_k m_j M5(α_j) s_kj
//!              · D_sggx(ω_h; R_k, α⁺_kj) · S_kj(ω_i, ω_o) · G_kj(ω_i, ω_o)              Eq. 15–22
//! ```
//!
//! with (c, μ, κ) the product of the two clamped-cosine SGs (Eq. 14), R = β^mβ^c + (1−β^m)β^s
//! and W90 = β^m + (1−β^m)·F90 (the KHR_materials_specular weight of F_c), (m_j, α_j) the two
//! microfacet lobes of the roughness beta (M2, Eq. 19), (α⁺, s) from M1/M3, S from the LTC lune
//! integral (M4, Eq. 21) read at the narrower of the pair's widths (`lune_alpha`), G the
//! height-correlated Smith term at the dominant normal (see `pair_g2` for why not Eq. 22's
//! convolved lobe), and the moments looked up at ω_h (Eq. 23).

pub mod cases;
pub mod estimate;

use std::f32::consts::FRAC_1_PI;

use glam::{Mat3, Vec2, Vec3};

use crate::math::beta::RoughnessDistribution;
use crate::math::microfacet::{ggx_lambda_iso, schlick_weight, ALPHA_MIN};
use crate::math::sg::COSINE_SHARPNESS;
use crate::math::sggx::{Sggx, SggxDensity};
use crate::math::sphere_maps::{equal_area_sphere_to_square, grid_cell};
use crate::math::{finite_or_zero, finite_vec_or_zero, unit_or_zero};
use crate::tables::ltc::LuneTable;
use crate::tables::Tables;

/// One lobe of the surface normal distribution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NdfLobe {
    /// Mixture weight: the lobe's share of the voxel's surface area (weights sum to one).
    pub weight: f32,
    /// Eigenbasis (columns: the two tangent axes, then the mean normal axis).
    pub frame: Mat3,
    /// (αx, αy), clamped to [ALPHA_MIN, 1].
    pub alpha: Vec2,
}

/// Means of the material quantities the factorization needs (Eq. 13, 17 and the F90 weight).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct MaterialMoments {
    /// E[β^c].
    pub c: Vec3,
    /// E[β^m β^c].
    pub mc: Vec3,
    /// E[β^s].
    pub s: f32,
    /// E[β^m β^s].
    pub ms: f32,
    /// E[β^m].
    pub m: f32,
    /// E\[F90\].
    pub f90: f32,
    /// E[β^m F90].
    pub mf90: f32,
}

impl MaterialMoments {
    /// Eq. 13: E[β^c] − E[β^m β^c].
    #[inline]
    pub fn diffuse(&self) -> Vec3 {
        (self.c - self.mc).max(Vec3::ZERO)
    }
    /// Eq. 17: E[β^m β^c] + E[β^s] − E[β^m β^s].
    #[inline]
    pub fn reflectance(&self) -> Vec3 {
        (self.mc + Vec3::splat(self.s - self.ms)).max(Vec3::ZERO)
    }
    /// The weight of F_c: E\[β^m\] + E\[F90\] − E\[β^m F90\] (1 in the paper).
    #[inline]
    pub fn grazing(&self) -> f32 {
        (self.m + self.f90 - self.mf90).max(0.0)
    }

    /// Weighted accumulation of one surface sample.
    pub fn add(&mut self, w: f32, c: Vec3, m: f32, s: f32, f90: f32) {
        self.c += w * c;
        self.mc += w * m * c;
        self.s += w * s;
        self.ms += w * m * s;
        self.m += w * m;
        self.f90 += w * f90;
        self.mf90 += w * m * f90;
    }

    /// The unweighted mean of several.
    pub fn mean(list: &[MaterialMoments]) -> Self {
        Self::mean_of(list.iter().copied(), list.len())
    }

    /// [`MaterialMoments::mean`] of the `len` sets `list` yields (no slice needed).
    fn mean_of(list: impl Iterator<Item = MaterialMoments>, len: usize) -> Self {
        let n = len.max(1) as f32;
        let mut a = MaterialMoments::default();
        for m in list {
            a.c += m.c / n;
            a.mc += m.mc / n;
            a.s += m.s / n;
            a.ms += m.ms / n;
            a.m += m.m / n;
            a.f90 += m.f90 / n;
            a.mf90 += m.mf90 / n;
        }
        a
    }

    /// Divides by the accumulated weight.
    pub fn normalized(&self, wsum: f32) -> Self {
        if !(wsum > 0.0) {
            return MaterialMoments::default();
        }
        let k = 1.0 / wsum;
        MaterialMoments {
            c: self.c * k,
            mc: self.mc * k,
            s: self.s * k,
            ms: self.ms * k,
            m: self.m * k,
            f90: self.f90 * k,
            mf90: self.mf90 * k,
        }
    }
}

/// Material moments, constant or directional (Eq. 23) on a `res × res` equal-area grid over
/// the sphere (Clarberg's map), one set for the diffuse and one for the specular kernel.
#[derive(Clone, Debug, PartialEq)]
pub enum Moments {
    /// The same moments in every direction.
    Constant(MaterialMoments),
    /// Moments looked up at ω_h on the equal-area grid (Eq. 23).
    Directional {
        /// Grid resolution: `res × res` cells over the sphere.
        res: u32,
        /// Moments of the diffuse kernel, one per cell.
        diffuse: Vec<MaterialMoments>,
        /// Moments of the specular kernel, one per cell.
        specular: Vec<MaterialMoments>,
    },
}

/// Eq. 23's moment table as an ABSDF holds it, looked up at ω_h.
///
/// A voxel's ABSDF is most of what the runtime's cache holds, and its directional moments
/// were most of the ABSDF: 2 × res² sets of eleven f32 (792 bytes at the default res = 3),
/// where a quantized file stores them as binary16 (five halves a set for a voxel without
/// metal, eleven with). The table keeps those halves (180 bytes) and decodes the two sets a
/// look-up reads; moments that binary16 does not hold exactly (an unquantized file, or the
/// bake's own estimates) stay f32, so every look-up returns the value it was given.
#[derive(Clone, Debug)]
enum MomentTable<'t> {
    /// The same moments in every direction.
    Constant(MaterialMoments),
    /// f32 sets: the `res²` diffuse cells, then the `res²` specular cells.
    Full {
        res: u32,
        sets: Box<[MaterialMoments]>,
    },
    /// binary16 sets in the same order, [`HALVES_DIELECTRIC`] or [`HALVES_METAL`] halves
    /// each.
    Half {
        res: u32,
        metal: bool,
        halves: Box<[u16]>,
    },
    /// The same, read in place where a quantized block stores them ([`MomentHalves`]).
    Borrowed(MomentHalves<'t>),
}

/// A voxel's directional moments as a quantized block (format 1.4) stores them: `2·res²`
/// binary16 sets, the diffuse cells then the specular cells, each c (3), s, f90 or, where
/// `metal`, c (3), mc (3), s, ms, m, f90, mf90: the layout of the ABSDF's own binary16 table,
/// so that [`Absdf::with_moment_halves`] reads them in place instead of holding a copy (a
/// third of a shaded voxel's ABSDF bytes, 180 B on the maple's 128³ level).
#[derive(Clone, Copy, Debug)]
pub struct MomentHalves<'a> {
    /// Cells per side of each of the two direction maps.
    pub res: u32,
    /// Whether the sets hold the metal moments ([`HALVES_METAL`] halves each).
    pub metal: bool,
    /// The sets' binary16 bits.
    pub halves: &'a [u16],
}

impl MomentHalves<'_> {
    /// Whether the halves are the `2·res²` sets of their layout, each finite.
    pub fn is_valid(&self) -> bool {
        let stride = if self.metal {
            HALVES_METAL
        } else {
            HALVES_DIELECTRIC
        };
        self.res > 0
            && self.halves.len() == 2 * (self.res * self.res) as usize * stride
            && self
                .halves
                .iter()
                .all(|&h| half::f16::from_bits(h).is_finite())
    }
}

/// Halves of a set without metal: c (3), s, f90 (the metal moments are 0).
const HALVES_DIELECTRIC: usize = 5;
/// Halves of a set with metal: c (3), mc (3), s, ms, m, f90, mf90.
const HALVES_METAL: usize = 11;

impl MomentTable<'_> {
    fn new(m: &Moments) -> Self {
        let (res, sets): (u32, Vec<MaterialMoments>) = match m {
            Moments::Constant(c) => return MomentTable::Constant(*c),
            Moments::Directional {
                res,
                diffuse,
                specular,
            } => (*res, diffuse.iter().chain(specular).copied().collect()),
        };
        let metal = sets
            .iter()
            .any(|m| m.mc != Vec3::ZERO || m.ms != 0.0 || m.m != 0.0 || m.mf90 != 0.0);
        let mut halves = Vec::with_capacity(sets.len() * HALVES_METAL);
        for m in &sets {
            if metal {
                halves.extend_from_slice(&[m.c.x, m.c.y, m.c.z, m.mc.x, m.mc.y, m.mc.z]);
                halves.extend_from_slice(&[m.s, m.ms, m.m, m.f90, m.mf90]);
            } else {
                halves.extend_from_slice(&[m.c.x, m.c.y, m.c.z, m.s, m.f90]);
            }
        }
        let exact = halves
            .iter()
            .all(|&x| half::f16::from_f32(x).to_f32().to_bits() == x.to_bits());
        if !exact {
            return MomentTable::Full {
                res,
                sets: sets.into_boxed_slice(),
            };
        }
        MomentTable::Half {
            res,
            metal,
            halves: halves
                .iter()
                .map(|&x| half::f16::from_f32(x).to_bits())
                .collect(),
        }
    }

    /// The (diffuse, specular) sets of the cell holding `w`.
    #[inline]
    fn at(&self, w: Vec3) -> (MaterialMoments, MaterialMoments) {
        let cell = |res: u32| grid_cell(equal_area_sphere_to_square(w), res) as usize;
        match self {
            MomentTable::Constant(m) => (*m, *m),
            MomentTable::Full { res, sets } => {
                let (i, n) = (cell(*res), (*res * *res) as usize);
                (sets[i], sets[n + i])
            }
            MomentTable::Half { res, metal, halves } => {
                let (i, n) = (cell(*res), (*res * *res) as usize);
                (half_set(halves, *metal, i), half_set(halves, *metal, n + i))
            }
            MomentTable::Borrowed(h) => {
                let (i, n) = (cell(h.res), (h.res * h.res) as usize);
                (
                    half_set(h.halves, h.metal, i),
                    half_set(h.halves, h.metal, n + i),
                )
            }
        }
    }

    /// The means of the diffuse and of the specular sets over every direction, as
    /// [`MaterialMoments::mean`] of the sets the table was built from (the same bits: the
    /// binary16 tables hold them exactly).
    fn mean(&self) -> (MaterialMoments, MaterialMoments) {
        let halves_mean = |res: u32, metal: bool, halves: &[u16]| {
            let n = (res * res) as usize;
            // No allocation: an evaluation with ω_i = −ω_o is on a hot path, however rare.
            let set = |k| half_set(halves, metal, k);
            (
                MaterialMoments::mean_of((0..n).map(set), n),
                MaterialMoments::mean_of((n..2 * n).map(set), n),
            )
        };
        match self {
            MomentTable::Constant(m) => (*m, *m),
            MomentTable::Full { res, sets } => {
                let n = (*res * *res) as usize;
                (
                    MaterialMoments::mean(&sets[..n]),
                    MaterialMoments::mean(&sets[n..]),
                )
            }
            MomentTable::Half { res, metal, halves } => halves_mean(*res, *metal, halves),
            MomentTable::Borrowed(h) => halves_mean(h.res, h.metal, h.halves),
        }
    }

    fn memory_bytes(&self) -> usize {
        match self {
            MomentTable::Constant(_) => 0,
            MomentTable::Full { sets, .. } => std::mem::size_of_val(&**sets),
            MomentTable::Half { halves, .. } => std::mem::size_of_val(&**halves),
            MomentTable::Borrowed(_) => 0,
        }
    }
}

/// Set `k` of a binary16 moment table.
#[inline]
fn half_set(halves: &[u16], metal: bool, k: usize) -> MaterialMoments {
    let h = |j: usize| half::f16::from_bits(halves[j]).to_f32();
    if metal {
        let b = k * HALVES_METAL;
        MaterialMoments {
            c: Vec3::new(h(b), h(b + 1), h(b + 2)),
            mc: Vec3::new(h(b + 3), h(b + 4), h(b + 5)),
            s: h(b + 6),
            ms: h(b + 7),
            m: h(b + 8),
            f90: h(b + 9),
            mf90: h(b + 10),
        }
    } else {
        let b = k * HALVES_DIELECTRIC;
        MaterialMoments {
            c: Vec3::new(h(b), h(b + 1), h(b + 2)),
            s: h(b + 3),
            f90: h(b + 4),
            ..Default::default()
        }
    }
}

/// What the factorized ABSDF needs to know about a voxel.
#[derive(Clone, Debug, PartialEq)]
pub struct VoxelAppearance {
    /// Up to four lobes (Eq. 8).
    pub lobes: Vec<NdfLobe>,
    /// Mean of GGX α over the surfaces.
    pub roughness_mean: f32,
    /// Variance of α (with the mean, the roughness beta of Eq. 19 that table M2 splits into two lobes).
    pub roughness_variance: f32,
    /// The material moments E[·] of Eq. 13 and 15, constant or directional (Eq. 23).
    pub moments: Moments,
}

/// A convolved lobe ready for evaluation.
#[derive(Clone, Copy, Debug)]
struct SpecLobe {
    weight: f32,
    sggx: Sggx,
    density: SggxDensity,
    /// The macro lobe's index in [`Absdf`]'s lobes: its frame and roughness (for G).
    lobe: u32,
    /// Roughness of the microfacet lobe (for G).
    micro_alpha: f32,
    /// The lune table's roughness coordinate for S of Eq. 21, read at [`lune_alpha`].
    lune_coord: f32,
}

/// The roughness at which to read S (Eq. 21) for a (macro lobe, microfacet lobe) pair: per
/// axis the narrower of the two, min(α_j, α_k), the geometric mean of the two axes.
///
/// Eq. 21 takes the mass of the microfacet lobe alone inside the lune of normals that see both
/// directions. That is the limit of macro normals spread wider than α_j, where the product of
/// the two lobes (as a function of the macro normal n) is the microfacet lobe; in the other
/// limit, a flat voxel, every normal is the one normal, the Heaviside terms are exact at it (as
/// [`pair_g2`] applies them) and S must be 1. With S read at α_j, a flat rough dielectric
/// (α = 1, the glTF default) lost up to half of its grazing specular (0.51 of the base BSDF
/// towards ω_i at 80° from a view at 72°) and a flat α = 1 metal a quarter to a half of its
/// energy, and a flat pavement tile rendered 2–4% dark. The narrower lobe bounds the product's
/// width and is exact in both limits. Tried beside it, measured on the validation voxels
/// (`aggtool absdf-plot all`) and the quality study: the product's width
/// α_j·α_k/√(α_j² + α_k²) read a uniform sphere of α = 1 normals 0.71× too narrow (∫f̂ 1.063
/// of the ground truth, against 1.046 for Eq. 21 and 1.048 for this); the wider axis
/// min(α_j, max(α_x, α_y)) kept Eq. 21 on the anisotropic voxel (relative RMSE 0.103, against
/// 0.088 for this). A rough cylinder (α = 1 dielectric, normals on a circle) integrates to
/// 1.065–1.073 of the ground truth at three views, against 1.026–1.038 with Eq. 21's S; the
/// study's medians are the same for all three.
fn lune_alpha(macro_alpha: Vec2, micro_alpha: f32) -> f32 {
    (micro_alpha.min(macro_alpha.x) * micro_alpha.min(macro_alpha.y)).sqrt()
}

use crate::bsdf::{Bsdf, BsdfSample};

/// The factorized ABSDF of one voxel, with every ω-independent table lookup done once.
#[derive(Clone, Debug)]
pub struct Absdf<'t> {
    /// The tables (S of Eq. 21 is read from them at evaluation).
    tables: &'t Tables,
    /// The macro lobes, with what evaluation and diffuse sampling read of each.
    lobes: Box<[MacroLobe]>,
    spec: Box<[SpecLobe]>,
    /// The specular lobes' total weight (they are also the specular sampling mixture).
    spec_total: f32,
    /// The diffuse sampling lobes' total weight.
    diffuse_total: f32,
    /// Probability of sampling the specular component (from the moments' means).
    spec_probability: f32,
    moments: MomentTable<'t>,
}

/// A macro lobe (Eq. 8) with what evaluation and diffuse sampling read of it, in one array:
/// a shaded voxel's ABSDF is what the runtime's cache holds most of, and four arrays a voxel
/// (lobes, unit SGGX, diffuse terms, sampling lobes) were four allocations.
#[derive(Clone, Copy, Debug)]
struct MacroLobe {
    /// Weight, frame and roughness (the frame and roughness for G of the specular pairs).
    ndf: NdfLobe,
    /// The lobe's SGGX: σ(ω) of the projected area.
    unit: Sggx,
    /// For the diffuse term: 1 / mass and (mass/4)·E[n nᵀ] in world space.
    inv_mass: f32,
    second: Mat3,
    /// The diffuse sampling lobe at the fixed κ (§7.3) and its density.
    sampling: Sggx,
    sampling_density: SggxDensity,
}

/// A lobe of a sampling mixture: its weight, its SGGX and the SGGX's precomputed density. The
/// specular mixture samples the specular lobes themselves ([`SpecLobe`], not a copy of their
/// three fields: a voxel's ABSDF is what the runtime's cache holds most of).
trait SamplingLobe {
    fn weight(&self) -> f32;
    fn sggx(&self) -> &Sggx;
    fn density(&self) -> &SggxDensity;
}

impl SamplingLobe for SpecLobe {
    #[inline]
    fn weight(&self) -> f32 {
        self.weight
    }
    #[inline]
    fn sggx(&self) -> &Sggx {
        &self.sggx
    }
    #[inline]
    fn density(&self) -> &SggxDensity {
        &self.density
    }
}

impl SamplingLobe for MacroLobe {
    #[inline]
    fn weight(&self) -> f32 {
        self.ndf.weight
    }
    #[inline]
    fn sggx(&self) -> &Sggx {
        &self.sampling
    }
    #[inline]
    fn density(&self) -> &SggxDensity {
        &self.sampling_density
    }
}

/// κ assumed when sampling the diffuse component (§7.3): that of ω_i = ω_o, the sharpest.
pub const SAMPLING_KAPPA: f32 = 2.0 * COSINE_SHARPNESS;

fn lobe_sggx(frame: Mat3, alpha: Vec2) -> Sggx {
    Sggx::from_frame_roughness(frame, alpha)
}

/// Shadowing–masking of a (macro lobe k, microfacet lobe j) pair: the height-correlated Smith
/// G2 of the microfacet roughness α_j about the normal n* that dominates the specular response
/// at ω_h. n* is the mode of the product of the microfacet lobe around ω_h and the macro lobe,
/// found in slope space, where the two act like Gaussians of variances α_j² and (αx², αy²):
/// s* = αx²/(αx² + α_j²) · s_h per axis.
///
/// This departs from Eq. 22, which evaluates G with the convolved roughness α⁺ about the lobe
/// axis: that charges the spread of the macro normals (a cylinder's, say) to microfacet
/// shadowing. Measured on the anisotropic validation voxel (normals around a circle), Eq. 22's
/// G left the factored ABSDF at 0.46 of the ground truth's mean (0.89 with this one). The
/// Heaviside terms of Eq. 15 are also applied at n*, which removes the light a flat voxel
/// otherwise leaks to grazing views on its far side (flat voxel relative RMSE 0.12 → 0.08).
#[inline]
fn pair_g2(frame: Mat3, macro_alpha: Vec2, micro_alpha: f32, wi: Vec3, wo: Vec3, wh: Vec3) -> f32 {
    let t = frame.transpose();
    let mut h = t * wh;
    // The lobe is double-sided: work on the side of ω_h.
    let side = if h.z < 0.0 { -1.0 } else { 1.0 };
    h *= side;
    let hz = h.z.max(1e-4);
    let a2 = micro_alpha * micro_alpha;
    let kx = macro_alpha.x * macro_alpha.x / (macro_alpha.x * macro_alpha.x + a2);
    let ky = macro_alpha.y * macro_alpha.y / (macro_alpha.y * macro_alpha.y + a2);
    let n = side * (frame * Vec3::new(kx * h.x / hz, ky * h.y / hz, 1.0).normalize());
    // Eq. 15's Heaviside terms at the dominant normal: a surface facing ω_h must see both
    // directions (a flat voxel lit from below does not reflect towards a grazing view above).
    let (ci, co) = (n.dot(wi), n.dot(wo));
    if ci <= 0.0 || co <= 0.0 {
        return 0.0;
    }
    // The microfacet lobe is isotropic: Λ needs only the cosines to n.
    let l = ggx_lambda_iso(ci, micro_alpha) + ggx_lambda_iso(co, micro_alpha);
    if l >= f32::MAX {
        0.0
    } else {
        1.0 / (1.0 + l)
    }
}

impl<'t> Absdf<'t> {
    /// Bytes this ABSDF holds, itself and on the heap (what the runtime's block cache counts
    /// for a voxel shaded).
    pub fn memory_bytes(&self) -> usize {
        fn vec<T>(v: &[T]) -> usize {
            std::mem::size_of_val(v)
        }
        std::mem::size_of::<Self>()
            + vec(&self.lobes)
            + vec(&self.spec)
            + self.moments.memory_bytes()
    }

    /// [`Absdf::memory_bytes`] by part (the struct, macro lobes, specular lobes, moment
    /// table), for the resident-memory probe.
    pub fn memory_parts(&self) -> [(&'static str, usize); 4] {
        [
            ("struct", std::mem::size_of::<Self>()),
            ("lobes", std::mem::size_of_val(&*self.lobes)),
            ("spec", std::mem::size_of_val(&*self.spec)),
            ("moments", self.moments.memory_bytes()),
        ]
    }

    /// The ABSDF of voxel `v`: converts its lobes and moments once, with the tables' M1–M5
    /// lookups that do not depend on the directions.
    pub fn new(v: &VoxelAppearance, tables: &'t Tables) -> Self {
        Self::build(
            &v.lobes,
            v.roughness_mean,
            v.roughness_variance,
            MomentTable::new(&v.moments),
            tables,
        )
    }

    /// [`Absdf::new`] of a voxel whose directional moments are read in place, where a
    /// quantized block stores them ([`MomentHalves`]; the runtime's way, through
    /// `format::VoxelRef::absdf`: the ABSDF holds no copy of them, and they are not decoded
    /// to be dropped). The same ABSDF, bit for bit, as [`Absdf::new`] of the voxel's
    /// appearance; `None` where `halves` are not a valid table.
    pub fn with_moment_halves(
        lobes: &[NdfLobe],
        roughness_mean: f32,
        roughness_variance: f32,
        halves: MomentHalves<'t>,
        tables: &'t Tables,
    ) -> Option<Self> {
        halves.is_valid().then(|| {
            Self::build(
                lobes,
                roughness_mean,
                roughness_variance,
                MomentTable::Borrowed(halves),
                tables,
            )
        })
    }

    fn build(
        lobes: &[NdfLobe],
        roughness_mean: f32,
        roughness_variance: f32,
        moments: MomentTable<'t>,
        tables: &'t Tables,
    ) -> Self {
        // Two allocations a voxel, the lobes and the specular pairs: a shaded voxel's ABSDF is
        // built once and kept, and the runtime builds one for every voxel a render shades.
        let usable = |l: &&NdfLobe| l.weight > 0.0 && l.weight.is_finite() && l.frame.is_finite();
        let clamped = |l: &NdfLobe| NdfLobe {
            alpha: l.alpha.clamp(Vec2::splat(ALPHA_MIN), Vec2::ONE),
            ..*l
        };
        // Where no lobe is usable (no normal information): an isotropic distribution.
        const ISOTROPIC: NdfLobe = NdfLobe {
            weight: 1.0,
            frame: Mat3::IDENTITY,
            alpha: Vec2::ONE,
        };
        let count = lobes.iter().filter(usable).count();
        let ndfs = || {
            let none = (count == 0).then_some(ISOTROPIC);
            lobes.iter().filter(usable).map(clamped).chain(none)
        };
        // A lobe's weight is its share of the voxel's area (`estimate`), and every term below
        // takes the lobe unnormalised (σ = 1 along its normal, mass ∫D from 2 for a flat lobe to
        // 4 for a sphere), so the mixture with those shares weighs lobe k by w_k / mass_k. With
        // w_k alone, a rough lobe beside a flat one weighed up to twice its share: the
        // leaf-and-twig case's relative RMSE against Eq. 3 was 0.255, and is 0.157 so.
        let share = |l: &NdfLobe| l.weight / crate::math::sggx::lobe_shape(l.alpha).mass.max(1e-6);
        let wsum: f32 = ndfs().map(|l| share(&l)).sum();
        // Collected at their exact count, so that the boxes are the vectors' one allocation.
        let mut macros = Vec::with_capacity(count.max(1));
        macros.extend(ndfs().map(|l| {
            let l = NdfLobe {
                weight: share(&l) / wsum,
                ..l
            };
            let shape = crate::math::sggx::lobe_shape(l.alpha);
            let m = l.frame * Mat3::from_diagonal(shape.second) * l.frame.transpose();
            // The diffuse sampling lobe at the fixed κ (§7.3, M1).
            let mut o = [0f32; 3];
            tables
                .m1
                .lookup_into(&[l.alpha.x, l.alpha.y, SAMPLING_KAPPA], &mut o);
            let sampling = lobe_sggx(
                l.frame,
                Vec2::new(o[0], o[1]).clamp(Vec2::splat(ALPHA_MIN), Vec2::ONE),
            );
            MacroLobe {
                ndf: l,
                unit: lobe_sggx(l.frame, l.alpha),
                inv_mass: 1.0 / shape.mass.max(1e-6),
                second: m * (0.25 * shape.mass),
                sampling,
                sampling_density: sampling.density(),
            }
        }));
        let lobes = macros.into_boxed_slice();
        // Microfacet lobes of the roughness distribution (Eq. 19, M2).
        let micro: [(f32, f32); 2] =
            match RoughnessDistribution::from_moments(roughness_mean, roughness_variance) {
                RoughnessDistribution::Constant(a) => [(1.0, a.clamp(ALPHA_MIN, 1.0)), (0.0, 1.0)],
                d => {
                    let mu = d.mean();
                    let nu = d.variance() / (mu * (1.0 - mu)).max(1e-12);
                    let mut q = [0f32; 3];
                    tables.m2.lookup_into(&[mu, nu], &mut q);
                    [
                        (q[0].clamp(0.0, 1.0), q[1].clamp(ALPHA_MIN, 1.0)),
                        (1.0 - q[0].clamp(0.0, 1.0), q[2].clamp(ALPHA_MIN, 1.0)),
                    ]
                }
            };
        let reflects = |&&(m, _): &&(f32, f32)| !(m <= 0.0);
        let mut spec = Vec::with_capacity(lobes.len() * micro.iter().filter(reflects).count());
        let pairs = lobes.iter().enumerate().flat_map(|(k, l)| {
            micro
                .iter()
                .filter(reflects)
                .map(move |&(m, a)| (k, l.ndf, m, a))
        });
        spec.extend(pairs.map(|(k, l, m, a)| {
            let mut o = [0f32; 3];
            tables.m3.lookup_into(&[l.alpha.x, l.alpha.y, a], &mut o);
            let alpha = Vec2::new(o[0], o[1]).clamp(Vec2::splat(ALPHA_MIN), Vec2::ONE);
            let m5 = tables.m5.lookup1(&[a]);
            let sggx = lobe_sggx(l.frame, alpha);
            SpecLobe {
                weight: l.weight * m * m5 * o[2].max(0.0),
                sggx,
                density: sggx.density(),
                lobe: k as u32,
                micro_alpha: a,
                lune_coord: LuneTable::alpha_coord(lune_alpha(l.alpha, a)),
            }
        }));
        let spec = spec.into_boxed_slice();
        let spec_total = spec.iter().map(|x| x.weight).sum();
        let diffuse_total = lobes.iter().map(|x| x.ndf.weight).sum();
        // Sampling picks the specular component in proportion to nothing finer than whether
        // each component reflects at all (the moments' means).
        let (dm, sm) = moments.mean();
        let wd = crate::math::color::luminance(dm.diffuse());
        let ws = crate::math::color::luminance(sm.reflectance()).max(0.0) + 0.1 * sm.grazing();
        let spec_probability = if spec.is_empty() || ws <= 0.0 {
            0.0
        } else if wd <= 0.0 {
            1.0
        } else {
            0.5
        };
        Absdf {
            tables,
            lobes,
            spec,
            spec_total,
            diffuse_total,
            spec_probability,
            moments,
        }
    }

    /// Projected area σ_N(ω) of the normal distribution (up to the scale that cancels).
    #[inline]
    pub fn projected_area(&self, w: Vec3) -> f32 {
        self.lobes
            .iter()
            .map(|l| l.ndf.weight * l.unit.sigma(w))
            .sum()
    }

    /// The diffuse numerator of Eq. 13 without the moments, ∫ ⟨n·ω_i⟩⟨n·ω_o⟩ D(n) dn, in
    /// closed form per lobe. A double-sided distribution gives
    ///
    /// ```text
    /// ∫⟨n·ω_i⟩⟨n·ω_o⟩ D = ¼ ∫ (|n·ω_i||n·ω_o| + (n·ω_i)(n·ω_o)) D
    ///                   ≈ σ(ω_i) σ(ω_o) / mass + (mass/4) ω_iᵀ E[n nᵀ] ω_o
    /// ```
    ///
    /// The second term is exact (the lobe's second moment, [`crate::math::sggx::lobe_shape`]);
    /// the first replaces E|n·ω_i||n·ω_o| by E|n·ω_i| E|n·ω_o|, exact for a flat lobe and 12%
    /// low for a sphere at ω_i = ω_o. The result is exact for flat lobes (no light through a
    /// sheet, the right radiance at every angle), reciprocal, and conserves energy for every
    /// lobe: ∫ over ω_i of the first term is π σ(ω_o) and of the second 0 (up to the clamp at
    /// 0 for opposite directions, which adds 2% for a sphere's lobe).
    ///
    /// A departure from the paper: Eq. 14 convolves the product of two clamped-cosine SGs with
    /// the lobes (M1). That SG is 0.14 at the horizon where the cosine is 0, so a flat
    /// Lambertian voxel reflected 0.81 / 0.90 / 0.83 / 0.63 of its albedo to views at
    /// 0° / 30° / 60° / 80° and let 0.05–0.25 of it through from below (measured by
    /// integrating f̂ over ω_i; `flat_lambertian_voxel_reflects_its_albedo` now checks 1%).
    fn diffuse_numerator(&self, wi: Vec3, wo: Vec3) -> f32 {
        let mut acc = 0.0f32;
        for l in self.lobes.iter() {
            let p = l.unit.sigma(wi) * l.unit.sigma(wo) * l.inv_mass + wi.dot(l.second * wo);
            acc += l.ndf.weight * p.max(0.0);
        }
        acc
    }

    /// Density of ω_h under a visible-normal mixture and the reflection Jacobian.
    fn mixture_pdf<L: SamplingLobe>(lobes: &[L], total: f32, wi: Vec3, wo: Vec3) -> f32 {
        let h = wi + wo;
        let hl = h.length();
        if !(hl > 1e-6) || total <= 0.0 {
            return 0.0;
        }
        let wh = h / hl;
        let oh = wo.dot(wh);
        if oh <= 0.0 {
            return 0.0;
        }
        let mut p = 0.0;
        for l in lobes {
            // The visible-normal density max(0, ω_o·m) D(m) / σ(ω_o), D precomputed.
            let sigma = l.sggx().sigma(wo);
            if sigma > 0.0 {
                p += l.weight() / total * (oh * l.density().d(wh) / sigma);
            }
        }
        finite_or_zero(p / (4.0 * oh))
    }

    /// The lobe of a mixture whose share of the total weight holds `v` in [0, 1).
    #[inline]
    fn pick<L: SamplingLobe>(list: &[L], total: f32, v: f32) -> Option<Sggx> {
        if !(total > 0.0) {
            return None;
        }
        let mut v = v.clamp(0.0, 0.999_999) * total;
        let mut chosen = *list.last()?.sggx();
        for l in list {
            if v < l.weight() {
                chosen = *l.sggx();
                break;
            }
            v -= l.weight();
        }
        Some(chosen)
    }
}

impl Bsdf for Absdf<'_> {
    /// f̂(ω_i, ω_o) without visibility (Eq. 7 through Eq. 23). Finite for every input.
    fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        if !(wi.is_finite() && wo.is_finite()) {
            return Vec3::ZERO;
        }
        let (wi, wo) = (unit_or_zero(wi), unit_or_zero(wo));
        if wi == Vec3::ZERO || wo == Vec3::ZERO {
            return Vec3::ZERO;
        }
        let sigma_o = self.projected_area(wo);
        if !(sigma_o > 1e-12) {
            return Vec3::ZERO;
        }
        let h = wi + wo;
        let hl = h.length();
        let (dm, sm) = if hl > 1e-6 {
            self.moments.at(h / hl)
        } else {
            // ω_h is undefined (ω_i = −ω_o): the means over directions, so that the look-up
            // stays symmetric in ω_i and ω_o (a rare path; the means are computed here).
            self.moments.mean()
        };
        // Diffuse (Eq. 13; the lobe integral in closed form, see `diffuse_numerator`).
        let mut f = dm.diffuse() * (FRAC_1_PI * self.diffuse_numerator(wi, wo));
        // Specular (Eq. 15–22).
        if hl > 1e-6 {
            let wh = h / hl;
            let fc = schlick_weight(wh.dot(wo));
            let fres = (1.0 - fc) * sm.reflectance() + Vec3::splat(fc * sm.grazing());
            let mut acc = 0.0f32;
            // S's coordinate along the angle between ω_i and ω_o, shared by every lobe.
            let t = LuneTable::io_coord(wi.dot(wo));
            for l in &self.spec {
                let d = l.density.d(wh);
                if d <= 0.0 {
                    continue;
                }
                let s = self.tables.lune.at(t, l.lune_coord);
                if s <= 0.0 {
                    continue;
                }
                let n = &self.lobes[l.lobe as usize].ndf;
                acc += l.weight * d * s * pair_g2(n.frame, n.alpha, l.micro_alpha, wi, wo, wh);
            }
            f += fres * (0.25 * acc);
        }
        finite_vec_or_zero(f / sigma_o)
    }

    /// Solid-angle density of [`Bsdf::sample`].
    fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        if !(wi.is_finite() && wo.is_finite()) {
            return 0.0;
        }
        let (wi, wo) = (unit_or_zero(wi), unit_or_zero(wo));
        let ps = self.spec_probability;
        let mut p = 0.0;
        if ps > 0.0 {
            p += ps * Self::mixture_pdf(&self.spec, self.spec_total, wi, wo);
        }
        if ps < 1.0 {
            p += (1.0 - ps) * Self::mixture_pdf(&self.lobes, self.diffuse_total, wi, wo);
        }
        finite_or_zero(p)
    }

    /// Samples ω_i (§7.3): pick the specular or diffuse component, a lobe by weight, a visible
    /// normal of that lobe for ω_o, and reflect ω_o about it. `u` = (component and lobe,
    /// direction 2D).
    fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        if !wo.is_finite() {
            return None;
        }
        let wo = unit_or_zero(wo);
        if wo == Vec3::ZERO {
            return None;
        }
        let ps = self.spec_probability;
        let chosen = if u_lobe < ps {
            Self::pick(&self.spec, self.spec_total, u_lobe / ps.max(1e-12))?
        } else {
            Self::pick(
                &self.lobes,
                self.diffuse_total,
                (u_lobe - ps) / (1.0 - ps).max(1e-12),
            )?
        };
        let wh = chosen.sample_visible(wo, u);
        let oh = wo.dot(wh);
        if !(oh > 0.0) {
            return None;
        }
        let wi = unit_or_zero(2.0 * oh * wh - wo);
        let pdf = self.pdf(wi, wo);
        if !(pdf > 0.0) || wi == Vec3::ZERO {
            return None;
        }
        Some(BsdfSample {
            wi,
            value: self.eval(wi, wo),
            pdf,
        })
    }
}

/// Ground truth of Eq. 3 without visibility by direct integration over surface samples: each
/// sample (normal, params, area weight) contributes f(ω_i, ω_o) |n·ω_i| |n·ω_o| when both
/// directions are on the same side of it (double-sided surfaces), normalised by the projected
/// area Σ w |n·ω_o|.
pub fn ground_truth(
    samples: &[(Vec3, crate::scene::SurfaceParams, f32)],
    wi: Vec3,
    wo: Vec3,
) -> Vec3 {
    let mut num = Vec3::ZERO;
    let mut den = 0.0f64;
    for (n, p, w) in samples {
        let n = n.normalize_or_zero();
        let co = n.dot(wo);
        den += (*w * co.abs()) as f64;
        let ci = n.dot(wi);
        if ci * co <= 0.0 {
            continue;
        }
        let n = if co < 0.0 { -n } else { n };
        let frame = crate::math::frame::Frame::from_z(n);
        let b = crate::bsdf::BaseBsdf::new(*p);
        let f = b.eval(frame.to_local(wi), frame.to_local(wo));
        num += f * (w * ci.abs() * co.abs());
    }
    if den > 0.0 {
        finite_vec_or_zero(num / den as f32)
    } else {
        Vec3::ZERO
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The moment table returns, at every direction, the (diffuse, specular) sets of that
    /// direction's cell bit for bit: binary16 where binary16 holds every value exactly (as in a
    /// quantized file), f32 otherwise; dielectric and metal sets. The binary16 table is the
    /// smaller.
    #[test]
    fn moment_table_returns_the_cells_sets_exactly() {
        let res = 3u32;
        let cells = (res * res) as usize;
        for (metal, exact) in [(false, true), (true, true), (false, false), (true, false)] {
            let set = |k: usize| {
                // Binary16 holds multiples of 1/1024 below 2 exactly; 1e-4 more it does not.
                let x = |j: usize| {
                    ((k * 37 + j * 11) % 1500) as f32 / 1024.0 + if exact { 0.0 } else { 1e-4 }
                };
                let m = if metal { x(9) } else { 0.0 };
                MaterialMoments {
                    c: Vec3::new(x(0), x(1), x(2)),
                    mc: Vec3::new(x(3), x(4), x(5)) * m.signum(),
                    s: x(6),
                    ms: x(7) * m.signum(),
                    m,
                    f90: x(8),
                    mf90: x(10) * m.signum(),
                }
            };
            let (diffuse, specular): (Vec<_>, Vec<_>) = (
                (0..cells).map(set).collect(),
                (cells..2 * cells).map(set).collect(),
            );
            let table = MomentTable::new(&Moments::Directional {
                res,
                diffuse: diffuse.clone(),
                specular: specular.clone(),
            });
            assert_eq!(
                matches!(table, MomentTable::Half { .. }),
                exact,
                "metal {metal}"
            );
            let full = 2 * cells * std::mem::size_of::<MaterialMoments>();
            assert_eq!(
                2 * table.memory_bytes() <= full,
                exact,
                "{}",
                table.memory_bytes()
            );
            for i in 0..4096 {
                let u = Vec2::new((i % 64) as f32 + 0.5, (i / 64) as f32 + 0.5) / 64.0;
                let w = crate::math::sphere_maps::equal_area_square_to_sphere(u);
                let cell = grid_cell(equal_area_sphere_to_square(w), res) as usize;
                let (d, s) = table.at(w);
                assert_eq!(
                    (d, s),
                    (diffuse[cell], specular[cell]),
                    "metal {metal} exact {exact}"
                );
                // Bitwise: PartialEq would take −0 for 0.
                let bits = |m: MaterialMoments| {
                    [
                        m.c.x, m.c.y, m.c.z, m.mc.x, m.mc.y, m.mc.z, m.s, m.ms, m.m, m.f90, m.mf90,
                    ]
                    .map(f32::to_bits)
                };
                assert_eq!(bits(d), bits(diffuse[cell]));
                assert_eq!(bits(s), bits(specular[cell]));
            }
        }
    }
}
