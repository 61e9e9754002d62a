//! Command-line arguments several commands share.

use std::path::{Component, Path, PathBuf};

use clap::Args;
use formation_topology::Scenario;

use crate::error::CliError;

/// Scenario selection shared by every command that runs one.
#[derive(Args, Debug, Clone)]
pub struct ScenarioArgs {
    /// Scenario file (TOML), or a built-in one by name (paper, paper-velocity, paper-tables, turtlebot). Every key: docs/scenarios.md.
    pub scenario: PathBuf,
    /// Override a scenario value without editing the file, e.g.
    /// `--set filter=kf --set fault.time=10 --set duration=5`. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
}

impl ScenarioArgs {
    pub fn load(&self) -> Result<Scenario, CliError> {
        Scenario::load(&self.scenario, &self.overrides).map_err(|e| CliError::Input(e.to_string()))
    }
}

/// The longest path the file systems take (PATH_MAX less a margin).
const MAX_PATH_BYTES: usize = 4000;
/// The longest name of one folder or file (NAME_MAX).
pub const MAX_NAME_BYTES: usize = 255;
/// The longest name of a folder a command writes: room for `.partial`
/// and the like after it.
pub const MAX_OUT_NAME_BYTES: usize = 200;

/// Refuses, before anything runs, a path to write (`flag`, e.g. `--out`)
/// that the file system would refuse with "File name too long": one of
/// more than [`MAX_PATH_BYTES`], a folder name of more than 255 bytes, or a
/// last name of more than `leaf_most` bytes.
pub fn check_out_path(flag: &str, path: &Path, leaf_most: usize) -> Result<(), CliError> {
    if path.file_name().is_none() {
        return Err(CliError::Input(format!(
            "{flag} {}: name the folder or file to write (not `.`, `..` or `/`)",
            path.display()
        )));
    }
    let total = path.as_os_str().len();
    let start = |name: &std::ffi::OsStr| -> String { name.to_string_lossy().chars().take(20).collect() };
    let names: Vec<&std::ffi::OsStr> = path
        .components()
        .filter_map(|c| match c {
            Component::Normal(n) => Some(n),
            _ => None,
        })
        .collect();
    for (k, name) in names.iter().enumerate() {
        let most = if k + 1 == names.len() { leaf_most } else { MAX_NAME_BYTES };
        if name.len() > most {
            return Err(CliError::Input(format!(
                "{flag}: the name `{}…` is {} bytes long, at most {most}",
                start(name),
                name.len()
            )));
        }
    }
    if total > MAX_PATH_BYTES {
        return Err(CliError::Input(format!(
            "{flag} {}…: the path is {total} bytes long, at most {MAX_PATH_BYTES}",
            start(path.as_os_str())
        )));
    }
    Ok(())
}

/// The command line parsed, or one line and exit status 2: clap's own
/// errors take 3–5 lines (the error, a tip, the usage, "For more
/// information"); they become the error and its tip on one line, with the
/// `--help` to ask. Help and version print as clap prints them.
pub fn parse_or_exit<T: clap::Parser>() -> T {
    use clap::error::ErrorKind;
    match T::try_parse() {
        Ok(t) => t,
        Err(e) => match e.kind() {
            ErrorKind::DisplayHelp
            | ErrorKind::DisplayVersion
            | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
            _ => {
                eprintln!("{}", one_line(&e.render().to_string()));
                std::process::exit(2)
            }
        },
    }
}

/// clap's error text on one line: "error: …; tip: … (formation sim --help)".
fn one_line(text: &str) -> String {
    let mut parts = Vec::new();
    let mut help = None;
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        if let Some(usage) = line.strip_prefix("Usage:") {
            // "formation sim [OPTIONS] <SCENARIO>": the command's own words.
            let words: Vec<&str> = usage.split_whitespace().take_while(|w| !w.starts_with(['[', '<', '-'])).collect();
            help = Some(format!("{} --help", words.join(" ")));
        } else if !line.starts_with("For more information") {
            parts.push(line.to_string());
        }
    }
    let mut out = parts.join("; ").replace(":; ", ": ");
    if !out.starts_with("error:") {
        out = format!("error: {out}");
    }
    match help {
        Some(h) => format!("{out} ({h})"),
        None => out,
    }
}

#[cfg(test)]
mod tests {
    use super::one_line;

    #[test]
    fn clap_errors_become_one_line() {
        let text = "error: invalid value 'bogus' for '--robots <WHO>'\n  [possible values: simulated, stand-in, \
                    external]\n\nFor more information, try '--help'.\n";
        assert_eq!(
            one_line(text),
            "error: invalid value 'bogus' for '--robots <WHO>'; [possible values: simulated, stand-in, external]"
        );
        let text = "error: unexpected argument '--foo' found\n\n  tip: to pass '--foo' as a value, use '-- \
                    --foo'\n\nUsage: formation sim [OPTIONS] <SCENARIO>\n\nFor more information, try '--help'.\n";
        assert_eq!(
            one_line(text),
            "error: unexpected argument '--foo' found; tip: to pass '--foo' as a value, use '-- --foo' (formation \
             sim --help)"
        );
    }
}
