//! Small utilities every stage uses and that belong to none: progress reporting through a
//! callback (libraries never draw; the CLI does), and atomic file writes. Depends on nothing
//! else in the crate.

pub mod atomic;
pub mod progress;

pub use atomic::write_atomic;
pub use progress::{no_progress, Progress, TerminalProgress};
