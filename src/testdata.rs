//! Where the tests find the real recordings (`../shared/data` beside the checkout), and what a test
//! does when they are absent: it says so plainly and returns, unless `IMUCALD_REQUIRE_DATA=1` (set by
//! `scripts/test`, which CI runs) makes the absence a failure. For tests only; no other use.

use std::path::PathBuf;

/// Environment variable that turns "recordings absent" into a test failure when set to `1`.
pub const REQUIRE_DATA_ENV: &str = "IMUCALD_REQUIRE_DATA";

/// The shared recordings directory, or `None` (with a message) when it is absent.
///
/// # Panics
/// When it is absent and `IMUCALD_REQUIRE_DATA=1`: a real-data test must not pass without its data.
pub fn shared_data() -> Option<PathBuf> {
    let p = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"));
    if p.is_dir() {
        return Some(p);
    }
    if std::env::var(REQUIRE_DATA_ENV).is_ok_and(|v| v == "1") {
        panic!(
            "{} is absent and {REQUIRE_DATA_ENV}=1: real-data tests need the shared recordings",
            p.display()
        );
    }
    eprintln!(
        "SKIPPED: {} is absent; real-data tests need the shared recordings beside the checkout",
        p.display()
    );
    None
}

#[cfg(test)]
mod tests {
    #[test]
    fn finds_the_recordings_or_says_why_not() {
        // Both branches are real: with the data present the path is a directory; without it, the
        // result is None unless the switch is set (then the call fails the test).
        match super::shared_data() {
            Some(p) => assert!(p.is_dir(), "{}", p.display()),
            None => assert!(std::env::var(super::REQUIRE_DATA_ENV).ok().as_deref() != Some("1")),
        }
    }
}
