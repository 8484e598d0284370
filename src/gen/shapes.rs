//! Primitive shapes for the generators.

use std::f32::consts::PI;

use glam::{Vec2, Vec3};

use super::glb::MeshData;

/// A grid of `nu × nv` quads on the parametric surface `f(u, v) -> (position, normal)` over
/// [0, 1]², with UVs (u, v).
pub fn param_surface(nu: usize, nv: usize, f: impl Fn(f32, f32) -> (Vec3, Vec3)) -> MeshData {
    let mut m = MeshData::default();
    for j in 0..=nv {
        for i in 0..=nu {
            let (u, v) = (i as f32 / nu as f32, j as f32 / nv as f32);
            let (p, n) = f(u, v);
            m.positions.push(p);
            m.normals.push(n.normalize_or(Vec3::Y));
            m.uvs.push(Vec2::new(u, v));
        }
    }
    let row = nu as u32 + 1;
    for j in 0..nv as u32 {
        for i in 0..nu as u32 {
            let a = j * row + i;
            let (b, c, d) = (a + 1, a + row, a + row + 1);
            m.indices.extend([a, b, d, a, d, c]);
        }
    }
    m
}

/// A flat quad `origin + u·eu + v·ev`, subdivided `n × n`, normal `eu × ev`.
pub fn quad(origin: Vec3, eu: Vec3, ev: Vec3, n: usize) -> MeshData {
    let normal = eu.cross(ev).normalize_or(Vec3::Y);
    param_surface(n.max(1), n.max(1), |u, v| {
        (origin + u * eu + v * ev, normal)
    })
}

/// An axis-aligned box of the given centre and half extents, flat-shaded (each face subdivided
/// `n × n`).
pub fn cuboid(center: Vec3, half: Vec3, n: usize) -> MeshData {
    let mut m = MeshData::default();
    let axes = [Vec3::X, Vec3::Y, Vec3::Z];
    for a in 0..3 {
        let (b, c) = ((a + 1) % 3, (a + 2) % 3);
        for s in [-1.0f32, 1.0] {
            let nrm = axes[a] * s;
            let eu = axes[b] * 2.0 * half[b];
            let ev = axes[c] * 2.0 * half[c];
            let origin = center + nrm * half[a] - 0.5 * eu - 0.5 * ev;
            // Orient so that eu × ev points along the outward normal.
            let q = if eu.cross(ev).dot(nrm) > 0.0 {
                quad(origin, eu, ev, n)
            } else {
                quad(origin, ev, eu, n)
            };
            m.append(&q);
        }
    }
    m
}

/// A beam (box) from `a` to `b` with square cross-section of half width `r`.
pub fn beam(a: Vec3, b: Vec3, r: f32, n: usize) -> MeshData {
    let d = b - a;
    let len = d.length();
    let mut m = cuboid(
        Vec3::new(0.0, 0.5 * len, 0.0),
        Vec3::new(r, 0.5 * len, r),
        n,
    );
    let rot = glam::Quat::from_rotation_arc(Vec3::Y, d / len);
    m.transform(glam::Mat4::from_rotation_translation(rot, a));
    m
}

/// A UV sphere with `n` segments around and `n/2` from pole to pole, displaced along the normal
/// by `disp(direction)` (normals recomputed from the displaced surface by finite differences).
pub fn sphere(center: Vec3, radius: f32, n: usize, disp: impl Fn(Vec3) -> f32) -> MeshData {
    let pos = |u: f32, v: f32| {
        let theta = v.clamp(1e-4, 1.0 - 1e-4) * PI;
        let phi = u * 2.0 * PI;
        let d = Vec3::new(
            theta.sin() * phi.cos(),
            theta.cos(),
            theta.sin() * phi.sin(),
        );
        center + d * radius * (1.0 + disp(d))
    };
    let eps = 1e-3;
    param_surface(n, (n / 2).max(2), |u, v| {
        let p = pos(u, v);
        let du = pos(u + eps, v) - pos(u - eps, v);
        let dv = pos(u, v + eps) - pos(u, v - eps);
        let mut nrm = dv.cross(du);
        if nrm.dot(p - center) < 0.0 {
            nrm = -nrm;
        }
        (p, nrm)
    })
}

/// A torus in the xz plane: major radius `big`, tube radius `small`, `n` segments around.
pub fn torus(big: f32, small: f32, n: usize, tube: usize) -> MeshData {
    param_surface(n, tube, |u, v| {
        let (a, b) = (u * 2.0 * PI, v * 2.0 * PI);
        let ring = Vec3::new(a.cos(), 0.0, a.sin());
        let nrm = ring * b.cos() + Vec3::Y * b.sin();
        (ring * big + nrm * small, nrm)
    })
}

/// An open cylinder along +Y from `base`, radius `r`, height `h`.
pub fn cylinder(base: Vec3, r: f32, h: f32, n: usize, rows: usize) -> MeshData {
    param_surface(n, rows, |u, v| {
        let a = u * 2.0 * PI;
        let nrm = Vec3::new(a.cos(), 0.0, a.sin());
        (base + nrm * r + Vec3::Y * h * v, nrm)
    })
}
