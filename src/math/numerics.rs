//! Non-finite values, counted rather than hidden. A function that promises finite output
//! replaces a NaN or an infinity it computed by zero, and notes it here; renders report the
//! count (the `stats:` line's `non-finite` figure) and tests assert that it stays zero, so a
//! NaN that slips into a computation makes a test fail instead of vanishing. In debug builds
//! the note is also a `debug_assert!`, so the first one stops the program where it arose.
//!
//! Inputs are another matter: a caller's NaN direction or parameter is rejected by the
//! function's own guard (and gives zero) without being counted; only values a function
//! produced from valid inputs count.
//!
//! The counter is per thread, so that tests running side by side do not see each other's
//! values and a parallel render sums its workers' counts (see [`crate::film`]).

use std::cell::Cell;

thread_local! {
    static NON_FINITE: Cell<u64> = const { Cell::new(0) };
    static EXPECTING: Cell<bool> = const { Cell::new(false) };
}

/// Notes one non-finite value that was replaced instead of returned.
#[cold]
#[inline(never)]
pub fn note_non_finite(what: &'static str) {
    NON_FINITE.with(|c| c.set(c.get() + 1));
    debug_assert!(
        EXPECTING.with(|e| e.get()),
        "non-finite value in {what} (replaced by zero; counted in the stats)"
    );
}

/// Non-finite values noted on this thread so far.
pub fn non_finite_count() -> u64 {
    NON_FINITE.with(|c| c.get())
}

/// Runs `f` with the debug assertion of [`note_non_finite`] off and returns what it returned
/// and how many non-finite values it noted: for tests that inject a NaN on purpose, to show
/// that the count sees it.
pub fn counting<R>(f: impl FnOnce() -> R) -> (R, u64) {
    let before = non_finite_count();
    let was = EXPECTING.with(|e| e.replace(true));
    let r = f();
    EXPECTING.with(|e| e.set(was));
    (r, non_finite_count() - before)
}

/// `x`, or zero (noted) when it is NaN or infinite: the last line of defence before a value
/// leaves a function that promises finite output.
#[inline]
pub fn finite_or_zero(x: f32) -> f32 {
    if x.is_finite() {
        x
    } else {
        note_non_finite("a scalar");
        0.0
    }
}

/// Component-wise [`finite_or_zero`] (one note per vector).
#[inline]
pub fn finite_vec_or_zero(v: glam::Vec3) -> glam::Vec3 {
    if v.is_finite() {
        v
    } else {
        note_non_finite("a vector");
        glam::Vec3::ZERO
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An injected NaN is replaced, and the count (what the tests assert on) sees it.
    #[test]
    fn an_injected_nan_is_counted() {
        let (v, n) = counting(|| finite_or_zero(f32::NAN) + finite_vec_or_zero(glam::Vec3::ONE).x);
        assert_eq!((v, n), (1.0, 1));
        let (_, n) = counting(|| finite_or_zero(2.0));
        assert_eq!(n, 0);
    }
}
