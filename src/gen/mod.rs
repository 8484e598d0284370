//! Generators for the hard cases of the paper, each a deterministic glTF (GLB) scene whose
//! triangle count is set by a target (`--triangles`), from thousands to millions.
//!
//! | name | what it stresses |
//! |---|---|
//! | `plane45` | Fig. 6 double counting: a plane at 45° to the voxel grid |
//! | `lattice` | correlated partial occlusion: a tower of thin beams |
//! | `foliage` | unstructured geometry: many small, randomly oriented, alpha-cut leaf quads |
//! | `displaced-sphere` | Fig. 5: base colour that depends on the normal's orientation |
//! | `rings` | glossy, curved, anisotropic aggregates: brushed-metal rings (a chandelier) |
//! | `buildings` | a block of distinct buildings, some instanced, windows via EXT_mesh_gpu_instancing |

pub mod glb;
pub mod shapes;

use std::f32::consts::PI;
use std::path::Path;

use glam::{Mat4, Quat, Vec3};

use crate::math::rng::Pcg32;
use glb::{MaterialData, MeshData, NodeData, SceneData};
use shapes::*;

/// Names accepted by [`generate`].
pub const NAMES: &[&str] = &[
    "plane45",
    "lattice",
    "foliage",
    "displaced-sphere",
    "rings",
    "buildings",
];

/// Generation settings.
#[derive(Clone, Copy, Debug)]
pub struct GenSettings {
    /// Approximate number of triangles placed in the world.
    pub triangles: usize,
    /// Make every material Lambertian (metallic 0, specularFactor 0), for checks against other
    /// renderers that implement only diffuse reflection exactly.
    pub lambertian: bool,
    /// Seed of the generator's random numbers: equal settings give equal bytes.
    pub seed: u64,
}

impl Default for GenSettings {
    fn default() -> Self {
        GenSettings {
            triangles: 20_000,
            lambertian: false,
            seed: 1,
        }
    }
}

/// Fig. 6: a unit plane through the origin containing +Y, turned 45° about Y, red.
fn plane45(s: &GenSettings) -> SceneData {
    let n = ((s.triangles as f32 / 2.0).sqrt() as usize).max(1);
    let mut m = quad(Vec3::new(-0.5, -0.5, 0.0), Vec3::X, Vec3::Y, n);
    m.transform(Mat4::from_rotation_y(PI / 4.0));
    SceneData::single(m, MaterialData::new("red", [0.8, 0.05, 0.05], 0.0, 0.5))
}

/// A tower of thin beams on a k×k×h lattice.
fn lattice(s: &GenSettings) -> SceneData {
    // Beams per level ≈ 3 k², levels 3k; 12 triangles per beam at subdivision 1.
    let k = (((s.triangles as f32 / 12.0) / 9.0).cbrt().floor() as usize).clamp(2, 200);
    let sub = ((s.triangles as f32 / (12.0 * 9.0 * (k * k * k) as f32)).sqrt() as usize).max(1);
    let levels = 3 * k;
    let cell = 1.0 / k as f32;
    let r = 0.06 * cell;
    let mut m = MeshData::default();
    let origin = Vec3::new(-0.5, 0.0, -0.5);
    for y in 0..=levels {
        for i in 0..=k {
            for j in 0..=k {
                let p = origin + Vec3::new(i as f32, y as f32, j as f32) * cell;
                if i < k {
                    m.append(&beam(p, p + Vec3::X * cell, r, sub));
                }
                if j < k {
                    m.append(&beam(p, p + Vec3::Z * cell, r, sub));
                }
                if y < levels && (i == 0 || i == k || j == 0 || j == k || (i + j + y) % 3 == 0) {
                    m.append(&beam(p, p + Vec3::Y * cell, r, sub));
                }
            }
        }
    }
    SceneData::single(m, MaterialData::new("steel", [0.6, 0.6, 0.62], 0.8, 0.4))
}

/// A leaf-shaped alpha mask (an ellipse with a pointed tip), green.
fn leaf_texture() -> (u32, u32, Vec<u8>) {
    let n = 64u32;
    let mut px = Vec::with_capacity((n * n * 4) as usize);
    for y in 0..n {
        for x in 0..n {
            let u = (x as f32 + 0.5) / n as f32 * 2.0 - 1.0;
            let v = (y as f32 + 0.5) / n as f32;
            // Half-width along the leaf: sin profile from stem (v=0) to tip (v=1).
            let w = 0.9 * (PI * v).sin().powf(0.8);
            let inside = u.abs() < w;
            let shade = 0.75 + 0.25 * (1.0 - u.abs());
            px.extend([
                (60.0 * shade) as u8,
                (140.0 * shade) as u8,
                (40.0 * shade) as u8,
                if inside { 255 } else { 0 },
            ]);
        }
    }
    (n, n, px)
}

/// A crown of randomly oriented alpha-cut leaves on a trunk.
fn foliage(s: &GenSettings) -> SceneData {
    let mut rng = Pcg32::new(s.seed, 11);
    let trunk = cylinder(Vec3::ZERO, 0.04, 0.6, 16, 4);
    let trunk_tris = trunk.triangle_count();
    let leaves = (s.triangles.saturating_sub(trunk_tris) / 2).max(50);
    // Leaf size so that the crown's total leaf area stays ~ 3x its cross-section.
    let crown_r = 0.4f32;
    let size = (3.0 * PI * crown_r * crown_r / leaves as f32)
        .sqrt()
        .clamp(0.002, 0.2);
    let mut m = MeshData::default();
    let center = Vec3::new(0.0, 0.75, 0.0);
    for _ in 0..leaves {
        // Uniform in the ball.
        let p = loop {
            let q = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - Vec3::ONE;
            if q.length_squared() <= 1.0 {
                break q;
            }
        };
        let pos = center + p * crown_r;
        let axis = crate::math::sampling::square_to_uniform_sphere(rng.next_2d());
        let rot = Quat::from_axis_angle(axis, rng.next_f32() * 2.0 * PI);
        let eu = rot * Vec3::X * size;
        let ev = rot * Vec3::Y * size * 1.6;
        m.append(&quad(pos - 0.5 * eu, eu, ev, 1));
    }
    let mut leaf = MaterialData::new("leaf", [1.0, 1.0, 1.0], 0.0, 0.6);
    leaf.alpha_cutoff = Some(0.5);
    leaf.texture = Some(leaf_texture());
    SceneData {
        meshes: vec![vec![(trunk, 0)], vec![(m, 1)]],
        materials: vec![MaterialData::new("bark", [0.25, 0.16, 0.1], 0.0, 0.9), leaf],
        nodes: vec![
            NodeData {
                mesh: 0,
                matrix: Mat4::IDENTITY,
                gpu_instances: Vec::new(),
            },
            NodeData {
                mesh: 1,
                matrix: Mat4::IDENTITY,
                gpu_instances: Vec::new(),
            },
        ],
    }
}

/// Fig. 5: a sphere with high-frequency bumps whose faces are coloured by orientation: those
/// facing +X orange, −X blue, and up-facing ones white, so that the aggregate's colour depends on
/// the viewing direction.
fn displaced_sphere(s: &GenSettings) -> SceneData {
    let n = (((s.triangles as f32).sqrt() * 1.0) as usize).max(16);
    let freq = 6.0 + (n as f32 / 16.0).min(40.0);
    let sph = sphere(Vec3::ZERO, 0.5, n, |d| {
        0.08 * (freq * d.x).sin() * (freq * d.y).sin() * (freq * d.z).sin()
    });
    // Split triangles into three primitives by face normal.
    let mut parts = vec![
        MeshData::default(),
        MeshData::default(),
        MeshData::default(),
    ];
    for t in sph.indices.chunks_exact(3) {
        let [a, b, c] = [t[0], t[1], t[2]].map(|i| sph.positions[i as usize]);
        let mut nrm = (b - a).cross(c - a).normalize_or_zero();
        if nrm.dot(a) < 0.0 {
            nrm = -nrm;
        }
        let k = if nrm.y > 0.6 {
            2
        } else if nrm.x >= 0.0 {
            0
        } else {
            1
        };
        let part = &mut parts[k];
        let base = part.positions.len() as u32;
        for &i in t {
            part.positions.push(sph.positions[i as usize]);
            part.normals.push(sph.normals[i as usize]);
        }
        part.indices.extend([base, base + 1, base + 2]);
    }
    SceneData {
        meshes: vec![parts.into_iter().enumerate().map(|(k, p)| (p, k)).collect()],
        materials: vec![
            MaterialData::new("facing+x", [0.9, 0.45, 0.05], 0.0, 0.5),
            MaterialData::new("facing-x", [0.05, 0.2, 0.9], 0.0, 0.5),
            MaterialData::new("facing-up", [0.9, 0.9, 0.9], 0.0, 0.5),
        ],
        nodes: vec![NodeData {
            mesh: 0,
            matrix: Mat4::IDENTITY,
            gpu_instances: Vec::new(),
        }],
    }
}

/// Brushed-metal rings: tilted thin tori around a vertical axis, gold, glossy.
fn rings(s: &GenSettings) -> SceneData {
    let count = 12usize;
    let per = (s.triangles / count).max(64);
    let tube = ((per as f32 / 2.0 / 8.0).sqrt() as usize).clamp(4, 64);
    let around = (per / (2 * tube)).max(16);
    let mut m = MeshData::default();
    for i in 0..count {
        let mut t = torus(0.3 + 0.015 * (i % 3) as f32, 0.012, around, tube);
        let a = i as f32 / count as f32 * PI;
        t.transform(
            Mat4::from_translation(Vec3::new(0.0, 0.5, 0.0))
                * Mat4::from_rotation_y(a)
                * Mat4::from_rotation_x(PI / 2.0 - 0.25 * (i % 2) as f32),
        );
        m.append(&t);
    }
    // A central column to cast shadows through the rings.
    m.append(&cylinder(Vec3::new(0.0, 0.1, 0.0), 0.02, 0.8, 24, 2));
    SceneData::single(m, MaterialData::new("gold", [1.0, 0.78, 0.34], 1.0, 0.3))
}

/// A block of buildings with distinct footprints, heights and colours on a ground slab. Every
/// third building reuses an earlier mesh (node instancing); windows are one small box mesh
/// repeated by EXT_mesh_gpu_instancing.
fn buildings(s: &GenSettings) -> SceneData {
    let mut rng = Pcg32::new(s.seed, 23);
    let grid = 4usize;
    let mut scene = SceneData::default();
    let palette = [
        [0.7, 0.55, 0.45],
        [0.55, 0.6, 0.65],
        [0.8, 0.78, 0.7],
        [0.45, 0.35, 0.3],
        [0.6, 0.65, 0.5],
    ];
    for (k, c) in palette.iter().enumerate() {
        scene
            .materials
            .push(MaterialData::new(&format!("facade{k}"), *c, 0.0, 0.8));
    }
    scene
        .materials
        .push(MaterialData::new("glass", [0.05, 0.07, 0.1], 0.0, 0.15));
    scene
        .materials
        .push(MaterialData::new("ground", [0.3, 0.3, 0.3], 0.0, 0.95));
    let glass = palette.len();
    let ground_mat = glass + 1;
    // Ground.
    scene.meshes.push(vec![(
        cuboid(Vec3::new(0.0, -0.01, 0.0), Vec3::new(0.55, 0.01, 0.55), 4),
        ground_mat,
    )]);
    scene.nodes.push(NodeData {
        mesh: 0,
        matrix: Mat4::IDENTITY,
        gpu_instances: Vec::new(),
    });
    // Windows: one shared mesh.
    let win_half = Vec3::new(0.012, 0.016, 0.004);
    scene
        .meshes
        .push(vec![(cuboid(Vec3::ZERO, win_half, 1), glass)]);
    let window_mesh = 1;
    let lot = 1.0 / grid as f32;
    let mut windows = Vec::new();
    let mut building_meshes: Vec<(usize, Vec3, f32)> = Vec::new();
    // Façades start unsubdivided; their subdivision is set below, once the windows are known.
    let sub = 1;
    for gz in 0..grid {
        for gx in 0..grid {
            let center = Vec3::new(
                (gx as f32 + 0.5) * lot - 0.5,
                0.0,
                (gz as f32 + 0.5) * lot - 0.5,
            );
            let idx = gz * grid + gx;
            let (mesh, half, height) = if idx % 3 == 2 && !building_meshes.is_empty() {
                // Reuse an earlier building: same mesh, another node.
                building_meshes[(idx / 3) % building_meshes.len()]
            } else {
                let hx = lot * (0.25 + 0.15 * rng.next_f32());
                let hz = lot * (0.25 + 0.15 * rng.next_f32());
                let height = 0.15 + 0.6 * rng.next_f32();
                let half = Vec3::new(hx, 0.5 * height, hz);
                let mat = (rng.next_u32() as usize) % palette.len();
                scene.meshes.push(vec![(
                    cuboid(Vec3::new(0.0, 0.5 * height, 0.0), half, sub),
                    mat,
                )]);
                let entry = (scene.meshes.len() - 1, half, height);
                building_meshes.push(entry);
                entry
            };
            scene.nodes.push(NodeData {
                mesh,
                matrix: Mat4::from_translation(center),
                gpu_instances: Vec::new(),
            });
            // Windows on the four façades, on a regular grid.
            let rows = ((height / 0.06) as usize).max(1);
            for face in 0..4 {
                let (axis, along, extent) = match face {
                    0 => (Vec3::Z, Vec3::X, half.x),
                    1 => (-Vec3::Z, Vec3::X, half.x),
                    2 => (Vec3::X, Vec3::Z, half.z),
                    _ => (-Vec3::X, Vec3::Z, half.z),
                };
                let depth = if face < 2 { half.z } else { half.x };
                let cols = ((2.0 * extent / 0.05) as usize).max(1);
                for r in 0..rows {
                    for c in 0..cols {
                        let y = (r as f32 + 0.5) / rows as f32 * height;
                        let a = ((c as f32 + 0.5) / cols as f32 * 2.0 - 1.0) * extent * 0.85;
                        let p = center + axis * (depth + win_half.z) + along * a + Vec3::Y * y;
                        let rot = Quat::from_rotation_arc(Vec3::Z, axis);
                        windows.push((p, rot, Vec3::ONE));
                    }
                }
            }
        }
    }
    // Subdivide the façades so that the placed triangles reach the target: the windows are a
    // fixed count, the façades (12 sub² triangles per placed building) take the rest.
    let placements = (grid * grid) as f32;
    let rest = s.triangles.saturating_sub(windows.len() * 12 + 12 * 16) as f32;
    let sub = ((rest / (12.0 * placements)).sqrt() as usize).clamp(1, 400);
    for &(mi, half, height) in &building_meshes {
        let mat = scene.meshes[mi][0].1;
        scene.meshes[mi] = vec![(cuboid(Vec3::new(0.0, 0.5 * height, 0.0), half, sub), mat)];
    }
    scene.nodes.push(NodeData {
        mesh: window_mesh,
        matrix: Mat4::IDENTITY,
        gpu_instances: windows,
    });
    scene
}

/// Builds a named scene. `None` for an unknown name.
pub fn generate(name: &str, settings: &GenSettings) -> Option<SceneData> {
    let mut s = match name {
        "plane45" => plane45(settings),
        "lattice" => lattice(settings),
        "foliage" => foliage(settings),
        "displaced-sphere" => displaced_sphere(settings),
        "rings" => rings(settings),
        "buildings" => buildings(settings),
        _ => return None,
    };
    if settings.lambertian {
        s.make_lambertian();
    }
    Some(s)
}

/// Generates `name` and writes `dir/name.glb` atomically; returns the path and the number of
/// triangles placed.
pub fn write(
    name: &str,
    settings: &GenSettings,
    dir: &Path,
    quantize: bool,
) -> Result<(std::path::PathBuf, usize), String> {
    let scene = generate(name, settings).ok_or_else(|| {
        format!(
            "unknown scene '{name}'; choose one of: {}",
            NAMES.join(", ")
        )
    })?;
    let path = dir.join(format!("{name}.glb"));
    let bytes = glb::to_glb(&scene, quantize);
    crate::util::write_atomic(&path, |tmp| {
        std::fs::write(tmp, &bytes).map_err(|e| e.to_string())
    })?;
    Ok((path, scene.instanced_triangles()))
}
