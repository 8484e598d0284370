//! Assemblies: scenes of many instances of a few assets, read from a manifest
//! ([`manifest`]), rendered with the LoD runtime and with the reference renderer.

pub mod lod;
pub mod manifest;

pub use manifest::{Asset, Manifest, ManifestError};
pub use lod::{render, Assembly, AssemblyError};
