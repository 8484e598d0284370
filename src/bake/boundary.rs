//! Boundary faces of a level (paper §7.1): the faces between occupied voxels and the empty
//! space connected to the outside, found by one flood fill from beyond the grid. Cavities
//! sealed inside the geometry do not count.

use std::collections::{BTreeSet, VecDeque};

use crate::spatial::{Face, UVec3Key, FACE_DIRS};

/// Boundary faces of the occupied set on a `res³` grid, in a deterministic order.
pub fn boundary_faces(occupied: &BTreeSet<UVec3Key>, res: u32) -> Vec<Face> {
    // Padded grid: coordinates −1..=res, stored shifted by one.
    let p = (res + 2) as usize;
    let idx =
        |x: i32, y: i32, z: i32| ((z + 1) as usize * p + (y + 1) as usize) * p + (x + 1) as usize;
    let mut solid = vec![false; p * p * p];
    for v in occupied {
        solid[idx(v.0 as i32, v.1 as i32, v.2 as i32)] = true;
    }
    let mut outside = vec![false; p * p * p];
    let mut queue = VecDeque::new();
    outside[idx(-1, -1, -1)] = true;
    queue.push_back((-1, -1, -1));
    let lim = res as i32;
    while let Some((x, y, z)) = queue.pop_front() {
        for (dx, dy, dz) in FACE_DIRS {
            let (nx, ny, nz) = (x + dx, y + dy, z + dz);
            if nx < -1 || ny < -1 || nz < -1 || nx > lim || ny > lim || nz > lim {
                continue;
            }
            let k = idx(nx, ny, nz);
            if !outside[k] && !solid[k] {
                outside[k] = true;
                queue.push_back((nx, ny, nz));
            }
        }
    }
    let mut faces = Vec::new();
    for v in occupied {
        for (d, (dx, dy, dz)) in FACE_DIRS.iter().enumerate() {
            if outside[idx(v.0 as i32 + dx, v.1 as i32 + dy, v.2 as i32 + dz)] {
                faces.push(Face {
                    voxel: *v,
                    dir: d as u8,
                });
            }
        }
    }
    faces
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_voxel_and_hollow_shell() {
        let one: BTreeSet<UVec3Key> = [UVec3Key(1, 1, 1)].into_iter().collect();
        assert_eq!(boundary_faces(&one, 4).len(), 6);
        // A 3³ shell with an empty centre: only the 6·9 outer faces, none facing the cavity.
        let mut shell = BTreeSet::new();
        for z in 0..3 {
            for y in 0..3 {
                for x in 0..3 {
                    if (x, y, z) != (1, 1, 1) {
                        shell.insert(UVec3Key(x, y, z));
                    }
                }
            }
        }
        let f = boundary_faces(&shell, 3);
        assert_eq!(f.len(), 54);
        // Voxels touching the grid's edge still get their outward faces.
        let corner: BTreeSet<UVec3Key> = [UVec3Key(0, 0, 0)].into_iter().collect();
        assert_eq!(boundary_faces(&corner, 1).len(), 6);
    }
}
