//! The truncated ellipsoid primitive (paper §6.1): the intersection of a voxel with an
//! ellipsoid bounding the voxel's surfaces. [`truncated_entry`] is the one ray test of the
//! project: the bake's P⁺ test (which rays of a boundary face count towards the ABV, Eq. 26)
//! and the runtime's primitive hit (Eq. 30) both call it.
//!
//! The projected area |B|_ω of Eq. 24 follows the supplemental Algorithm 1 (points spread over
//! the ellipsoid's shadow, with its two early exits, decided once per primitive) with two
//! changes. N = 64 points on a stratified 8×8 pattern instead of 16: with 16, the estimate for
//! a flat voxel's ellipse clipped to its square was off by up to 25% from voxel to voxel, a
//! visible pattern on flat surfaces (c = |A|/|B| is divided by it). And each line along ω is
//! tested against the truncated ellipsoid itself (ellipsoid ∩ voxel), not against the voxel
//! alone, which the paper's version does and which over-counts lines that meet both but not
//! their intersection. The points are a fixed pattern, so |B|_ω is deterministic (no per-frame
//! noise) and costs no random numbers. The ellipsoid's shadow is parameterised in the
//! ellipsoid's own unit ball: lines along ω are lines along q = M⁻¹ω there, the ball's shadow
//! is the unit disk ⊥ q, and area-uniform points on that disk are area-uniform on the ellipse.

use glam::{Mat3, Vec2, Vec3};

use super::grid::{box_interval, box_projected_area};
use crate::math::frame::Frame;
use crate::math::sampling::square_to_concentric_disk;

/// Points per projected-area estimate.
pub const AREA_SAMPLES: usize = 64;

/// An ellipsoid {c + M u : |u| ≤ 1}.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ellipsoid {
    /// The centre c.
    pub center: Vec3,
    /// M: its columns are the semi-axes.
    pub axes: Mat3,
}

impl Ellipsoid {
    /// Whether `p` is inside (with a relative tolerance).
    pub fn contains(&self, p: Vec3, tol: f32) -> bool {
        let inv = self.axes.inverse();
        (inv * (p - self.center)).length() <= 1.0 + tol
    }

    /// Volume (4/3 π |det M|).
    pub fn volume(&self) -> f32 {
        4.0 / 3.0 * std::f32::consts::PI * self.axes.determinant().abs()
    }

    /// Half extents of its axis-aligned bounding box: |row i of M| along axis i.
    pub fn half_extents(&self) -> Vec3 {
        let m = self.axes.transpose();
        Vec3::new(m.x_axis.length(), m.y_axis.length(), m.z_axis.length())
    }
}

/// Parameter interval where `o + t d` lies inside the ellipsoid {c + M u : |u| ≤ 1}, given
/// `inv` = M⁻¹. Numerically stable for thin ellipsoids far from the ray origin: the ray is
/// first moved to its closest approach to the centre, and the discriminant is taken as the
/// squared distance of the closest point in the ellipsoid's unit-ball space (the textbook
/// b² − ac cancels catastrophically in f32 when the ellipsoid is a thousand times thinner
/// than its distance to the origin).
#[inline]
pub fn ellipsoid_ray_interval(center: Vec3, inv: Mat3, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
    let dd = d.dot(d);
    if !(dd > 0.0) {
        return None;
    }
    let tc = (center - o).dot(d) / dd;
    let p = inv * (o + tc * d - center);
    let q = inv * d;
    let a = q.dot(q);
    if !(a > 0.0) || !a.is_finite() {
        return None;
    }
    let k = p.dot(q) / a;
    let m = p - q * k;
    let h = 1.0 - m.dot(m);
    if !(h >= 0.0) {
        return None;
    }
    let s = (h / a).sqrt();
    let t = tc - k;
    Some((t - s, t + s))
}

/// Where the ray `o + t d` enters the ellipsoid (centre `center`, inverse axes `inv`) within
/// the parameter interval [t0, t1] the ray spends inside the primitive's voxel: the one
/// primitive hit test of bake and runtime. The bake gets [t0, t1] from the voxel's box
/// ([`TruncatedEllipsoid::intersect`]), the runtime from its DDA, both padded by
/// [`VOXEL_PAD`] of the voxel size.
#[inline]
pub fn truncated_entry(center: Vec3, inv: Mat3, o: Vec3, d: Vec3, t0: f32, t1: f32) -> Option<f32> {
    if !(t0 <= t1) {
        return None;
    }
    let (e0, e1) = ellipsoid_ray_interval(center, inv, o, d)?;
    let (lo, hi) = (e0.max(t0), e1.min(t1));
    (lo <= hi).then_some(lo)
}

/// The padding of a primitive's voxel, as a fraction of its size: a ray on a voxel boundary,
/// placed in this voxel by one computation's rounding, is not outside its box by another's.
pub const VOXEL_PAD: f32 = 1e-5;

/// How |B|_ω is computed for a primitive, decided once when it is made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AreaCase {
    /// The ellipsoid lies inside its voxel: |B|_ω = π |det M| |M⁻¹ ω| exactly.
    EllipsoidInside,
    /// The voxel lies inside the ellipsoid: |B|_ω is the box's projected area exactly.
    VoxelInside,
    /// They cross: the 64-point estimate.
    Crossing,
}

/// A truncated ellipsoid ready for ray tests: the ellipsoid (centre, axes and their inverse)
/// and its voxel's box, padded by a hair.
#[derive(Clone, Copy, Debug)]
pub struct TruncatedEllipsoid {
    /// The ellipsoid's centre.
    pub center: Vec3,
    /// The ellipsoid's semi-axes (columns).
    pub axes: Mat3,
    /// The inverse of `axes`.
    pub inv: Mat3,
    /// |det M|.
    pub det: f32,
    /// The voxel box, a hair wider than the voxel.
    pub lo: Vec3,
    /// See `lo`.
    pub hi: Vec3,
    /// How |B|_ω is computed.
    pub area_case: AreaCase,
}

impl TruncatedEllipsoid {
    /// The primitive of an ellipsoid in the voxel box [lo, hi]; `None` for a degenerate
    /// ellipsoid (singular or non-finite axes).
    pub fn new(e: &Ellipsoid, lo: Vec3, hi: Vec3) -> Option<TruncatedEllipsoid> {
        let pad = Vec3::splat(VOXEL_PAD * (hi - lo).max_element());
        let (lo, hi) = (lo - pad, hi + pad);
        let inv = e.axes.inverse();
        let det = e.axes.determinant().abs();
        if !(inv.is_finite() && det > 0.0 && det.is_finite() && e.center.is_finite()) {
            return None;
        }
        let half = e.half_extents();
        let area_case = if (e.center - half).cmpge(lo).all() && (e.center + half).cmple(hi).all() {
            AreaCase::EllipsoidInside
        } else if (0..8).all(|i| {
            let c = Vec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            );
            (inv * (c - e.center)).length_squared() <= 1.0
        }) {
            AreaCase::VoxelInside
        } else {
            AreaCase::Crossing
        };
        Some(TruncatedEllipsoid {
            center: e.center,
            axes: e.axes,
            inv,
            det,
            lo,
            hi,
            area_case,
        })
    }

    /// The box of the primitive: the ellipsoid's box clipped to the (padded) voxel; `None`
    /// when they do not overlap.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let half = Ellipsoid {
            center: self.center,
            axes: self.axes,
        }
        .half_extents();
        let (lo, hi) = (
            (self.center - half).max(self.lo),
            (self.center + half).min(self.hi),
        );
        lo.cmple(hi).all().then_some((lo, hi))
    }

    /// Entry parameter of the ray `o + t d` (with `inv_d` = 1/d) into the truncated ellipsoid
    /// within [tmin, tmax] ([`truncated_entry`] over the ray's interval in the padded box).
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, inv_d: Vec3, tmin: f32, tmax: f32) -> Option<f32> {
        let (b0, b1) = box_interval(self.lo, self.hi, o, inv_d);
        truncated_entry(self.center, self.inv, o, d, b0.max(tmin), b1.min(tmax))
    }

    /// Projected area of the whole ellipsoid along unit `w`: π |det M| |M⁻¹ w|.
    #[inline]
    pub fn ellipsoid_projected_area(&self, w: Vec3) -> f32 {
        std::f32::consts::PI * self.det * (self.inv * w).length()
    }

    /// Projected area of the voxel box along unit `w`.
    #[inline]
    pub fn box_projected_area(&self, w: Vec3) -> f32 {
        box_projected_area(self.hi - self.lo, w)
    }

    /// |B|_ω of the truncated ellipsoid along unit `w` (see the module notes).
    #[inline]
    pub fn projected_area(&self, w: Vec3) -> f32 {
        match self.area_case {
            AreaCase::EllipsoidInside => self.ellipsoid_projected_area(w),
            AreaCase::VoxelInside => self.box_projected_area(w),
            AreaCase::Crossing => self.crossing_projected_area(w),
        }
    }

    /// An upper bound on |B|_ω, cheap: exact in the two early-exit cases, otherwise the smaller
    /// of the ellipsoid's and the box's projected areas (the truncated ellipsoid lies inside
    /// both). Within a small factor of |B|_ω, so a weight computed with it can choose which of
    /// a cone's voxels to shade, the exact |B|_ω being computed for the chosen one only.
    #[inline]
    pub fn projected_area_bound(&self, w: Vec3) -> f32 {
        match self.area_case {
            AreaCase::EllipsoidInside => self.ellipsoid_projected_area(w),
            AreaCase::VoxelInside => self.box_projected_area(w),
            AreaCase::Crossing => self
                .ellipsoid_projected_area(w)
                .min(self.box_projected_area(w)),
        }
    }

    /// The 64-point estimate of |B|_ω for an ellipsoid that crosses its voxel's boundary.
    ///
    /// Its loops vectorise; where the processor has AVX2 they run eight lanes wide instead of
    /// the baseline's four (the same operations, so the same bits: no fused multiply-adds).
    #[inline]
    fn crossing_projected_area(&self, w: Vec3) -> f32 {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is present (checked just above).
            return unsafe { self.crossing_projected_area_avx2(w) };
        }
        self.crossing_projected_area_in(w)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn crossing_projected_area_avx2(&self, w: Vec3) -> f32 {
        self.crossing_projected_area_in(w)
    }

    #[inline(always)]
    fn crossing_projected_area_in(&self, w: Vec3) -> f32 {
        let full = self.ellipsoid_projected_area(w);
        // Lines along w through area-uniform points of the ellipsoid's shadow.
        let q = (self.inv * w).normalize_or_zero();
        if q == Vec3::ZERO {
            return 0.0;
        }
        let f = Frame::from_z(q);
        // The chord of the unit ball along q through (p, 0) maps to a + t·w in world space,
        // a = c + p.x·mx + p.y·my − h·mz, spanning t in [0, 2h·(mz·w)]. Per axis the slab
        // test of that chord is affine in (p.x, p.y, h): evaluated for all points at once,
        // structure of arrays, so that the loop vectorises.
        let (mx, my, mz) = (self.axes * f.x, self.axes * f.y, self.axes * f.z);
        let mzw = 2.0 * mz.dot(w);
        let pts = disk_points();
        let mut t0 = [0f32; AREA_SAMPLES];
        let mut t1 = [0f32; AREA_SAMPLES];
        // Plain comparisons rather than f32::min/max, whose NaN handling kept the loops from
        // compiling to packed min/max (a third of the function's instructions): a NaN operand
        // (never met with finite inputs) is ignored as f32::max ignores it.
        #[inline(always)]
        fn lo_of(a: f32, b: f32) -> f32 {
            if b < a {
                b
            } else {
                a
            }
        }
        #[inline(always)]
        fn hi_of(a: f32, b: f32) -> f32 {
            if b > a {
                b
            } else {
                a
            }
        }
        for k in 0..AREA_SAMPLES {
            let len = pts.h[k] * mzw;
            t0[k] = lo_of(len, 0.0);
            t1[k] = hi_of(len, 0.0);
        }
        for axis in 0..3 {
            let (lo, hi, c) = (self.lo[axis], self.hi[axis], self.center[axis]);
            if w[axis] == 0.0 {
                // Lines parallel to the slab: inside it for every t or for none.
                for k in 0..AREA_SAMPLES {
                    let a = c + pts.x[k] * mx[axis] + pts.y[k] * my[axis] - pts.h[k] * mz[axis];
                    if a < lo || a > hi {
                        t0[k] = f32::INFINITY;
                    }
                }
                continue;
            }
            let inv = 1.0 / w[axis];
            let (a_lo, a_hi) = ((lo - c) * inv, (hi - c) * inv);
            let (bx, by, bz) = (mx[axis] * inv, my[axis] * inv, mz[axis] * inv);
            for k in 0..AREA_SAMPLES {
                let off = bx * pts.x[k] + by * pts.y[k] - bz * pts.h[k];
                let (u, v) = (a_lo - off, a_hi - off);
                t0[k] = hi_of(t0[k], lo_of(u, v));
                t1[k] = lo_of(t1[k], hi_of(u, v));
            }
        }
        let hits = (0..AREA_SAMPLES).filter(|&k| t0[k] <= t1[k]).count();
        full * hits as f32 / AREA_SAMPLES as f32
    }
}

/// The stratified points of the unit disk that |B|_ω tests, with the unit ball's half-chord
/// height over each, as arrays: computed once (their sines and cosines were 8% of a LoD
/// render).
struct DiskPoints {
    x: [f32; AREA_SAMPLES],
    y: [f32; AREA_SAMPLES],
    h: [f32; AREA_SAMPLES],
}

fn disk_points() -> &'static DiskPoints {
    static POINTS: std::sync::OnceLock<DiskPoints> = std::sync::OnceLock::new();
    POINTS.get_or_init(|| {
        let mut d = DiskPoints {
            x: [0.0; AREA_SAMPLES],
            y: [0.0; AREA_SAMPLES],
            h: [0.0; AREA_SAMPLES],
        };
        for k in 0..AREA_SAMPLES {
            let u = Vec2::new(((k % 8) as f32 + 0.5) / 8.0, ((k / 8) as f32 + 0.5) / 8.0);
            let p = square_to_concentric_disk(u);
            d.x[k] = p.x;
            d.y[k] = p.y;
            d.h[k] = (1.0 - p.length_squared()).max(0.0).sqrt();
        }
        d
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;

    fn prim(c: Vec3, m: Mat3) -> TruncatedEllipsoid {
        TruncatedEllipsoid::new(&Ellipsoid { center: c, axes: m }, Vec3::ZERO, Vec3::ONE).unwrap()
    }

    /// The AVX2 build of the crossing |B|_ω and the baseline's give the same bits (the
    /// processor that runs the tests runs one of them in renders), on random crossing
    /// ellipsoids and directions, axis-parallel ones among them.
    #[test]
    fn crossing_area_same_bits_on_every_path() {
        let mut rng = Pcg32::new(11, 3);
        let mut crossing = 0;
        for k in 0..400 {
            let c = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let m = Mat3::from_cols(
                Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5,
                Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5,
                Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 0.1,
            );
            let Some(p) =
                TruncatedEllipsoid::new(&Ellipsoid { center: c, axes: m }, Vec3::ZERO, Vec3::ONE)
            else {
                continue;
            };
            if p.area_case != AreaCase::Crossing {
                continue;
            }
            crossing += 1;
            let w = if k % 7 == 0 {
                Vec3::X
            } else {
                crate::math::sampling::square_to_uniform_sphere(rng.next_2d())
            };
            let a = p.crossing_projected_area(w);
            assert!(a.is_finite() && a >= 0.0);
            assert_eq!(
                a.to_bits(),
                p.crossing_projected_area_in(w).to_bits(),
                "{k}"
            );
        }
        assert!(crossing > 100, "{crossing}");
    }

    /// A flat ellipsoid (1e-4 thick) three units from the ray origin: the interval is found,
    /// and it is where the ray crosses the disk (the textbook quadratic loses it in f32).
    #[test]
    fn thin_ellipsoid_far_away() {
        let c = Vec3::new(0.31, 0.0, 0.31);
        let m = Mat3::from_diagonal(Vec3::new(0.09, 1.3e-4, 0.09));
        let (t0, t1) =
            ellipsoid_ray_interval(c, m.inverse(), Vec3::new(0.33, 3.0, 0.29), Vec3::NEG_Y)
                .expect("hits");
        assert!(
            (t0 - (3.0 - 1.3e-4)).abs() < 2e-5 && (t1 - (3.0 + 1.3e-4)).abs() < 2e-5,
            "{t0} {t1}"
        );
        assert!(
            ellipsoid_ray_interval(c, m.inverse(), Vec3::new(0.5, 3.0, 0.31), Vec3::NEG_Y)
                .is_none()
        );
        // Unit sphere from outside, oblique: exact chord.
        let (a, b) = ellipsoid_ray_interval(
            Vec3::ZERO,
            Mat3::IDENTITY,
            Vec3::new(0.6, 0.0, -5.0),
            Vec3::Z,
        )
        .unwrap();
        assert!((a - 4.2).abs() < 1e-5 && (b - 5.8).abs() < 1e-5);
    }

    /// Brute force: the fraction of a fine grid of lines along w, over a square covering the
    /// box's shadow, that meet the truncated ellipsoid.
    fn brute(p: &TruncatedEllipsoid, w: Vec3) -> f32 {
        let f = Frame::from_z(w);
        let c = 0.5 * (p.lo + p.hi);
        let r = (p.hi - p.lo).length() * 0.5;
        let n = 300;
        let mut hits = 0;
        for i in 0..n {
            for j in 0..n {
                let x = (i as f32 + 0.5) / n as f32 * 2.0 - 1.0;
                let y = (j as f32 + 0.5) / n as f32 * 2.0 - 1.0;
                let o = c + f.to_world(Vec3::new(x * r, y * r, -10.0 * r));
                if p.intersect(o, w, w.recip(), 0.0, f32::INFINITY).is_some() {
                    hits += 1;
                }
            }
        }
        hits as f32 / (n * n) as f32 * (2.0 * r) * (2.0 * r)
    }

    /// The 64-point estimate against a brute-force projection, for ellipsoids inside, around
    /// and across their voxel: within 8% on average, exact in the early exits.
    #[test]
    fn projected_area_matches_brute_force() {
        let mut rng = Pcg32::new(5, 5);
        let mut rel = Vec::new();
        let cases = [
            (
                Vec3::splat(0.5),
                Mat3::from_diagonal(Vec3::new(0.3, 0.2, 0.1)),
            ), // inside
            (Vec3::splat(0.5), Mat3::from_diagonal(Vec3::splat(1.0))), // voxel inside
            (
                Vec3::new(0.5, 0.5, 0.5),
                Mat3::from_diagonal(Vec3::new(0.7, 0.7, 0.01)),
            ), // flat
            (
                Vec3::new(0.8, 0.3, 0.5),
                Mat3::from_diagonal(Vec3::new(0.5, 0.4, 0.6)),
            ),
        ];
        for (c, m) in cases {
            let p = prim(c, m);
            for _ in 0..8 {
                let w = crate::math::sampling::square_to_uniform_sphere(rng.next_2d());
                let (est, want) = (p.projected_area(w), brute(&p, w));
                assert!(est.is_finite() && est >= 0.0);
                rel.push(((est - want) / want.max(1e-3)).abs());
            }
        }
        let mean = rel.iter().sum::<f32>() / rel.len() as f32;
        assert!(mean < 0.08, "mean relative error {mean}: {rel:?}");
        // Early exits are exact (up to the brute force's own grid error).
        let inside = prim(Vec3::splat(0.5), Mat3::from_diagonal(Vec3::splat(0.2)));
        assert_eq!(inside.area_case, AreaCase::EllipsoidInside);
        assert!((inside.projected_area(Vec3::Z) - std::f32::consts::PI * 0.04).abs() < 1e-4);
        let big = prim(Vec3::splat(0.5), Mat3::from_diagonal(Vec3::splat(2.0)));
        assert_eq!(big.area_case, AreaCase::VoxelInside);
        assert!((big.projected_area(Vec3::new(0.6, 0.0, 0.8)) - 1.4).abs() < 1e-3);
    }

    /// The primitive's box holds every point of the truncated ellipsoid a ray can enter.
    #[test]
    fn bounds_hold_the_hits() {
        let mut rng = Pcg32::new(9, 1);
        let p = prim(
            Vec3::new(0.9, 0.5, 0.4),
            Mat3::from_diagonal(Vec3::new(0.4, 0.05, 0.3)),
        );
        let (lo, hi) = p.bounds().unwrap();
        for _ in 0..2000 {
            let d = crate::math::sampling::square_to_uniform_sphere(rng.next_2d());
            let o = Vec3::splat(0.5) - d * 3.0
                + Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, 0.0);
            if let Some(t) = p.intersect(o, d, d.recip(), 0.0, f32::INFINITY) {
                let x = o + d * t;
                assert!(x.cmpge(lo - 1e-4).all() && x.cmple(hi + 1e-4).all());
            }
        }
        assert!(TruncatedEllipsoid::new(
            &Ellipsoid {
                center: Vec3::ZERO,
                axes: Mat3::ZERO
            },
            Vec3::ZERO,
            Vec3::ONE
        )
        .is_none());
    }
}
