//! Asset import: one module per format, all producing a [`Scene`].
//!
//! Bad input never panics: it is either an [`ImportError`] naming the file and the element, or
//! a warning in [`Scene::warnings`] when the element can be skipped and the rest is usable
//! ([`ImportOptions::strict`] turns such warnings into errors).

mod gltf;
mod images;
mod obj;

use std::path::{Path, PathBuf};

use glam::Vec3;

use crate::scene::Scene;

pub use self::images::decode_texture;

/// Errors of the import stage.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The extension is none of the formats imported.
    #[error("{path}: unsupported file type (expected .gltf, .glb or .obj)")]
    UnsupportedFormat {
        /// The file.
        path: PathBuf,
    },
    /// An element of the file is invalid and cannot be skipped.
    #[error("{path}: {element}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The element (e.g. `mesh 3 primitive 0`).
        element: String,
        /// What is wrong with it.
        message: String,
    },
    /// The file does not parse as its format.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message.
        message: String,
    },
    /// Nothing with area is left to render or bake.
    #[error("{path}: the scene has no usable triangles")]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// A warning under [`ImportOptions::strict`].
    #[error("{path}: {warning} (--strict)")]
    Strict {
        /// The file.
        path: PathBuf,
        /// The warning that became an error.
        warning: String,
    },
}

/// Import settings.
#[derive(Clone, Copy, Debug, Default)]
pub struct ImportOptions {
    /// Treat every warning (skipped element, missing texture, ignored feature) as an error.
    pub strict: bool,
}

/// Loads an asset by its extension: `.gltf`, `.glb` or `.obj`.
pub fn load(path: &Path, options: ImportOptions) -> Result<Scene, ImportError> {
    let mut scene = by_format(path, gltf::load, obj::load)?;
    scene.source = Some(path.to_path_buf());
    if options.strict {
        if let Some(w) = scene.warnings.first() {
            return Err(ImportError::Strict {
                path: path.to_path_buf(),
                warning: w.clone(),
            });
        }
    }
    if scene.instanced_triangle_count() == 0 {
        return Err(ImportError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(scene)
}

/// The triangles an asset places (every instance of every mesh of its scene), counted without
/// importing it, up to `at_most + 1`: enough to tell whether it has at most `at_most`. A glTF
/// file's JSON is read (a `.glb`'s first chunk only, not its buffers) and each triangle
/// primitive counted by its accessors; an OBJ file's faces are read until the count passes
/// `at_most` (a face of k corners is k − 2 triangles). What [`load`] then finds can be fewer
/// (degenerate or non-finite triangles are dropped there), never more. For choosing how to
/// draw an asset before importing it (an assembly draws an asset of few triangles from its
/// mesh, `crate::assembly::Assembly::draw_small_meshes`).
pub fn triangle_count(path: &Path, at_most: u64) -> Result<u64, ImportError> {
    by_format(
        path,
        |p| gltf::triangle_count(p, at_most),
        |p| obj::triangle_count(p, at_most),
    )
}

/// `gltf` or `obj` on `path` by its extension (`.gltf`, `.glb` or `.obj`). A panic inside a
/// third-party parser on hostile input must not take the caller down: it becomes a parse
/// error.
fn by_format<T>(
    path: &Path,
    gltf: impl FnOnce(&Path) -> Result<T, ImportError> + std::panic::UnwindSafe,
    obj: impl FnOnce(&Path) -> Result<T, ImportError> + std::panic::UnwindSafe,
) -> Result<T, ImportError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    let result = std::panic::catch_unwind(|| match ext.as_str() {
        "gltf" | "glb" => gltf(path),
        "obj" => obj(path),
        _ => Err(ImportError::UnsupportedFormat {
            path: path.to_path_buf(),
        }),
    });
    result.unwrap_or_else(|_| {
        Err(ImportError::Parse {
            path: path.to_path_buf(),
            message: "the file could not be parsed (internal parser failure)".into(),
        })
    })
}

/// The glTF importer on bytes in memory (a `.gltf` or `.glb` as if read from `path`, which
/// names it in errors and places relative URIs), without [`load`]'s `catch_unwind`, so that the
/// fuzz target (fuzz/fuzz_targets/gltf.rs) sees every panic. Not an API: use [`load`].
#[doc(hidden)]
pub fn load_gltf_slice(bytes: &[u8], path: &Path) -> Result<Scene, ImportError> {
    gltf::load_slice(bytes, path)
}

/// Appends the triangle if all three vertices are finite, in range, and it has non-zero area;
/// counts what it skipped. Returns an error for out-of-range indices (a broken file).
pub(crate) struct TriangleFilter {
    pub nan: usize,
    pub degenerate: usize,
}

impl TriangleFilter {
    pub fn new() -> Self {
        TriangleFilter {
            nan: 0,
            degenerate: 0,
        }
    }

    /// `Ok(true)` when the triangle is kept.
    pub fn accept(&mut self, positions: &[Vec3], tri: [u32; 3]) -> Result<bool, String> {
        let n = positions.len();
        if let Some(&bad) = tri.iter().find(|&&i| i as usize >= n) {
            return Err(format!("vertex index {bad} out of range ({n} vertices)"));
        }
        let [a, b, c] = tri.map(|i| positions[i as usize]);
        if !(a.is_finite() && b.is_finite() && c.is_finite()) {
            self.nan += 1;
            return Ok(false);
        }
        let cr = (b - a).cross(c - a);
        if !(cr.length_squared() > 0.0) || !cr.is_finite() {
            self.degenerate += 1;
            return Ok(false);
        }
        Ok(true)
    }

    pub fn report(&self, element: &str, warnings: &mut Vec<String>) {
        if self.nan > 0 {
            warnings.push(format!(
                "{element}: skipped {} triangles with NaN or infinite vertices",
                self.nan
            ));
        }
        if self.degenerate > 0 {
            warnings.push(format!(
                "{element}: skipped {} degenerate (zero-area) triangles",
                self.degenerate
            ));
        }
    }
}

/// Normalised shading normals: invalid ones (zero, NaN) become zero, which the tracer treats as
/// "use the geometric normal".
pub(crate) fn sanitize_normals(normals: &mut [Vec3]) {
    for n in normals {
        *n = n.try_normalize().unwrap_or(Vec3::ZERO);
    }
}
