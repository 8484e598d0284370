//! The spatial core shared by the bake, the format and the runtime: the grid of a level,
//! Morton keys, voxel faces and their directions, the truncated ellipsoid (paper §6.1) with
//! its one ray test and its projected area (Eq. 24), and one 3D DDA.
//!
//! Everything that decides *where* something is lives here once, so that the bake and the
//! runtime agree by construction: the bake's P⁺ test of the boundary visibility (Eq. 26) and the
//! runtime's primitive hit are the same [`truncated_entry`] over the ray's interval in the
//! padded voxel, so the ABV is defined over exactly the rays the runtime counts as hits; the cone tracer and the volume baseline walk
//! the same [`Dda`]. This module depends on [`crate::math`] only.

mod dda;
mod ellipsoid;
mod face;
mod grid;
mod morton;

pub use dda::*;
pub use ellipsoid::*;
pub use face::*;
pub use grid::{box_interval, box_projected_area, Grid};
pub use morton::{demorton3, morton3};
