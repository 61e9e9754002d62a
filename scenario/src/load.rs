//! A scenario loaded: its text read (a file, or a copy built into the
//! binary), `--set` applied and every field checked, into a [`Scenario`].
//! The way down: [`crate::syntax`] reads the text and words its TOML
//! errors, [`crate::overrides`] applies `--set`, [`crate::validate`] checks.

use std::path::Path;

use crate::error::ScenarioError;
use crate::file::ScenarioFile;
use crate::overrides::*;
use crate::scenario::{Scenario, MAX_FOLLOWERS};
use crate::syntax::*;
use crate::validate::*;

/// The scenarios inside the binary: the files of `scenarios/` that the
/// documentation runs, by name.
pub const BUILT_IN: [(&str, &str); 8] = [
    ("paper", include_str!("../../scenarios/paper.toml")),
    ("paper-velocity", include_str!("../../scenarios/paper-velocity.toml")),
    ("paper-tables", include_str!("../../scenarios/paper-tables.toml")),
    ("turtlebot", include_str!("../../scenarios/turtlebot.toml")),
    ("swap", include_str!("../../scenarios/swap.toml")),
    ("rotation", include_str!("../../scenarios/rotation.toml")),
    ("doorway", include_str!("../../scenarios/doorway.toml")),
    ("teleop", include_str!("../../scenarios/teleop.toml")),
];

/// The built-in scenario `path` names: `paper`, `paper.toml` or
/// `scenarios/paper.toml` (and the same for every name of [`BUILT_IN`]).
pub fn built_in(path: &Path) -> Option<(&'static str, &'static str)> {
    let text = path.to_str()?;
    let name = text.strip_prefix("scenarios/").unwrap_or(text);
    let name = name.strip_suffix(".toml").unwrap_or(name);
    BUILT_IN.iter().find(|(n, _)| *n == name).copied()
}

impl Scenario {
    /// Reads, overrides (`KEY=VALUE`, dotted keys) and validates a scenario file.
    ///
    /// A path that names no file but a built-in scenario ([`BUILT_IN`]:
    /// `paper`, `paper-velocity`, `paper-tables`, or their
    /// `scenarios/<name>.toml` as in a checkout) loads the copy inside the binary, so an installed binary
    /// runs the paper's scenario anywhere.
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self, ScenarioError> {
        let (label, text) = Self::source(path)?;
        let stem = match built_in(path).filter(|_| !path.exists()) {
            Some((name, _)) => name,
            None => path.file_stem().and_then(|s| s.to_str()).unwrap_or("scenario"),
        };
        Self::from_toml(&text, &label, stem, overrides)
    }

    /// The text [`Scenario::load`] reads for `path`, and the label it is
    /// known by in errors: the file's, or the built-in copy's (a run's
    /// hearing record carries it, so `formation replay` needs no file).
    pub fn source(path: &Path) -> Result<(String, String), ScenarioError> {
        if !path.exists() {
            if let Some((name, text)) = built_in(path) {
                return Ok((format!("{name} (built in)"), text.to_string()));
            }
        }
        let label = path.display().to_string();
        let text = read_scenario_file(path).map_err(|mut message| {
            if !path.exists() {
                let names: Vec<&str> = BUILT_IN.iter().map(|(n, _)| *n).collect();
                message.push_str(&format!(" (the built-in scenarios are {})", names.join(", ")));
            }
            ScenarioError::Io { file: label.clone(), message }
        })?;
        Ok((label, text))
    }

    /// Like [`Scenario::load`] from text; `label` names it in errors and
    /// `default_name` is the run name when the file gives none.
    pub fn from_toml(text: &str, label: &str, default_name: &str, overrides: &[String]) -> Result<Self, ScenarioError> {
        let line_of = |span: Option<std::ops::Range<usize>>| {
            span.map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1)
        };
        let file: ScenarioFile = toml::from_str(text).map_err(|e| ScenarioError::Syntax {
            file: label.to_string(),
            line: line_of(e.span()),
            message: syntax_message(text, &e),
        })?;
        let (file, overridden) =
            if overrides.is_empty() { (file, Vec::new()) } else { apply_overrides(text, label, overrides)? };
        validate(file, label, default_name, Some(text), &overridden, MAX_FOLLOWERS)
    }

    /// The file [`Scenario::from_toml`] validates: `text` with `overrides`
    /// applied, every key the text leaves out at its default (what the
    /// Python package reads keys from and saves).
    pub fn effective_file(text: &str, label: &str, overrides: &[String]) -> Result<ScenarioFile, ScenarioError> {
        if overrides.is_empty() {
            return toml::from_str(text).map_err(|e| ScenarioError::Syntax {
                file: label.to_string(),
                line: e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1),
                message: syntax_message(text, &e),
            });
        }
        apply_overrides(text, label, overrides).map(|(file, _)| file)
    }

    /// A scenario text built in code with up to `most_followers` followers
    /// (the benchmarks' rings of 100,000): a file or a `--set` is held to
    /// [`MAX_FOLLOWERS`].
    pub fn from_toml_sized(
        text: &str,
        label: &str,
        default_name: &str,
        most_followers: usize,
    ) -> Result<Self, ScenarioError> {
        let file: ScenarioFile = toml::from_str(text).map_err(|e| ScenarioError::Syntax {
            file: label.to_string(),
            line: None,
            message: syntax_message(text, &e),
        })?;
        validate(file, label, default_name, Some(text), &[], most_followers)
    }

    /// Validates a scenario built in code (no file lines to report).
    pub fn from_file(file: ScenarioFile, name: &str) -> Result<Self, ScenarioError> {
        validate(file, "", name, None, &[], MAX_FOLLOWERS)
    }
}
