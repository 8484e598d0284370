//! Format 1.4's quantized records, encoded and decoded in one place: the SGGX lobes (`QLobe`:
//! the eigenframe as a unit quaternion, the weight as unorm16, α as binary16) and the
//! material moments (`QMoments`, `QDielectricMoments`: binary16). The Haar nodes' fixed point
//! is [`crate::math::haar::QNode`].
//!
//! Precision, and why it is enough (measured on bakes in `tests/format.rs`):
//! - quaternion components · 32767: frame error below 1e-4 rad, far below any lobe's width;
//! - weight · 65535: 7.6e-6 absolute, and [`crate::absdf::Absdf::new`] renormalises weights;
//! - α and moments as binary16: relative error at most 2^-11 (4.9e-4), α down to
//!   `ALPHA_MIN` and dark colours keep their relative precision (unorm16 would not).
//!
//! Nothing decodes to NaN or out of range: the encoder clamps to the stored ranges, the
//! verifier ([`crate::format::Aggregate`]'s) refuses any other bit pattern (non-finite or negative
//! binary16, α above one, a quaternion far from unit length), and the decoder normalises the
//! quaternion.

use glam::{Mat3, Quat, Vec2, Vec3};
use half::f16;

use super::fb;
use crate::absdf::{MaterialMoments, NdfLobe};

/// Largest finite binary16.
const F16_MAX: f32 = 65504.0;
/// Fixed-point scale of quaternion components.
const Q_QUAT: f32 = 32767.0;

/// `x` clamped to [0, 65504] as binary16 bits (NaN: 0).
fn f16_bits(x: f32) -> u16 {
    let x = if x.is_nan() {
        0.0
    } else {
        x.clamp(0.0, F16_MAX)
    };
    f16::from_f32(x).to_bits()
}

fn from_f16(b: u16) -> f32 {
    f16::from_bits(b).to_f32()
}

/// Binary16 bits of a finite value in [0, 65504] (the sign bit clear; -0 excluded).
fn f16_ok(b: u16) -> bool {
    b & 0x8000 == 0 && f16::from_bits(b).is_finite()
}

fn unorm16(x: f32) -> u16 {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    (x * 65535.0).round() as u16
}

fn v3h(v: Vec3) -> fb::Vec3h {
    fb::Vec3h::new(f16_bits(v.x), f16_bits(v.y), f16_bits(v.z))
}

fn from_v3h(v: &fb::Vec3h) -> Vec3 {
    Vec3::new(from_f16(v.x()), from_f16(v.y()), from_f16(v.z()))
}

fn v3h_ok(v: &fb::Vec3h) -> bool {
    f16_ok(v.x()) && f16_ok(v.y()) && f16_ok(v.z())
}

/// The rotation of a lobe's eigenframe [t b n]: a frame of determinant −1 has t negated first
/// (σ(ω) = ωᵀ F diag(α²) Fᵀ ω, Eq. 8, does not see an axis' sign). The canonical sign w ≥ 0;
/// the identity for a frame that is not a rotation at all (never written by the bake).
fn frame_quat(frame: Mat3) -> Quat {
    let f = if frame.determinant() < 0.0 {
        Mat3::from_cols(-frame.x_axis, frame.y_axis, frame.z_axis)
    } else {
        frame
    };
    let q = Quat::from_mat3(&f);
    let len = q.length();
    if !(len.is_finite() && len > 0.5) {
        return Quat::IDENTITY;
    }
    let q = q / len;
    if q.w < 0.0 {
        -q
    } else {
        q
    }
}

/// A lobe quantized.
pub fn qlobe(l: &NdfLobe) -> fb::QLobe {
    let q = frame_quat(l.frame);
    let c = |x: f32| (x * Q_QUAT).round().clamp(-Q_QUAT, Q_QUAT) as i16;
    fb::QLobe::new(
        c(q.x),
        c(q.y),
        c(q.z),
        c(q.w),
        unorm16(l.weight),
        f16_bits(l.alpha.x.min(1.0)),
        f16_bits(l.alpha.y.min(1.0)),
    )
}

fn quat_of(q: &fb::QLobe) -> Quat {
    Quat::from_xyzw(q.qx() as f32, q.qy() as f32, q.qz() as f32, q.qw() as f32)
}

/// Whether a stored lobe decodes in range: a quaternion within 1% of unit length (the
/// encoder's rounding moves it by at most 3e-5), α binary16 in [0, 1].
pub fn lobe_ok(q: &fb::QLobe) -> bool {
    let len = quat_of(q).length() / Q_QUAT;
    (0.99..=1.01).contains(&len)
        && [q.alpha_x(), q.alpha_y()]
            .iter()
            .all(|&a| f16_ok(a) && from_f16(a) <= 1.0)
}

/// A verified stored lobe, decoded (the quaternion renormalised: the frame is orthonormal).
pub fn lobe(q: &fb::QLobe) -> NdfLobe {
    let r = quat_of(q).normalize();
    NdfLobe {
        weight: q.weight() as f32 / 65535.0,
        frame: Mat3::from_quat(r),
        alpha: Vec2::new(from_f16(q.alpha_x()), from_f16(q.alpha_y())),
    }
}

/// Full moments quantized.
pub fn qmoments(m: &MaterialMoments) -> fb::QMoments {
    fb::QMoments::new(
        &v3h(m.c),
        &v3h(m.mc),
        f16_bits(m.s),
        f16_bits(m.ms),
        f16_bits(m.m),
        f16_bits(m.f90),
        f16_bits(m.mf90),
    )
}

/// Whether stored full moments decode to finite values in [0, 65504].
pub fn moments_ok(q: &fb::QMoments) -> bool {
    v3h_ok(q.base())
        && v3h_ok(q.metal_base())
        && [
            q.specular(),
            q.metal_specular(),
            q.metallic(),
            q.f90(),
            q.metal_f90(),
        ]
        .iter()
        .all(|&b| f16_ok(b))
}

/// Stored full moments, decoded.
pub fn moments(q: &fb::QMoments) -> MaterialMoments {
    MaterialMoments {
        c: from_v3h(q.base()),
        mc: from_v3h(q.metal_base()),
        s: from_f16(q.specular()),
        ms: from_f16(q.metal_specular()),
        m: from_f16(q.metallic()),
        f90: from_f16(q.f90()),
        mf90: from_f16(q.metal_f90()),
    }
}

/// Dielectric moments quantized.
pub fn qdielectric_moments(m: &MaterialMoments) -> fb::QDielectricMoments {
    fb::QDielectricMoments::new(&v3h(m.c), f16_bits(m.s), f16_bits(m.f90))
}

/// Whether stored dielectric moments decode to finite values in [0, 65504].
pub fn dielectric_moments_ok(q: &fb::QDielectricMoments) -> bool {
    v3h_ok(q.base()) && f16_ok(q.specular()) && f16_ok(q.f90())
}

/// Stored dielectric moments, decoded.
pub fn dielectric_moments(q: &fb::QDielectricMoments) -> MaterialMoments {
    MaterialMoments {
        c: from_v3h(q.base()),
        s: from_f16(q.specular()),
        f90: from_f16(q.f90()),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::sggx::Sggx;

    fn sggx(l: &NdfLobe) -> Sggx {
        Sggx::from_frame_roughness(l.frame, l.alpha)
    }

    /// Hard lobes round-trip: a reflected frame (determinant −1), a rank-deficient lobe (a
    /// flat voxel: α at its floor on one axis), an isotropic one, a zero-weight one. The SGGX
    /// matrix (what the ABSDF sees, Eq. 8) agrees within 1e-3 of its largest entry; α within
    /// binary16's 2^-11 relative; the weight within 1e-5.
    #[test]
    fn hard_lobes_round_trip() {
        let rot = Mat3::from_quat(Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0));
        let reflected = Mat3::from_cols(-rot.x_axis, rot.y_axis, rot.z_axis);
        let cases = [
            (rot, Vec2::new(0.2, 0.7), 0.4),
            (reflected, Vec2::new(0.05, 0.9), 0.6),
            (rot, Vec2::new(crate::math::microfacet::ALPHA_MIN, 1.0), 1.0),
            (Mat3::IDENTITY, Vec2::ONE, 0.0),
            (
                Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X),
                Vec2::splat(0.5),
                1.0,
            ),
        ];
        for (frame, alpha, weight) in cases {
            let l = NdfLobe {
                weight,
                frame,
                alpha,
            };
            let q = qlobe(&l);
            assert!(lobe_ok(&q));
            let back = lobe(&q);
            assert!(back.frame.is_finite() && (back.frame.determinant() - 1.0).abs() < 1e-4);
            assert!((back.weight - weight).abs() < 1e-5);
            for k in 0..2 {
                let (a, b) = (alpha[k], back.alpha[k]);
                assert!((a - b).abs() <= a * 4.9e-4, "alpha {a} -> {b}");
            }
            let (s, t) = (sggx(&l), sggx(&back));
            let e = [
                s.xx - t.xx,
                s.yy - t.yy,
                s.zz - t.zz,
                s.xy - t.xy,
                s.xz - t.xz,
                s.yz - t.yz,
            ];
            let big = [s.xx, s.yy, s.zz].iter().fold(0f32, |m, x| m.max(x.abs()));
            assert!(e.iter().all(|x| x.abs() <= 1e-3 * big), "{frame}: {e:?}");
        }
        // A frame that is no rotation at all (never baked) still decodes to a unit frame.
        let bad = NdfLobe {
            weight: 1.0,
            frame: Mat3::ZERO,
            alpha: Vec2::new(f32::NAN, 2.0),
        };
        let q = qlobe(&bad);
        assert!(lobe_ok(&q));
        let back = lobe(&q);
        assert!(back.frame.is_finite() && back.alpha.cmple(Vec2::ONE).all());
    }

    /// Moments round-trip within binary16's relative 2^-11 (plus its subnormal step near
    /// zero), clamp to [0, 65504], and never decode to NaN.
    #[test]
    fn moments_round_trip_and_clamp() {
        let m = MaterialMoments {
            c: Vec3::new(0.8, 0.001, 0.0),
            mc: Vec3::new(0.3, 0.2, 0.1),
            s: 0.5,
            ms: 1e-5,
            m: 1.0,
            f90: 0.99,
            mf90: 0.25,
        };
        let back = moments(&qmoments(&m));
        let pairs = [
            (m.c, back.c),
            (m.mc, back.mc),
            (
                Vec3::new(m.s, m.ms, m.m),
                Vec3::new(back.s, back.ms, back.m),
            ),
            (
                Vec3::new(m.f90, m.mf90, 0.0),
                Vec3::new(back.f90, back.mf90, 0.0),
            ),
        ];
        for (a, b) in pairs {
            assert!(((a - b).abs().cmple(a.abs() * 4.9e-4 + Vec3::splat(6e-8))).all());
        }
        let d = dielectric_moments(&qdielectric_moments(&m));
        assert!((d.c - m.c).abs().max_element() < 1e-3 && d.m == 0.0);
        let wild = MaterialMoments {
            c: Vec3::new(f32::NAN, -1.0, 1e9),
            s: f32::INFINITY,
            ..m
        };
        let q = qmoments(&wild);
        assert!(moments_ok(&q));
        let w = moments(&q);
        assert_eq!(w.c, Vec3::new(0.0, 0.0, F16_MAX));
        assert_eq!(w.s, F16_MAX);
        // The verifier refuses binary16 NaN, infinity and negative values.
        for bits in [0x7e00u16, 0x7c00, 0xbc00] {
            assert!(!f16_ok(bits));
        }
    }
}
