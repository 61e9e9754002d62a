//! A scenario as text plus `--set` assignments: every change goes through
//! the same parser and checks as the command line's `--set`, and keys are
//! read from the file as it would run (defaults filled in).

use std::path::{Path, PathBuf};

use formation_scenario::generate::{self, GraphKind, Spec};
use formation_scenario::load::built_in;
use formation_scenario::Scenario;

/// A scenario file's text, where it came from, and the assignments made to it.
#[derive(Clone, Debug)]
pub struct Source {
    pub text: String,
    /// How errors name it: the file's path, or "paper (built in)".
    pub label: String,
    /// The run name when the file gives none (the file's stem).
    pub stem: String,
    /// `KEY=VALUE` assignments, as `--set` takes them, in order.
    pub overrides: Vec<String>,
    /// The validated scenario of `text` with `overrides`.
    pub scenario: Scenario,
    /// The file or built-in name it was loaded from (None: text or generated).
    pub path: Option<PathBuf>,
}

impl Source {
    /// A file, or a built-in scenario by name (`paper`, `paper-velocity`,
    /// `paper-tables`, `turtlebot`, `swap`, `rotation`), as `formation sim` finds it.
    pub fn load(path: &Path, overrides: Vec<String>) -> Result<Self, String> {
        let (label, text) = Scenario::source(path).map_err(|e| e.to_string())?;
        let stem = match built_in(path).filter(|_| !path.exists()) {
            Some((name, _)) => name.to_string(),
            None => path.file_stem().and_then(|s| s.to_str()).unwrap_or("scenario").to_string(),
        };
        let mut source = Self::from_text(text, label, stem, overrides)?;
        source.path = Some(path.to_path_buf());
        Ok(source)
    }

    /// A scenario from TOML text; `name` is its run name when the text gives none.
    pub fn from_text(text: String, label: String, stem: String, overrides: Vec<String>) -> Result<Self, String> {
        let scenario = Scenario::from_toml(&text, &label, &stem, &overrides).map_err(|e| e.to_string())?;
        Ok(Self { text, label, stem, overrides, scenario, path: None })
    }

    /// A generated scenario, as `formation generate` writes it.
    pub fn generate(spec: &Spec) -> Result<Self, String> {
        let text = generate::toml(spec).map_err(|e| e.to_string())?;
        let name = format!("{}-{}", spec.graph.name(), spec.followers);
        Self::from_text(text, format!("generated {name}"), name, Vec::new())
    }

    /// `KEY=VALUE` applied after the assignments so far, with `--set`'s
    /// checks; refused (and nothing changed) with its one-line message.
    pub fn set(&mut self, assignment: &str) -> Result<(), String> {
        let mut overrides = self.overrides.clone();
        overrides.push(assignment.to_string());
        let scenario =
            Scenario::from_toml(&self.text, &self.label, &self.stem, &overrides).map_err(|e| e.to_string())?;
        self.overrides = overrides;
        self.scenario = scenario;
        Ok(())
    }

    /// The file as it runs: every key, defaults filled in.
    pub fn table(&self) -> Result<toml::Table, String> {
        let file = Scenario::effective_file(&self.text, &self.label, &self.overrides).map_err(|e| e.to_string())?;
        toml::Table::try_from(file).map_err(|e| e.to_string())
    }

    /// The value at a dotted key (`robot.mass`, `followers[0].offset`), as
    /// `--set` names keys; `None` where the file has no such key.
    pub fn get(&self, key: &str) -> Result<Option<toml::Value>, String> {
        let root = toml::Value::Table(self.table()?);
        let mut at = &root;
        for part in key.split('.') {
            let (name, indexes) = part.split_at(part.find('[').unwrap_or(part.len()));
            let Some(next) = at.get(name) else { return Ok(None) };
            at = next;
            for index in indexes.split('[').skip(1) {
                let i: usize = index
                    .strip_suffix(']')
                    .and_then(|n| n.trim().parse().ok())
                    .ok_or_else(|| format!("{key}: `[{index}` is not an index"))?;
                let Some(next) = at.get(i) else { return Ok(None) };
                at = next;
            }
        }
        Ok(Some(at.clone()))
    }

    /// The scenario as a TOML file (every key written out; the original's
    /// comments are not kept).
    pub fn to_toml(&self) -> Result<String, String> {
        toml::to_string(&self.table()?).map_err(|e| e.to_string())
    }
}

/// The graph kind named as `formation generate --graph` names it.
pub fn graph_kind(name: &str) -> Result<GraphKind, String> {
    GraphKind::parse(name).ok_or_else(|| {
        let names: Vec<&str> = GraphKind::ALL.iter().map(|k| k.name()).collect();
        format!("graph {name:?}: unknown (the graphs are {})", names.join(", "))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper() -> Source {
        Source::load(Path::new("paper"), Vec::new()).expect("paper")
    }

    #[test]
    fn a_key_reads_as_the_file_gives_it_and_a_default_where_it_is_silent() {
        let mut s = paper();
        assert_eq!(s.get("dt").unwrap(), Some(toml::Value::Float(0.001)));
        assert_eq!(s.get("followers[1].id").unwrap(), Some(toml::Value::Integer(2)));
        assert_eq!(s.get("robot.weight").unwrap(), None);
        s.set("robot.mass=12.5").unwrap();
        assert_eq!(s.get("robot.mass").unwrap(), Some(toml::Value::Float(12.5)));
        assert_eq!(s.scenario.name, "paper");
    }

    #[test]
    fn a_refused_assignment_changes_nothing_and_says_what_the_command_line_says() {
        let mut s = paper();
        let e = s.set("robot.weight=3").unwrap_err();
        assert!(e.starts_with("--set robot.weight=3: unknown key `robot.weight`"), "{e}");
        assert!(s.overrides.is_empty());
    }

    /// Saved and loaded again, a changed scenario is the same scenario.
    #[test]
    fn a_saved_scenario_loads_as_the_one_saved() {
        let mut s = paper();
        s.set("faults+={node=3, from=8, to=11}").unwrap();
        s.set("filter=kf").unwrap();
        let text = s.to_toml().unwrap();
        let again = Source::from_text(text, "saved".into(), "paper".into(), Vec::new()).expect("the saved text loads");
        assert_eq!(again.table().unwrap(), s.table().unwrap());
        assert_eq!(format!("{:?}", again.scenario), format!("{:?}", s.scenario));
    }

    #[test]
    fn a_generated_ring_is_formation_generates() {
        let spec = Spec { chords: 2, ..Spec::new(12, graph_kind("ring").unwrap()) };
        let s = Source::generate(&spec).expect("ring");
        assert_eq!(s.scenario.followers.len(), 12);
        assert_eq!(s.text, generate::toml(&spec).unwrap());
        assert!(graph_kind("torus").unwrap_err().contains("ring, grid"));
    }
}
