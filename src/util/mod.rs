//! Small utilities every stage uses and that belong to none: progress reporting through a
//! callback (libraries never draw; the CLI does), and atomic file writes. Depends on nothing
//! else in the crate.

mod atomic;
pub mod process;
mod progress;

pub use atomic::*;
pub use progress::*;

/// CPU seconds this process has spent so far (user + system, all threads): the figure to
/// compare on a shared machine, where wall-clock time depends on what else runs. Zero where
/// the platform does not report it.
pub fn cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage writes one plain struct we own.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } == 0 {
            let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
            return tv(u.ru_utime) + tv(u.ru_stime);
        }
    }
    0.0
}
