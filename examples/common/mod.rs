//! Argument helpers shared by the measurement examples.

/// The value after `flag` in `args`, parsed, or `default`.
#[allow(dead_code)] // Not every example reads numeric flags this way.
pub fn flag_u32(args: &[String], flag: &str, default: u32) -> u32 {
    flag_value(args, flag)
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The text after `flag` in `args`, if the flag is there.
pub fn flag_value(args: &[String], flag: &str) -> Option<String> {
    args.iter()
        .position(|a| a == flag)
        .and_then(|i| args.get(i + 1))
        .cloned()
}
