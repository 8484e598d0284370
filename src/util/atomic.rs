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

/// Checks, before work whose result would be lost, that [`write_atomic`] can put a file at
/// `path`: `path` is not a folder, and no existing path above it is a file (missing folders
/// are created by the write). Permissions and free space are found out only by writing.
pub fn check_destination(path: &Path) -> std::io::Result<()> {
    use std::io::{Error, ErrorKind};
    if path.is_dir() {
        return Err(Error::new(
            ErrorKind::IsADirectory,
            "it is a folder: give the path of a file (in it or elsewhere)",
        ));
    }
    for dir in path.ancestors().skip(1) {
        if dir.as_os_str().is_empty() {
            break;
        }
        match std::fs::metadata(dir) {
            Ok(m) if m.is_dir() => break,
            Ok(_) => {
                return Err(Error::new(
                    ErrorKind::NotADirectory,
                    format!("{} is a file, not a folder", dir.display()),
                ))
            }
            // Missing: the write creates it (a folder it cannot create fails there).
            Err(_) => continue,
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_or_a_file_above_is_not_a_destination() {
        let d = tempfile::tempdir().unwrap();
        let file = d.path().join("f");
        std::fs::write(&file, b"x").unwrap();
        assert!(check_destination(&d.path().join("new/deeper/out.agg")).is_ok());
        assert!(
            check_destination(&file).is_ok(),
            "an existing file is replaced"
        );
        assert_eq!(
            check_destination(d.path()).unwrap_err().kind(),
            std::io::ErrorKind::IsADirectory
        );
        let e = check_destination(&file.join("out.agg")).unwrap_err();
        assert!(e.to_string().contains("is a file"), "{e}");
    }
}
