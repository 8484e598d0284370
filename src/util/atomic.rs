//! Atomic file writes: into a temporary file beside the destination, then renamed into place,
//! so that a failed or interrupted write leaves any previous file untouched.

use std::path::Path;

/// Writes `path` through `write(tmp)`, which writes the temporary file `tmp` (same folder,
/// same extension, so encoders that pick a format by extension still do); then renames it into
/// place. On any error the temporary file is removed and `path` is left as it was.
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), String> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("out");
    // Keep the extension last: encoders pick the format from it.
    let tmp = dir.join(format!(
        ".{}.{}.tmp.{}",
        name,
        std::process::id(),
        path.extension().and_then(|e| e.to_str()).unwrap_or("bin")
    ));
    let result = write(&tmp).and_then(|_| {
        std::fs::rename(&tmp, path).map_err(|e| format!("cannot rename into place: {e}"))
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// [`write_atomic`] of a byte string.
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> Result<(), String> {
    write_atomic(path, |tmp| {
        std::fs::write(tmp, bytes).map_err(|e| format!("cannot write {}: {e}", tmp.display()))
    })
}
