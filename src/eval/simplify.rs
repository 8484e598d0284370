//! The mesh-simplification baseline of the quality study: every mesh of a scene simplified with
//! meshoptimizer (the `meshopt` crate) until the scene's geometry fits a memory budget, then
//! rendered by the reference renderer.

use glam::{Vec2, Vec3};

use crate::scene::{Mesh, Scene};

/// Bytes a renderer holds per vertex: position, normal (f32×3 each) and UV (f32×2).
pub const VERTEX_BYTES: usize = 32;
/// Bytes per triangle: three u32 indices.
pub const TRIANGLE_BYTES: usize = 12;

/// Geometry bytes of one mesh (normals and UVs counted whether present or not, as a renderer
/// that needs them at all would store them).
pub fn mesh_bytes(m: &Mesh) -> usize {
    m.positions.len() * VERTEX_BYTES + m.triangles.len() * TRIANGLE_BYTES
}

/// Geometry bytes of a scene: each mesh once (instances share it). Textures are not counted,
/// and the simplified scene keeps them.
pub fn scene_bytes(scene: &Scene) -> usize {
    scene.meshes.iter().map(mesh_bytes).sum()
}

/// What [`simplify_to_budget`] did.
#[derive(Clone, Debug)]
pub struct Simplified {
    /// The simplified scene.
    pub scene: Scene,
    /// Geometry bytes before.
    pub bytes_before: usize,
    /// Geometry bytes after.
    pub bytes_after: usize,
    /// Triangles before.
    pub triangles_before: usize,
    /// Triangles after.
    pub triangles_after: usize,
    /// The mesh already fitted the budget and was left as it is.
    pub unchanged: bool,
}

/// Simplifies one mesh to about `target` triangles (at least one when the mesh has any):
/// meshoptimizer's edge collapse first, its sloppy clustering where topology stops the collapse
/// short of 1.5 × the target. Unused vertices are dropped.
pub fn simplify_mesh(m: &Mesh, target: usize) -> Mesh {
    let target = target.max(1);
    if m.triangles.len() <= target {
        return m.clone();
    }
    // Weld corners that share a position (many assets are triangle soups, with no shared
    // vertices): each index points at the first vertex with its position, so that the edge
    // collapse sees the connectivity. The survivor's normal and UV stand for the others.
    let mut first: std::collections::HashMap<[u32; 3], u32> = std::collections::HashMap::new();
    let rep: Vec<u32> = m
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            *first
                .entry(p.to_array().map(f32::to_bits))
                .or_insert(i as u32)
        })
        .collect();
    let indices: Vec<u32> = m
        .triangles
        .iter()
        .flatten()
        .map(|&i| rep.get(i as usize).copied().unwrap_or(i))
        .collect();
    let bytes: Vec<u8> = m
        .positions
        .iter()
        .flat_map(|p| p.to_array())
        .flat_map(f32::to_ne_bytes)
        .collect();
    let Ok(adapter) = meshopt::VertexDataAdapter::new(&bytes, 12, 0) else {
        return m.clone();
    };
    let mut out = meshopt::simplify(
        &indices,
        &adapter,
        target * 3,
        1.0,
        // No `Prune`: with an error bound this loose it deletes whole components.
        meshopt::SimplifyOptions::None,
        None,
    );
    if out.len() > target * 3 * 3 / 2 {
        // Sloppy clustering can erase thin parts entirely (a lattice's rods collapse into
        // degenerate triangles): keep it only where it leaves at least half the target.
        let sloppy = meshopt::simplify_sloppy(&indices, &adapter, target * 3, 1.0, None);
        if sloppy.len() >= target * 3 / 2 {
            out = sloppy;
        }
    }
    compact(m, &out)
}

/// A mesh with `indices` over `m`'s vertices, keeping only the vertices they use.
fn compact(m: &Mesh, indices: &[u32]) -> Mesh {
    let mut remap = vec![u32::MAX; m.positions.len()];
    let mut positions: Vec<Vec3> = Vec::new();
    let mut normals: Vec<Vec3> = Vec::new();
    let mut uvs: Vec<Vec2> = Vec::new();
    let mut triangles = Vec::with_capacity(indices.len() / 3);
    for t in indices.chunks_exact(3) {
        let mut tri = [0u32; 3];
        for (k, &i) in t.iter().enumerate() {
            let i = i as usize;
            if remap[i] == u32::MAX {
                remap[i] = positions.len() as u32;
                positions.push(m.positions[i]);
                if !m.normals.is_empty() {
                    normals.push(m.normals[i]);
                }
                if !m.uvs.is_empty() {
                    uvs.push(m.uvs[i]);
                }
            }
            tri[k] = remap[i];
        }
        triangles.push(tri);
    }
    Mesh {
        name: m.name.clone(),
        positions,
        normals,
        uvs,
        triangles,
        material: m.material,
    }
}

/// Simplifies every mesh of `scene` by one common ratio, refined a few times, so that the
/// geometry takes about `budget` bytes ([`scene_bytes`]).
pub fn simplify_to_budget(scene: &Scene, budget: usize) -> Simplified {
    let before = scene_bytes(scene);
    let tris = scene.unique_triangle_count();
    if before <= budget || tris == 0 {
        return Simplified {
            scene: scene.clone(),
            bytes_before: before,
            bytes_after: before,
            triangles_before: tris,
            triangles_after: tris,
            unchanged: true,
        };
    }
    let mut ratio = budget as f64 / before as f64;
    let mut best: Option<(Scene, usize)> = None;
    for _ in 0..4 {
        let mut s = scene.clone();
        s.meshes = scene
            .meshes
            .iter()
            .map(|m| simplify_mesh(m, (m.triangles.len() as f64 * ratio).round() as usize))
            .collect();
        let b = scene_bytes(&s);
        // An empty mesh is no simplification: it wins only if nothing else was found.
        let better = match &best {
            None => true,
            Some((_, 0)) => b > 0,
            Some((_, bb)) => {
                b > 0 && (b as f64 - budget as f64).abs() < (*bb as f64 - budget as f64).abs()
            }
        };
        if better {
            best = Some((s, b));
        }
        let err = budget as f64 / b.max(1) as f64;
        if (err - 1.0).abs() < 0.05 {
            break;
        }
        ratio = (ratio * err).min(1.0);
    }
    let (s, b) = best.expect("one pass ran");
    Simplified {
        triangles_after: s.unique_triangle_count(),
        scene: s,
        bytes_before: before,
        bytes_after: b,
        triangles_before: tris,
        unchanged: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid_mesh(n: u32) -> Mesh {
        let mut m = Mesh::default();
        for y in 0..=n {
            for x in 0..=n {
                let (u, v) = (x as f32 / n as f32, y as f32 / n as f32);
                m.positions.push(Vec3::new(u, (u * 6.0).sin() * 0.1, v));
                m.normals.push(Vec3::Y);
                m.uvs.push(Vec2::new(u, v));
            }
        }
        for y in 0..n {
            for x in 0..n {
                let i = y * (n + 1) + x;
                m.triangles.push([i, i + n + 1, i + 1]);
                m.triangles.push([i + 1, i + n + 1, i + n + 2]);
            }
        }
        m
    }

    #[test]
    fn meets_a_budget_and_keeps_attributes_consistent() {
        let mut scene = Scene::default();
        scene.meshes.push(grid_mesh(64));
        let before = scene_bytes(&scene);
        let s = simplify_to_budget(&scene, before / 10);
        assert!(!s.unchanged);
        let ratio = s.bytes_after as f64 / (before / 10) as f64;
        assert!((0.5..1.5).contains(&ratio), "budget missed: {ratio}");
        let m = &s.scene.meshes[0];
        assert_eq!(m.normals.len(), m.positions.len());
        assert_eq!(m.uvs.len(), m.positions.len());
        assert!(m
            .triangles
            .iter()
            .flatten()
            .all(|&i| (i as usize) < m.positions.len()));
        // A budget above the mesh leaves it alone.
        assert!(simplify_to_budget(&scene, before * 2).unchanged);
    }

    /// A triangle soup (no shared vertices, as many assets are) is welded and simplified by
    /// edge collapse, not pruned to nothing or left untouched.
    /// Thin separate parts (a lattice of rods) are simplified, not erased: the result keeps
    /// triangles even where sloppy clustering would collapse every rod.
    #[test]
    fn thin_parts_are_not_erased() {
        let scene = crate::gen::generate(
            "lattice",
            &crate::gen::GenSettings {
                triangles: 6000,
                ..Default::default()
            },
        )
        .unwrap()
        .to_scene();
        let before = scene_bytes(&scene);
        let s = simplify_to_budget(&scene, before / 3);
        assert!(s.triangles_after > 0, "the lattice was erased");
        assert!(s.bytes_after < before, "nothing was simplified");
    }

    #[test]
    fn triangle_soups_simplify() {
        let g = grid_mesh(40);
        let mut soup = Mesh::default();
        for t in &g.triangles {
            let base = soup.positions.len() as u32;
            for &i in t {
                soup.positions.push(g.positions[i as usize]);
                soup.normals.push(g.normals[i as usize]);
                soup.uvs.push(g.uvs[i as usize]);
            }
            soup.triangles.push([base, base + 1, base + 2]);
        }
        let target = soup.triangles.len() / 4;
        let out = simplify_mesh(&soup, target);
        assert!(
            out.triangles.len() >= target / 2 && out.triangles.len() <= target * 3 / 2,
            "{} triangles for a target of {target}",
            out.triangles.len()
        );
        // Welding shares the vertices: fewer than three per triangle remain.
        assert!(out.positions.len() < out.triangles.len() * 3);
    }
}
