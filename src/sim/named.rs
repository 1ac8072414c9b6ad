//! A scenario by built-in name or from a scenario TOML file: the one lookup behind
//! `imucald simulate --scenario` and the `sim:` source.

use super::Scenario;
use std::path::PathBuf;

/// Why a scenario could not be had.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// Nothing named.
    #[error(
        "needs a scenario name ({}) or a path to a scenario .toml",
        Scenario::names().join(", ")
    )]
    Missing,
    /// Neither a built-in name nor a name that could be a scenario file.
    #[error(
        "`{name}` is neither a built-in scenario ({}) nor a path to a scenario .toml",
        Scenario::names().join(", ")
    )]
    NotAScenario { name: String },
    /// Not a built-in name, and no file of that name could be read.
    #[error(
        "`{name}` is neither a built-in scenario ({}) nor a readable file: {source}",
        Scenario::names().join(", ")
    )]
    Unreadable {
        name: String,
        source: std::io::Error,
    },
    /// A scenario file that is not a valid scenario.
    #[error("scenario file {}: {source}", path.display())]
    Invalid {
        path: PathBuf,
        source: crate::error::Error,
    },
}

/// Whether `name` can name a scenario before any file is read: a built-in name or a path ending
/// in `.toml` (for addresses checked when they are given, the file read later by [`scenario`]).
pub(crate) fn check_name(name: &str) -> Result<(), ScenarioError> {
    if name.is_empty() {
        return Err(ScenarioError::Missing);
    }
    if Scenario::names().contains(&name) || name.ends_with(".toml") {
        return Ok(());
    }
    Err(ScenarioError::NotAScenario { name: name.into() })
}

/// The built-in scenario `name`, else the scenario file at that path.
pub fn scenario(name: &str) -> Result<Scenario, ScenarioError> {
    if name.is_empty() {
        return Err(ScenarioError::Missing);
    }
    if let Some(sc) = Scenario::named(name) {
        return Ok(sc);
    }
    let text = std::fs::read_to_string(name).map_err(|source| ScenarioError::Unreadable {
        name: name.into(),
        source,
    })?;
    Scenario::from_toml_str(&text).map_err(|source| ScenarioError::Invalid {
        path: name.into(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scenario_by_name_or_file_or_a_reason_listing_the_built_ins() {
        assert_eq!(scenario("bench").unwrap().name, "bench");
        check_name("rover").unwrap();
        check_name("mine.toml").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let good = dir.path().join("short.toml");
        std::fs::write(&good, "name = \"turntable\"\nduration_s = 3.0\n").unwrap();
        let sc = scenario(good.to_str().unwrap()).unwrap();
        assert_eq!((sc.name.as_str(), sc.duration_s), ("turntable", Some(3.0)));
        let bad = dir.path().join("bad.toml");
        std::fs::write(&bad, "name = \"tumble\"\nspeed = 3\n").unwrap();
        let e = scenario(bad.to_str().unwrap()).unwrap_err();
        assert!(matches!(e, ScenarioError::Invalid { .. }), "{e}");
        assert!(e.to_string().contains("speed"), "{e}");
        for e in [
            scenario("tumbel").unwrap_err(),
            scenario("").unwrap_err(),
            check_name("tumbel").unwrap_err(),
            check_name("").unwrap_err(),
        ] {
            let text = e.to_string();
            assert!(
                text.contains("turntable, tumble, flight") && text.contains("saturation"),
                "{text}"
            );
        }
        assert!(matches!(
            scenario("tumbel"),
            Err(ScenarioError::Unreadable { .. })
        ));
    }
}
