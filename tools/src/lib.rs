//! The measurement probes of aggtool, one binary each in `src/bin/` (throughput, profiles and
//! the probes the studies in the book cite): `cargo run --release -p aggtool-tools --bin NAME
//! -- ARGS`. This library holds what they share.

#![deny(missing_docs)]

/// The value after `flag` in `args`, parsed, or `default`.
pub fn flag_u32(args: &[String], flag: &str, default: u32) -> u32 {
    args.iter()
        .position(|a| a == flag)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
