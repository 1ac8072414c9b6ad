//! The Python the tests and benches run their peers with: `.venv` (which `scripts/test` and
//! `scripts/bench` install), or `IMUCALD_PYTHON`.

/// The Python `scripts/test` installs (`.venv`), or `IMUCALD_PYTHON`.
pub fn python_path() -> String {
    std::env::var("IMUCALD_PYTHON")
        .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/.venv/bin/python").to_string())
}

/// [`python_path`] when it imports `modules` (`"scipy, pymavlink"`), else `None`.
pub fn python_importing(modules: &str) -> Option<String> {
    let p = python_path();
    std::process::Command::new(&p)
        .args(["-c", &format!("import {modules}")])
        .output()
        .is_ok_and(|o| o.status.success())
        .then_some(p)
}
