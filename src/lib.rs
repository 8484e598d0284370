//! # aggtool
//!
//! Appearance-preserving level of detail after Zhou et al., "Efficient Scene Appearance
//! Aggregation for Level-of-Detail Rendering". The modules are declared in pipeline order, and
//! each uses only modules declared before it (documentation links may name later users, and
//! the unit tests of [`math`] use [`validation`]'s chi-square test, itself built on [`math`]):
//!
//! - [`math`]: pure math (sampling, spherical maps, microfacets) that knows nothing of scenes;
//! - [`util`]: progress callbacks and atomic writes;
//! - [`report`]: what commands report (`Display` + `Serialize`) and how they fail: error kinds
//!   and exit statuses;
//! - [`validation`]: shared test harnesses (chi-square), over [`math`] alone;
//! - [`spatial`]: the spatial core of bake, format and runtime: grid, Morton keys, faces, the
//!   truncated ellipsoid with its one ray test, the DDA;
//! - [`scene`] and [`import`]: the scene representation and the glTF/OBJ importers;
//! - [`gen`]: generators for the paper's hard cases, scenes as an importer would produce them;
//! - [`tables`]: the five precomputed tables M1–M5 of the factorized ABSDF, and the lune table
//!   of Eq. 21 derived from M4;
//! - [`bsdf`]: the surface material model of the paper (Eq. 11);
//! - [`absdf`]: the factorized aggregated BSDF of a voxel (Eq. 7–23) with sampling;
//! - [`trace`]: two-level BVH ray tracing (obvhs) with alpha cut-outs;
//! - [`format`](mod@format): the `.agg` container and its FlatBuffers schema: writer, verifying zero-copy reader;
//! - [`bake`]: the sparse voxel hierarchy, per-voxel statistics and visibility, streamed to a file;
//! - [`inspect`]: what a file holds (`aggtool inspect`), its settings as the bake's own;
//! - [`film`]: the camera, images, the stratified sampler and the one image loop both renderers
//!   use;
//! - [`lights`]: the environment and the sun, shared by the reference and the runtime;
//! - [`runtime`]: the LoD renderer of `.agg` aggregates (cone tracing, Algorithm 1, Eq. 30);
//! - [`render`]: view files, the reference path tracer, image comparison, captions; independent
//!   of [`runtime`], so that it stays an oracle for it;
//! - [`eval`]: the quality and speed studies (our LoD against the reference and the
//!   alternatives: cube primitives, an exponential volume, a meshopt-simplified mesh);
//! - [`assembly`]: manifests of instanced assets, rendered with the runtime and the reference.

#![deny(missing_docs)]

// One module per group: rustfmt sorts the modules of a group, and this order is the pipeline's.

pub mod math;

pub mod util;

pub mod report;

pub mod validation;

pub mod spatial;

pub mod scene;

pub mod import;

pub mod gen;

pub mod tables;

pub mod bsdf;

pub mod absdf;

pub mod trace;

pub mod format;

pub mod bake;

pub mod inspect;

pub mod film;

pub mod lights;

pub mod runtime;

pub mod render;

pub mod eval;

pub mod assembly;
