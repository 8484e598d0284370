//! What commands report and how they fail, the same for every front end: the `aggtool`
//! command line prints a report's [`Display`](std::fmt::Display) (or, under `--json`, its
//! [`serde::Serialize`] form as one JSON object), and a host such as the Python module can print
//! the same. A failure has an [`ErrorKind`] (a [`Failure`] carries its own; the command line
//! finds the others' from the error types of the stages that failed), whose
//! [`ErrorKind::exit_code`] is the command line's exit status. This module sits low in the
//! pipeline, so that every stage can say how it failed.
//!
//! | status | kind | meaning |
//! | --- | --- | --- |
//! | 0 | | success |
//! | 2 | [`ErrorKind::Usage`] | bad flags or settings (clap's own status for parse errors) |
//! | 3 | [`ErrorKind::Input`] | an input is missing, unreadable or invalid |
//! | 4 | [`ErrorKind::Output`] | an output could not be written |
//! | 130 | [`ErrorKind::Interrupted`] | interrupted (SIGINT or SIGTERM) |

use std::fmt;

use serde::Serialize;

/// A command's report: text for people ([`fmt::Display`]) and one JSON object for programs.
pub trait Report: fmt::Display {
    /// The report as a JSON value (an object for every report of the command line).
    fn to_json(&self) -> serde_json::Value;
}

impl<T: fmt::Display + Serialize> Report for T {
    fn to_json(&self) -> serde_json::Value {
        json_value(self).unwrap_or_else(|e| serde_json::json!({ "error": format!("report: {e}") }))
    }
}

/// `v` as a JSON value, through JSON text rather than `serde_json::to_value`, which widens an
/// `f32` to the nearest `f64` (0.95 became 0.949999988079071): as text an `f32` is its
/// shortest decimal. The command line and the Python module both use it, so they print the
/// same numbers.
pub fn json_value<T: Serialize + ?Sized>(v: &T) -> serde_json::Result<serde_json::Value> {
    serde_json::from_str(&serde_json::to_string(v)?)
}

/// A callback for informational lines a long command says as it goes (one line a call, no
/// newline): the command line prints them unless `--quiet` or `--json`.
pub type Notes<'a> = &'a (dyn Fn(&str) + Sync);

/// A [`Notes`] that says nothing.
pub fn no_notes(_line: &str) {}

/// What kind of failure ended a command; each has its own exit status.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ErrorKind {
    /// Bad flags or settings: exit status 2, as clap's parse errors.
    Usage,
    /// An input is missing, unreadable or invalid: exit status 3.
    Input,
    /// An output could not be written: exit status 4.
    Output,
    /// Interrupted by SIGINT or SIGTERM: exit status 130 (128 + SIGINT).
    Interrupted,
}

impl ErrorKind {
    /// The process exit status of this kind of failure.
    pub fn exit_code(self) -> u8 {
        match self {
            ErrorKind::Usage => 2,
            ErrorKind::Input => 3,
            ErrorKind::Output => 4,
            ErrorKind::Interrupted => 130,
        }
    }

    /// The kind's name as JSON errors give it ("usage", "input", "output", "interrupted").
    pub fn name(self) -> &'static str {
        match self {
            ErrorKind::Usage => "usage",
            ErrorKind::Input => "input",
            ErrorKind::Output => "output",
            ErrorKind::Interrupted => "interrupted",
        }
    }
}

/// An error that says its own kind: what library code returns where the kind is not evident
/// from a typed error (see [`usage`], [`output`]).
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct Failure {
    /// The kind.
    pub kind: ErrorKind,
    /// What went wrong.
    pub message: String,
}

/// A usage error (bad flags or settings) with this message.
pub fn usage(message: impl Into<String>) -> anyhow::Error {
    Failure {
        kind: ErrorKind::Usage,
        message: message.into(),
    }
    .into()
}

/// An output error (a file that could not be written) with this message.
pub fn output(message: impl Into<String>) -> anyhow::Error {
    Failure {
        kind: ErrorKind::Output,
        message: message.into(),
    }
    .into()
}

/// A failure as the command line prints it under `--json`: `{"error", "kind", "causes"}`.
#[derive(Clone, Debug, Serialize)]
pub struct ErrorReport {
    /// The error's message.
    pub error: String,
    /// Its kind ("usage", "input", "output", "interrupted").
    pub kind: ErrorKind,
    /// Its causes not already said by the message, outermost first.
    pub causes: Vec<String>,
    /// The exit status.
    pub exit_code: u8,
}

impl ErrorReport {
    /// The report of `e`, whose kind the caller found (the command line classifies by the
    /// error types of the stages that failed).
    pub fn new(e: &anyhow::Error, kind: ErrorKind) -> ErrorReport {
        ErrorReport {
            error: e.to_string(),
            kind,
            causes: causes(e),
            exit_code: kind.exit_code(),
        }
    }
}

impl fmt::Display for ErrorReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "error: {}", self.error)?;
        for c in &self.causes {
            write!(f, "\n  caused by: {c}")?;
        }
        Ok(())
    }
}

/// The causes of `e` after its message, each left out when an earlier message already says
/// it (many errors put their source in their own message: "cannot read F: {source}").
pub fn causes(e: &anyhow::Error) -> Vec<String> {
    let mut said = e.to_string();
    let mut out = Vec::new();
    for cause in e.chain().skip(1) {
        let cause = cause.to_string();
        if !said.contains(&cause) {
            out.push(cause.clone());
        }
        said.push('\n');
        said.push_str(&cause);
    }
    out
}

/// Bytes as mebibytes with two decimals ("1.50 MiB"), as every report writes sizes.
pub fn mib(bytes: u64) -> String {
    format!("{:.2} MiB", bytes as f64 / (1024.0 * 1024.0))
}

/// A report of output files only: `output: PATH (what)` lines.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Written {
    /// The files or folders written, with what each holds.
    pub outputs: Vec<WrittenFile>,
}

/// One entry of [`Written`].
#[derive(Clone, Debug, Serialize)]
pub struct WrittenFile {
    /// The path.
    pub path: String,
    /// What it holds ("12000 triangles"), empty when nothing is to be said.
    pub what: String,
}

impl Written {
    /// Adds `path` with its description.
    pub fn push(&mut self, path: &std::path::Path, what: impl Into<String>) {
        self.outputs.push(WrittenFile {
            path: path.display().to_string(),
            what: what.into(),
        });
    }
}

impl fmt::Display for Written {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, o) in self.outputs.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "output: {}", o.path)?;
            if !o.what.is_empty() {
                write!(f, " ({})", o.what)?;
            }
        }
        Ok(())
    }
}

/// Writes `contents` to `path` atomically ([`crate::util::write_bytes_atomic`]); a
/// failure is an output error naming the file.
pub fn write_output(path: &std::path::Path, contents: impl AsRef<[u8]>) -> anyhow::Result<()> {
    crate::util::write_bytes_atomic(path, contents.as_ref()).map_err(output)
}
