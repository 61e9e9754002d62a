//! `--set KEY=VALUE`: overrides applied to a scenario's parsed document,
//! one at a time, so that an error names the assignment at fault.

use crate::error::ScenarioError;
use crate::file::ScenarioFile;

use crate::syntax::*;

/// The dotted keys `--set` gave a value, each with its assignment, in order.
pub(crate) type Overridden = Vec<(String, String)>;

/// Applies `KEY=VALUE` overrides to the parsed document, one at a time so
/// that an error names the assignment at fault.
pub(crate) fn apply_overrides(
    text: &str,
    label: &str,
    overrides: &[String],
) -> Result<(ScenarioFile, Overridden), ScenarioError> {
    let file_error =
        |message: &str| ScenarioError::Syntax { file: label.to_string(), line: None, message: message.trim().into() };
    let mut table: toml::Table = toml::from_str(text).map_err(|e| file_error(e.message()))?;
    // The file on its own must convert, so that a failure below is the
    // assignment's and never the file's.
    table.clone().try_into::<ScenarioFile>().map_err(|e| file_error(e.message()))?;
    let mut overridden = Vec::with_capacity(overrides.len());
    for assignment in overrides {
        let err = |message: String| ScenarioError::Override { assignment: assignment.clone(), message };
        let (key, value) = assignment.split_once('=').ok_or_else(|| err("expected KEY=VALUE".into()))?;
        let (key, value) = (key.trim(), value.trim());
        if key.is_empty() {
            return Err(err("empty key".into()));
        }
        let value = parse_value(value).map_err(err)?;
        // A table replaces the whole table at `key`: a value an earlier
        // --set gave inside it would be dropped without a word.
        if value.is_table() && !key.ends_with('+') {
            let inside = |given: &str| given.strip_prefix(key).is_some_and(|rest| rest.starts_with(['.', '[']));
            if let Some((given, earlier)) = overridden.iter().find(|(given, _): &&(String, String)| inside(given)) {
                return Err(err(format!(
                    "conflicts with --set {earlier}: a table replaces all of `{key}`, so {given} would be dropped \
                     (give every key in the one table, or each as {key}.KEY=VALUE)"
                )));
            }
        }
        let mut next = table.clone();
        match key.strip_suffix('+') {
            Some(array) => append_path(&mut next, array.trim(), value).map_err(err)?,
            None => set_path(&mut next, key, value).map_err(err)?,
        }
        next.clone().try_into::<ScenarioFile>().map_err(|e| err(override_message(key, e.message())))?;
        // `faults+=…` gave the array's new last element, nothing before it.
        let given = match key.strip_suffix('+').map(str::trim) {
            Some(array) => format!("{array}[{}]", array_len(&next, array).saturating_sub(1)),
            None => key.to_string(),
        };
        table = next;
        overridden.push((given, assignment.clone()));
    }
    let file = table
        .try_into::<ScenarioFile>()
        .map_err(|e| ScenarioError::Override { assignment: overrides.join(" "), message: e.message().to_string() })?;
    Ok((file, overridden))
}

pub(crate) fn override_message(key: &str, message: &str) -> String {
    let message = plain_message(message);
    let key = key.trim_end_matches('+').trim();
    if let Some(rest) = message.strip_prefix("unknown key `") {
        // The message names the last part of the key: name all of it; or a
        // key inside the table or array the value gave (`shunting={…, e=1}`:
        // it named the table, which exists, and listed the table's keys).
        let (name, after) = rest.split_once('`').unwrap_or((rest, ""));
        if key.rsplit('.').next() == Some(name) {
            format!("unknown key `{key}`{after}")
        } else {
            format!("`{key}`: unknown key `{name}`{after}")
        }
    } else if message.starts_with("unknown key") {
        format!("unknown key `{key}` ({message})")
    } else {
        format!("`{key}`: {message}")
    }
}

/// A TOML value if VALUE parses as one (number, bool, array, inline table,
/// quoted string); a bare word (`filter=kf`, `leader.trajectory=figure-eight`,
/// a path such as `leader.recorded=runs/teleop`) is a string; anything else is an error with TOML's reason (a missing
/// bracket is not taken for a string).
pub(crate) fn parse_value(value: &str) -> Result<toml::Value, String> {
    if value.trim().is_empty() {
        return Err("no value after `=` (write KEY=VALUE, e.g. duration=20 or filter=kf)".into());
    }
    match toml::from_str::<toml::Table>(&format!("v = {value}")) {
        Ok(mut t) => t.remove("v").ok_or_else(|| format!("`{value}` is not a value")),
        // Digits TOML cannot hold were taken for a word ("found the string").
        Err(_)
            if {
                let digits = value.trim_start_matches(['-', '+']);
                !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit())
            } =>
        {
            Err(format!("{value} is beyond the whole numbers a value can hold (±9223372036854775807)"))
        }
        Err(_) if !value.is_empty() && value.chars().all(|c| c.is_ascii_alphanumeric() || "-_./".contains(c)) => {
            Ok(toml::Value::String(value.to_string()))
        }
        Err(e) => Err(format!(
            "`{value}` is not a TOML value ({}); write a number, true/false, [array], {{table}} or a quoted \"string\"",
            e.message().trim()
        )),
    }
}

/// The length of the array at dotted `key` (0 if there is none).
pub(crate) fn array_len(table: &toml::Table, key: &str) -> usize {
    let mut parts = key.split('.').peekable();
    let mut current = table;
    while let Some(part) = parts.next() {
        match (current.get(part), parts.peek()) {
            (Some(toml::Value::Array(a)), None) => return a.len(),
            (Some(toml::Value::Table(t)), Some(_)) => current = t,
            _ => return 0,
        }
    }
    0
}

/// `KEY+=VALUE`: appends VALUE to the array at KEY (creating it), e.g.
/// `--set 'faults+={node=3, from=10, to=13}'`.
pub(crate) fn append_path(table: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let mut current = toml::Value::Array(Vec::new());
    let mut cursor: Option<&toml::Table> = Some(table);
    let parts: Vec<&str> = key.split('.').collect();
    for (n, part) in parts.iter().enumerate() {
        let found = cursor.and_then(|t| t.get(*part));
        if n + 1 == parts.len() {
            if let Some(v) = found {
                current = v.clone();
            }
        } else {
            cursor = found.and_then(toml::Value::as_table);
        }
    }
    let toml::Value::Array(mut items) = current else {
        return Err(format!("`{key}` is not an array, cannot append to it"));
    };
    items.push(value);
    set_path(table, key, toml::Value::Array(items))
}

pub(crate) fn set_path(table: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let mut parts = key.split('.').peekable();
    let mut current = table;
    while let Some(part) = parts.next() {
        if parts.peek().is_none() {
            current.insert(part.to_string(), value);
            return Ok(());
        }
        let entry = current.entry(part.to_string()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
        current = match entry {
            toml::Value::Table(t) => t,
            _ => return Err(format!("`{part}` is not a table, cannot set `{key}`")),
        };
    }
    Ok(())
}
