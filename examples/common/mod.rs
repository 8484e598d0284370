//! Argument helpers shared by the measurement examples.

/// The value after `flag` in `args`, parsed, or `default`.
pub fn flag_u32(args: &[String], flag: &str, default: u32) -> u32 {
    args.iter()
        .position(|a| a == flag)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
