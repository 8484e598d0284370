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

/// Progress as JSON lines, for programs that run the command line as a subprocess and show
/// their own progress (the Blender extension): `{"stage":"16³ voxels","done":3,"total":10}`,
/// one line when a stage starts, at each whole percent it passes and when it ends, so that a
/// bake of millions of units prints a few hundred lines, not millions.
pub struct JsonProgress<W: std::io::Write + Send> {
    /// The writer, the stage last reported and its last whole percent.
    state: Mutex<(W, String, u64)>,
}

impl JsonProgress<std::io::Stderr> {
    /// Lines on stderr (stdout keeps the `input:`/`output:`/`stats:` report).
    pub fn stderr() -> Self {
        Self::new(std::io::stderr())
    }
}

impl<W: std::io::Write + Send> JsonProgress<W> {
    /// JSON progress lines written to `writer`.
    pub fn new(writer: W) -> Self {
        JsonProgress {
            state: Mutex::new((writer, String::new(), 0)),
        }
    }

    /// Reports progress (the [`Progress`] signature); write errors are ignored, as a closed
    /// pipe must not stop a bake.
    pub fn report(&self, stage: &str, done: u64, total: u64) {
        let Ok(mut guard) = self.state.lock() else {
            return;
        };
        let (writer, last_stage, last_percent) = &mut *guard;
        let percent = (done.min(total) * 100).checked_div(total).unwrap_or(100);
        if last_stage == stage && percent <= *last_percent {
            return;
        }
        let line = serde_json::json!({ "stage": stage, "done": done.min(total), "total": total });
        let _ = writeln!(writer, "{line}");
        let _ = writer.flush();
        *last_stage = stage.to_string();
        *last_percent = percent;
    }

    /// The writer back (tests read what was written).
    pub fn into_inner(self) -> W {
        match self.state.into_inner() {
            Ok(s) => s.0,
            Err(p) => p.into_inner().0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_progress_prints_a_line_per_stage_start_and_whole_percent() {
        let p = JsonProgress::new(Vec::new());
        p.report("16³ voxels", 0, 1000);
        for d in 1..=1000 {
            p.report("16³ voxels", d, 1000);
        }
        p.report("16³ voxels", 500, 1000); // late report of a parallel worker: dropped
        p.report("16³ faces", 0, 0); // an empty stage is done at once
        let text = String::from_utf8(p.into_inner()).unwrap();
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        // 0%, then 1% .. 100%, then the empty stage.
        assert_eq!(lines.len(), 102, "{text}");
        assert_eq!(lines[0]["done"], 0);
        assert_eq!(lines[100]["done"], 1000);
        assert_eq!(lines[100]["total"], 1000);
        assert_eq!(lines[101]["stage"], "16³ faces");
    }
}
