//! The decoded form of one level, as the bake produces it and [`crate::format::Aggregate::read_level`]
//! returns it: every voxel's statistics (ABSDF inputs, truncated ellipsoid, interior visibility
//! tree, exposure) and every boundary face's visibility tree.

use crate::absdf::VoxelAppearance;
use crate::math::haar::SparseHaar;
use crate::spatial::{Ellipsoid, Face, Grid};

/// A voxel's baked data.
#[derive(Clone, Debug, PartialEq)]
pub struct VoxelData {
    /// Morton key in its level.
    pub key: u64,
    /// Surface area inside the voxel (world units²).
    pub area: f64,
    /// Fraction of that area that exists after cut-outs.
    pub coverage: f32,
    /// The ABSDF inputs.
    pub appearance: VoxelAppearance,
    /// The truncated ellipsoid's ellipsoid.
    pub ellipsoid: Ellipsoid,
    /// The AIV (Eq. 25) as a sparse Haar tree.
    pub aiv: SparseHaar,
    /// Exposure η in [1/16, 1]: how much the visibility of the voxel's surfaces concentrates
    /// on some of their sides (see the bake's interior visibility); 1 for an open sheet, 1/2
    /// for a solid.
    pub exposure: f32,
}

/// A boundary face's baked data.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceData {
    /// The face.
    pub face: Face,
    /// The ABV (Eq. 26) as a sparse Haar tree.
    pub abv: SparseHaar,
}

/// One baked level.
#[derive(Clone, Debug, PartialEq)]
pub struct LevelData {
    /// The level's grid.
    pub grid: Grid,
    /// Sorted by Morton key.
    pub voxels: Vec<VoxelData>,
    /// Boundary faces, sorted by voxel key, then direction.
    pub faces: Vec<FaceData>,
    /// Rays traced for the interior and boundary visibility.
    pub rays: u64,
}
