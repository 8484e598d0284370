//! The bake: from a scene to the per-level voxel statistics that the `.agg` format stores
//! (paper §7.1–§7.2). In progress: sparse voxelization with exact per-voxel areas and surface
//! sampling inside voxels, interior visibility maps, truncated-ellipsoid fits, boundary faces and their visibility maps, and one level baked in memory.

pub mod boundary;
pub mod boundary_visibility;
pub mod level;
pub mod primitive;
pub mod sampling;
pub mod visibility;
pub mod voxelize;
