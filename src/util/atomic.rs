//! Atomic file writes: into a temporary file beside the destination, then renamed into place,
//! so that a failed or interrupted write leaves any previous file untouched.
//!
//! Every temporary file being written is registered ([`LiveTemp`]) so that a process killed by
//! SIGTERM or SIGINT can remove them before it exits: [`clean_up_on_interrupt`], which the
//! command line installs (a library does not take over a host's signals, so the Python module
//! does not).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The exit status of a process interrupted by SIGTERM or SIGINT once
/// [`clean_up_on_interrupt`] is installed (128 + SIGINT's number, as shells report Ctrl-C).
pub const INTERRUPTED_EXIT_CODE: i32 = 130;

/// The temporary files being written now (absolute where the path could be made so), each
/// once per live [`LiveTemp`].
static LIVE: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn live() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    // A panic elsewhere while holding the lock leaves the list itself intact.
    LIVE.lock().unwrap_or_else(|e| e.into_inner())
}

/// A temporary file's registration: while it lives, the handler of [`clean_up_on_interrupt`]
/// removes the file on SIGTERM or SIGINT. Register before creating the file (so that no
/// moment exists when the file is there and unregistered); dropping it unregisters the path
/// and leaves the file alone (its owner renames or removes it).
#[derive(Debug)]
pub struct LiveTemp {
    path: PathBuf,
    registered: PathBuf,
}

impl LiveTemp {
    /// Registers `path`, the temporary file about to be created.
    pub fn register(path: PathBuf) -> LiveTemp {
        let registered = std::path::absolute(&path).unwrap_or_else(|_| path.clone());
        live().push(registered.clone());
        LiveTemp { path, registered }
    }

    /// The temporary file's path, as given.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for LiveTemp {
    fn drop(&mut self) {
        let mut live = live();
        if let Some(i) = live.iter().position(|p| *p == self.registered) {
            live.swap_remove(i);
        }
    }
}

/// The temporary files registered now (for tests and diagnostics).
pub fn live_temps() -> Vec<PathBuf> {
    live().clone()
}

/// Installs a handler of SIGTERM and SIGINT (signal-hook's, on a thread of its own) that
/// removes every registered temporary file ([`LiveTemp`]), says so on stderr and exits with
/// [`INTERRUPTED_EXIT_CODE`]. For programs (the `aggtool` command line), once, early in
/// `main`; a no-op where signals are not Unix's.
pub fn clean_up_on_interrupt() -> std::io::Result<()> {
    #[cfg(unix)]
    {
        use signal_hook::consts::{SIGINT, SIGTERM};
        let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM])?;
        std::thread::Builder::new()
            .name("aggtool-interrupt".into())
            .spawn(move || {
                if let Some(signal) = signals.forever().next() {
                    // The lock is held until the exit: no temporary file is registered (and
                    // so none created) after this.
                    let live = live();
                    let removed = live
                        .iter()
                        .filter(|p| std::fs::remove_file(p).is_ok())
                        .count();
                    let name = if signal == SIGTERM {
                        "SIGTERM"
                    } else {
                        "SIGINT"
                    };
                    eprintln!(
                        "\ninterrupted ({name}): removed {removed} unfinished temporary file(s)"
                    );
                    std::process::exit(INTERRUPTED_EXIT_CODE);
                }
            })?;
    }
    Ok(())
}

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
    let live = LiveTemp::register(dir.join(format!(
        ".{}.{}.tmp.{}",
        name,
        std::process::id(),
        path.extension().and_then(|e| e.to_str()).unwrap_or("bin")
    )));
    let tmp = live.path();
    let result = write(tmp).and_then(|_| {
        std::fs::rename(tmp, path).map_err(|e| format!("cannot rename into place: {e}"))
    });
    if result.is_err() {
        let _ = std::fs::remove_file(tmp);
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

    /// A temporary file is registered (absolute) from before its creation until its owner is
    /// done with it, whether the write succeeded or failed: what the interrupt handler
    /// removes is exactly what is being written.
    #[test]
    fn temporary_files_are_registered_while_written() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("f.png");
        let mut seen = None;
        write_atomic(&out, |tmp| {
            seen = Some(tmp.to_path_buf());
            assert!(live_temps().contains(&std::path::absolute(tmp).unwrap()));
            std::fs::write(tmp, b"x").map_err(|e| e.to_string())
        })
        .unwrap();
        let tmp = seen.unwrap();
        assert!(out.exists() && !tmp.exists());
        assert!(!live_temps().contains(&tmp));
        let e = write_atomic(&out, |tmp| {
            std::fs::write(tmp, b"y").unwrap();
            Err("failed".into())
        });
        assert!(e.is_err() && !tmp.exists() && !live_temps().contains(&tmp));
        let live = LiveTemp::register(d.path().join("g.tmp"));
        assert!(live_temps().contains(&d.path().join("g.tmp")));
        drop(live);
        assert!(!live_temps().contains(&d.path().join("g.tmp")));
    }

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
