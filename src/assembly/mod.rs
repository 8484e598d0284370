//! Assemblies: scenes of many instances of a few assets, read from a manifest
//! ([`Manifest`]), rendered with the LoD runtime and with the reference renderer.

pub mod bake;
pub mod city;
pub mod forest;
pub mod generate;
mod hybrid;
mod lod;
mod manifest;
pub mod mesh;
mod opened;
pub mod render_file;

pub use hybrid::*;
pub use lod::*;
pub use manifest::*;
pub use opened::{LayerPick, OpenError, Opened, VoxelShade};

/// Whether a path names a manifest (a `.json` file) rather than an asset or an aggregate: what
/// the CLI's `render`, `reference` and `inspect` go by.
pub fn is_manifest(path: &std::path::Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
}
