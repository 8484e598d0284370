//! The conditioned-domain correction S of paper Eq. 21: the mass of the normalised microfacet
//! lobe D_mic(ω_h; n, α)/M5(α), a function of n centred on ω_h, inside the spherical lune
//! X = {n : n·ω_i > 0, n·ω_o > 0}. The lobe is replaced by its isotropic linearly transformed
//! cosine (Heitz et al. 2016) with inverse matrix M⁻¹ = diag(1/s, 1/s, 1) in ω_h's frame (table
//! M4); the lune is split into two spherical triangles, each mapped by M⁻¹, clipped to the
//! horizon and integrated against the clamped cosine in closed form (Lambert's polygon formula).
//! Derived from M4 when the tables load, so it lives with them ([`super::Tables::lune`]); the
//! ABSDF reads it.

use std::f32::consts::PI;

use glam::Vec3;

use crate::math::frame::Frame;
use crate::math::safe_acos;

/// ∫ over the spherical polygon (vertices, great-arc edges) of cos θ / π, clipped to z ≥ 0.
/// Orientation-independent (absolute value).
pub fn clamped_cosine_polygon(verts: &[Vec3]) -> f32 {
    // Clip the cone spanned by the vertices to the half-space z ≥ 0 (Sutherland–Hodgman on the
    // vectors: great circles are planes through the origin).
    let mut clipped = [Vec3::ZERO; 8];
    let mut n = 0usize;
    let k = verts.len();
    for i in 0..k {
        let a = verts[i];
        let b = verts[(i + 1) % k];
        if a.z >= 0.0 && n < 8 {
            clipped[n] = a;
            n += 1;
        }
        if (a.z >= 0.0) != (b.z >= 0.0) && n < 8 {
            let t = a.z / (a.z - b.z);
            clipped[n] = a + (b - a) * t;
            n += 1;
        }
    }
    if n < 3 {
        return 0.0;
    }
    let mut sum = 0.0f32;
    for i in 0..n {
        let a = clipped[i].normalize_or_zero();
        let b = clipped[(i + 1) % n].normalize_or_zero();
        let c = a.cross(b);
        let len = c.length();
        if len > 1e-12 {
            sum += safe_acos(a.dot(b)) * c.z / len;
        }
    }
    crate::math::finite_or_zero((sum / (2.0 * PI)).abs())
}

/// S(ω_i, ω_o) for the lobe centred on ω_h with LTC inverse scale `inv_s` (= 1/s from M4).
/// In [0, 1]; 1 when the lune contains the whole lobe, 0 for opposite directions.
pub fn lune_mass(wi: Vec3, wo: Vec3, wh: Vec3, inv_s: f32) -> f32 {
    let frame = Frame::from_z(wh);
    let map = |v: Vec3| {
        let l = frame.to_local(v);
        Vec3::new(l.x * inv_s, l.y * inv_s, l.z)
    };
    let v = wi.cross(wo);
    let vl = v.length();
    let total = if vl < 1e-6 {
        if wi.dot(wo) <= 0.0 {
            return 0.0;
        }
        // X is the hemisphere around ω_i: four exact triangles (ω_i, e_k, e_{k+1}).
        let f = Frame::from_z(wi);
        let e = [f.x, f.y, -f.x, -f.y];
        (0..4)
            .map(|k| clamped_cosine_polygon(&[map(wi), map(e[k]), map(e[(k + 1) % 4])]))
            .sum::<f32>()
    } else {
        let v = v / vl;
        let q1 = (wo - wo.dot(wi) * wi).normalize_or_zero();
        let q2 = (wi - wi.dot(wo) * wo).normalize_or_zero();
        clamped_cosine_polygon(&[map(v), map(q1), map(q2)])
            + clamped_cosine_polygon(&[map(-v), map(q2), map(q1)])
    };
    total.clamp(0.0, 1.0)
}

/// S(ω_i, ω_o; α) tabulated. The lobe is isotropic about ω_h, the bisector of ω_i and ω_o, so
/// the lune's mass depends on the angle between ω_i and ω_o and on α alone: a 2D table over
/// t = √cos(θ_io / 2) and √((α − α_min)/(1 − α_min)), built once from M4 with [`lune_mass`]
/// (whose LTC integral was a quarter of a voxel's shading), read bilinearly.
#[derive(Clone, Debug, PartialEq)]
pub struct LuneTable {
    data: Vec<f32>,
}

/// Table size along t and along α.
const LUNE_T: usize = 65;
const LUNE_A: usize = 33;

impl LuneTable {
    /// The table for the LTC scales `m4` gives (α ↦ 1/s).
    pub fn new(m4: &super::Table) -> LuneTable {
        let amin = crate::math::microfacet::ALPHA_MIN;
        let mut data = vec![0f32; LUNE_T * LUNE_A];
        for j in 0..LUNE_A {
            let ua = j as f32 / (LUNE_A - 1) as f32;
            let alpha = amin + (1.0 - amin) * ua * ua;
            let inv_s = m4.lookup1(&[alpha]);
            for i in 0..LUNE_T {
                let t = i as f32 / (LUNE_T - 1) as f32;
                let c = t * t; // cos(θ/2)
                let s = (1.0 - c * c).max(0.0).sqrt();
                let (wi, wo) = (Vec3::new(s, 0.0, c), Vec3::new(-s, 0.0, c));
                data[j * LUNE_T + i] = if c <= 0.0 {
                    0.0
                } else {
                    lune_mass(wi, wo, Vec3::Z, inv_s)
                };
            }
        }
        LuneTable { data }
    }

    /// S for directions with ω_i·ω_o = `cos_io` and microfacet roughness `alpha`.
    #[inline]
    pub fn lookup(&self, cos_io: f32, alpha: f32) -> f32 {
        self.at(Self::io_coord(cos_io), Self::alpha_coord(alpha))
    }

    /// The table's coordinate along the angle between ω_i and ω_o (`cos_io` = ω_i·ω_o): one per
    /// evaluation, shared by every lobe.
    #[inline]
    pub fn io_coord(cos_io: f32) -> f32 {
        let c = (0.5 * (1.0 + cos_io)).max(0.0).sqrt(); // cos(θ/2)
        c.sqrt().clamp(0.0, 1.0) * (LUNE_T - 1) as f32
    }

    /// The table's coordinate along the roughness: fixed per lobe, so it can be kept with it.
    #[inline]
    pub fn alpha_coord(alpha: f32) -> f32 {
        let amin = crate::math::microfacet::ALPHA_MIN;
        ((alpha - amin) / (1.0 - amin)).clamp(0.0, 1.0).sqrt() * (LUNE_A - 1) as f32
    }

    /// S at the coordinates of [`LuneTable::io_coord`] and [`LuneTable::alpha_coord`], read
    /// bilinearly.
    #[inline]
    pub fn at(&self, t: f32, ua: f32) -> f32 {
        if !(t.is_finite() && ua.is_finite()) {
            return 0.0;
        }
        let (i, j) = ((t as usize).min(LUNE_T - 2), (ua as usize).min(LUNE_A - 2));
        let (fx, fy) = (t - i as f32, ua - j as f32);
        let at = |i: usize, j: usize| self.data[j * LUNE_T + i];
        let a = at(i, j) + (at(i + 1, j) - at(i, j)) * fx;
        let b = at(i, j + 1) + (at(i + 1, j + 1) - at(i, j + 1)) * fx;
        (a + (b - a) * fy).clamp(0.0, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;
    use crate::math::sampling::square_to_uniform_sphere;

    /// Lambert's formula: the upper hemisphere as 4 triangles carries mass 1; a polygon below
    /// the horizon carries 0.
    #[test]
    fn polygon_known_values() {
        let e = [Vec3::X, Vec3::Y, -Vec3::X, -Vec3::Y];
        let total: f32 = (0..4)
            .map(|k| clamped_cosine_polygon(&[Vec3::Z, e[k], e[(k + 1) % 4]]))
            .sum();
        assert!((total - 1.0).abs() < 1e-5, "{total}");
        assert_eq!(clamped_cosine_polygon(&[-Vec3::Z, Vec3::X, Vec3::Y]), 0.0);
        // An octant straddling the horizon: half of the upper octant's 1/4.
        let v = clamped_cosine_polygon(&[Vec3::X, Vec3::Y, -Vec3::Z]);
        assert_eq!(v, 0.0, "no area above the horizon");
    }

    /// The lune mass against Monte Carlo of the LTC density (cos θ' of the transformed
    /// direction times the Jacobian): uniform sphere samples, 400k, tolerance 1%.
    #[test]
    fn lune_mass_matches_monte_carlo() {
        let mut rng = Pcg32::new(4, 2);
        for (wi, wo, inv_s) in [
            (Vec3::new(0.3, 0.1, 0.9), Vec3::new(-0.5, 0.2, 0.7), 3.0f32),
            (Vec3::new(0.9, 0.0, 0.1), Vec3::new(-0.9, 0.1, 0.2), 1.0),
            (Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 0.0, 1.0), 0.7),
            (Vec3::new(0.2, 0.9, -0.3), Vec3::new(0.5, -0.1, 0.8), 10.0),
        ] {
            let (wi, wo) = (wi.normalize(), wo.normalize());
            let wh = (wi + wo).normalize();
            let frame = Frame::from_z(wh);
            let s = 1.0 / inv_s;
            let n = 400_000;
            let mut acc = 0f64;
            for _ in 0..n {
                let w = square_to_uniform_sphere(rng.next_2d());
                if w.dot(wi) > 0.0 && w.dot(wo) > 0.0 {
                    let l = frame.to_local(w);
                    // LTC density c · D_ggx(c; s) in ω_h's frame.
                    if l.z > 0.0 {
                        let t = l.z * l.z * (s * s - 1.0) + 1.0;
                        acc += (l.z * s * s / (PI * t * t)) as f64;
                    }
                }
            }
            let mc = acc / n as f64 * 4.0 * std::f64::consts::PI;
            let ours = lune_mass(wi, wo, wh, inv_s) as f64;
            assert!(
                (ours - mc).abs() < 0.01 + 0.02 * mc,
                "{wi} {wo} 1/s={inv_s}: {ours} vs {mc}"
            );
        }
        assert_eq!(lune_mass(Vec3::Z, -Vec3::Z, Vec3::X, 1.0), 0.0);
    }

    /// The table against the exact lune mass, for random direction pairs and roughnesses: the
    /// bilinear error stays below 0.01 everywhere and 0.002 on average.
    #[test]
    fn lune_table_matches_lune_mass() {
        let t = crate::tables::Tables::embedded();
        let table = LuneTable::new(&t.m4);
        let mut rng = Pcg32::new(8, 3);
        let (mut worst, mut sum) = (0f32, 0f32);
        let n = 4000;
        for k in 0..n {
            let wi = square_to_uniform_sphere(rng.next_2d());
            let wo = square_to_uniform_sphere(rng.next_2d());
            let u = rng.next_f32();
            let alpha = if k % 2 == 0 { u * u } else { u }.max(crate::math::microfacet::ALPHA_MIN);
            let h = wi + wo;
            if h.length() < 1e-4 {
                continue;
            }
            let exact = lune_mass(wi, wo, h.normalize(), t.m4.lookup1(&[alpha]));
            let e = (table.lookup(wi.dot(wo), alpha) - exact).abs();
            worst = worst.max(e);
            sum += e;
        }
        let mean = sum / n as f32;
        assert!(worst < 0.01 && mean < 0.002, "worst {worst}, mean {mean}");
    }
}
