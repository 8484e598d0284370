//! Progress through a callback. Library calls that take long (bakes, renders, table fits) take
//! a [`Progress`]: a function called with the stage's name, the units done so far and the
//! stage's total, from any thread. Libraries never draw; a command-line front end passes a
//! [`TerminalProgress`], a host renderer its own function, a test [`no_progress`].

use std::sync::Mutex;

/// A progress callback: `(stage, done, total)`, called from any thread; `done` grows within a
/// stage (reports may arrive slightly out of order from parallel workers), and a new stage name
/// starts a new stage.
pub type Progress<'a> = &'a (dyn Fn(&str, u64, u64) + Sync);

/// A callback that ignores every report.
pub fn no_progress(_stage: &str, _done: u64, _total: u64) {}

/// Progress bars on stderr, one per stage, hidden when stderr is not a terminal.
pub struct TerminalProgress {
    bar: Mutex<Option<(String, indicatif::ProgressBar)>>,
    enabled: bool,
}

impl Default for TerminalProgress {
    fn default() -> Self {
        Self::new()
    }
}

impl TerminalProgress {
    /// Bars on stderr when it is a terminal.
    pub fn new() -> Self {
        use std::io::IsTerminal;
        TerminalProgress {
            bar: Mutex::new(None),
            enabled: std::io::stderr().is_terminal(),
        }
    }

    /// Reports progress (the [`Progress`] signature).
    pub fn report(&self, stage: &str, done: u64, total: u64) {
        if !self.enabled {
            return;
        }
        let Ok(mut guard) = self.bar.lock() else {
            return;
        };
        if guard.as_ref().is_none_or(|(s, _)| s != stage) {
            if let Some((_, b)) = guard.take() {
                b.finish_and_clear();
            }
            let b = indicatif::ProgressBar::new(total);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{prefix:>14} [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta}",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            b.set_prefix(stage.to_string());
            *guard = Some((stage.to_string(), b));
        }
        if let Some((_, b)) = guard.as_ref() {
            b.set_length(total);
            if done > b.position() {
                b.set_position(done);
            }
            if done >= total {
                b.finish_and_clear();
            }
        }
    }

    /// Clears the bar of the stage in progress.
    pub fn finish(&self) {
        if let Ok(mut g) = self.bar.lock() {
            if let Some((_, b)) = g.take() {
                b.finish_and_clear();
            }
        }
    }
}

impl Drop for TerminalProgress {
    fn drop(&mut self) {
        self.finish();
    }
}

/// A counter over a stage that reports through a [`Progress`] as units finish (thread-safe).
pub struct StageCounter<'a> {
    progress: Progress<'a>,
    stage: String,
    total: u64,
    done: std::sync::atomic::AtomicU64,
}

impl<'a> StageCounter<'a> {
    /// Starts a stage of `total` units and reports 0 of them.
    pub fn new(progress: Progress<'a>, stage: impl Into<String>, total: u64) -> Self {
        let stage = stage.into();
        progress(&stage, 0, total);
        StageCounter {
            progress,
            stage,
            total,
            done: std::sync::atomic::AtomicU64::new(0),
        }
    }

    /// `n` more units are done.
    pub fn add(&self, n: u64) {
        let d = self.done.fetch_add(n, std::sync::atomic::Ordering::Relaxed) + n;
        (self.progress)(&self.stage, d.min(self.total), self.total);
    }
}
