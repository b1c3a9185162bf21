//! `SKIP` lines that `cargo test` shows, and the `REQUIRE_*` variables that turn them into
//! failures.

use std::io::Write;

/// Whether the environment variable `require` (`REQUIRE_GPU`, `REQUIRE_NGINX`, ...) is `1`.
pub fn required(require: &str) -> bool {
    std::env::var(require).as_deref() == Ok("1")
}

/// Prints `SKIP <test>: <why>` straight to standard error, where `cargo test` shows it
/// (libtest captures the `print!` output of passing tests, so a `println!` SKIP line is
/// never seen), or fails the test when `require` is `1` (CI sets every `REQUIRE_*`).
pub fn skip(test: &str, require: &str, why: &str) {
    assert!(!required(require), "{test}: {require}=1 but {why}");
    let _ = writeln!(std::io::stderr().lock(), "SKIP {test}: {why}");
}
