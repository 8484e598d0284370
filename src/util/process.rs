//! Whole commands measured as a user would: wall time, CPU time and peak resident memory of a
//! child process (`wait4`'s resource usage of that child alone), for the studies' speed and
//! memory columns and the cache-budget example.

use std::process::{Command, Stdio};
use std::time::Instant;

/// The peak resident memory of this process since it was started (`VmHWM` of
/// `/proc/self/status`, in bytes), or `None` where it cannot be read. Unlike `getrusage`'s
/// `ru_maxrss`, it starts afresh at `exec`: a child spawned by a large process (with
/// `CLONE_VM`, as `posix_spawn` does) inherits the parent's high-water mark in `ru_maxrss`.
pub fn peak_rss() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The line a command prints with [`peak_rss`], which [`measure`] reads back.
pub fn peak_rss_line() -> Option<String> {
    peak_rss().map(|b| {
        format!(
            "stats: peak resident memory {:.1} MiB ({b} bytes)",
            b as f64 / (1 << 20) as f64
        )
    })
}

/// What one child process took.
#[derive(Clone, Debug)]
pub struct Measured {
    /// Wall-clock seconds from spawn to exit.
    pub wall: f64,
    /// User plus system CPU seconds of the child.
    pub cpu: f64,
    /// Peak resident set size of the child, in bytes: what it printed with
    /// [`peak_rss_line`] if it did (exact), else `wait4`'s `ru_maxrss` (which may hold the
    /// parent's high-water mark, see [`peak_rss`]).
    pub max_rss: u64,
    /// Whether it exited with status 0.
    pub success: bool,
    /// What it printed on stdout.
    pub stdout: String,
    /// What it printed on stderr.
    pub stderr: String,
}

/// Runs `cmd` to its end, capturing its output, and measures it.
pub fn measure(cmd: &mut Command) -> std::io::Result<Measured> {
    use std::io::Read;
    let t = Instant::now();
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn()?;
    let (mut out, mut err) = (String::new(), String::new());
    // Read stderr on a thread so that neither pipe fills while the other is read.
    let mut e = child.stderr.take();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        if let Some(e) = e.as_mut() {
            let _ = e.read_to_string(&mut s);
        }
        s
    });
    if let Some(o) = child.stdout.as_mut() {
        let _ = o.read_to_string(&mut out);
    }
    if let Ok(s) = reader.join() {
        err = s;
    }
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    // SAFETY: wait4 writes one plain struct we own; the child is ours and not yet reaped
    // (std's `Child` is never waited on here; dropping it does not wait either).
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
    if r != pid {
        return Err(std::io::Error::last_os_error());
    }
    let secs = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 * 1e-6;
    Ok(Measured {
        wall: t.elapsed().as_secs_f64(),
        cpu: secs(ru.ru_utime) + secs(ru.ru_stime),
        // Linux reports ru_maxrss in KiB.
        max_rss: reported_rss(&out).unwrap_or(ru.ru_maxrss.max(0) as u64 * 1024),
        success: libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0,
        stdout: out,
        stderr: err,
    })
}

/// The bytes of a [`peak_rss_line`] in a command's output.
fn reported_rss(out: &str) -> Option<u64> {
    let l = out
        .lines()
        .rev()
        .find(|l| l.starts_with("stats: peak resident memory"))?;
    let inner = l.rsplit('(').next()?;
    inner.split_whitespace().next()?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A child that touches 64 MiB shows at least that much peak memory; one that fails says
    /// so; the output is captured.
    #[test]
    fn measures_a_child() {
        let m = measure(Command::new("sh").args([
            "-c",
            "echo out; echo err >&2; head -c 67108864 /dev/zero | tail -c 1 >/dev/null",
        ]))
        .unwrap();
        assert!(m.success);
        assert_eq!((m.stdout.trim(), m.stderr.trim()), ("out", "err"));
        assert!(m.wall >= 0.0 && m.cpu >= 0.0);
        // `tail -c 1` of a pipe holds at most a block: the peak is the largest child's alone.
        assert!(m.max_rss > 0 && m.max_rss < 1 << 30, "{}", m.max_rss);
        let f = measure(Command::new("sh").args(["-c", "exit 3"])).unwrap();
        assert!(!f.success);
        // A command that reports its own peak: that figure is taken.
        let line = "stats: peak resident memory 1.0 MiB (1048576 bytes)";
        let r = measure(Command::new("sh").args(["-c", &format!("echo '{line}'")])).unwrap();
        assert_eq!(r.max_rss, 1 << 20);
        assert!(peak_rss().is_some_and(|b| b > 0));
    }
}
