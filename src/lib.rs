//! # aggtool
//!
//! Appearance-preserving level of detail after Zhou et al., "Efficient Scene Appearance
//! Aggregation for Level-of-Detail Rendering". The crate follows the pipeline:
//!
//! - [`math`]: pure math (sampling, spherical maps, microfacets) that knows nothing of scenes;
//! - [`spatial`]: the spatial core of bake, format and runtime: grid, Morton keys, faces, the
//!   truncated ellipsoid with its one ray test, the DDA;
//! - [`scene`] and [`import`]: the scene representation and the glTF/OBJ importers;
//! - [`tables`]: the five precomputed tables M1–M5 of the factorized ABSDF;
//! - [`bsdf`]: the surface material model of the paper (Eq. 11);
//! - [`absdf`]: the factorized aggregated BSDF of a voxel (Eq. 7–23) with sampling;
//! - [`trace`]: two-level BVH ray tracing (obvhs) with alpha cut-outs;
//! - [`bake`]: the sparse voxel hierarchy, per-voxel statistics and visibility, streamed to a file;
//! - [`format`]: the `.agg` container and its FlatBuffers schema: writer, verifying zero-copy reader;
//! - [`inspect`]: what a file holds (`aggtool inspect`), its settings as the bake's own;
//! - [`runtime`]: the LoD renderer of `.agg` aggregates (cone tracing, Algorithm 1, Eq. 30);
//! - [`film`]: the camera, images and the one image loop both renderers use;
//! - [`lights`]: the environment and the sun, shared by the reference and the runtime;
//! - [`render`]: view files, the reference path tracer, image comparison, captions;
//! - [`util`]: progress callbacks and atomic writes;
//! - [`gen`]: generators for the paper's hard cases;
//! - [`eval`]: the quality and speed studies (our LoD against the reference and the
//!   alternatives: cube primitives, an exponential volume, a meshopt-simplified mesh);
//! - [`assembly`]: manifests of instanced assets, rendered with the runtime and the reference;
//! - [`validation`]: shared test harnesses (chi-square).

pub mod absdf;
#[deny(missing_docs)]
pub mod assembly;
pub mod bake;
pub mod bsdf;
pub mod eval;
pub mod film;
#[deny(missing_docs)]
pub mod format;
pub mod gen;
pub mod import;
pub mod inspect;
pub mod lights;
pub mod math;
pub mod render;
#[deny(missing_docs)]
pub mod report;
#[deny(missing_docs)]
pub mod runtime;
pub mod scene;
pub mod spatial;
pub mod tables;
pub mod trace;
pub mod util;
pub mod validation;
