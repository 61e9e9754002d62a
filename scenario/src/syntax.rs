//! A scenario file's text read and its TOML errors put in plain words,
//! with the line and the dotted field they are about.

use std::path::Path;

use crate::file::exact;

use crate::scenario::*;

/// Reads a scenario file: a regular file (not a FIFO, a device or a
/// folder, which could block or never end) of at most [`MAX_FILE_BYTES`].
pub(crate) fn read_scenario_file(path: &Path) -> Result<String, String> {
    use std::io::Read;
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot read: {e}"))?;
    if meta.is_dir() {
        return Err("is a folder, not a scenario file".into());
    }
    if !meta.is_file() {
        return Err("is not a regular file (a FIFO, a socket or a device): a scenario must be a file".into());
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(format!("is {} bytes; a scenario file may have at most {MAX_FILE_BYTES}", meta.len()));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| format!("cannot read: {e}"))?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(format!("is more than {MAX_FILE_BYTES} bytes, the most a scenario file may have"));
    }
    String::from_utf8(bytes)
        .map_err(|e| format!("is not UTF-8 text (byte {}): a scenario is a TOML file", e.utf8_error().valid_up_to()))
}

/// A deserialization message in plain words, prefixed with the key it is
/// about where the source says (`followers[2].offset: expected 2 numbers,
/// got 3`; `dt: expected a number, found the string "x"`).
pub(crate) fn syntax_message(text: &str, e: &toml::de::Error) -> String {
    let message = plain_message(e.message().trim());
    let field = e.span().and_then(|s| field_at(text, s.start));
    let key = duplicate_key(&message)
        .map(str::to_string)
        .or_else(|| (message == "duplicate key").then(|| key_at(text, e.span()?.start)).flatten());
    let message = match key {
        Some(key) => match first_line_of(text, &key, e.span().map(|s| s.start)) {
            Some(line) if message == "duplicate key" => {
                format!("duplicate key `{key}`: first given on line {line} (a key may be given once)")
            }
            Some(line) => format!("{message} (first given on line {line}; a key may be given once)"),
            None => format!("{message} (a key may be given once)"),
        },
        None => message,
    };
    match field {
        Some(field) if !message.starts_with(&format!("{field}:")) => format!("{field}: {message}"),
        None if message.starts_with("unknown key") => match e.span().and_then(|s| table_before(text, s.start)) {
            Some(table) => format!("[{table}]: {message}"),
            None => message,
        },
        _ => message,
    }
}

/// The `[table]` or `[[array]]` header last opened before byte `at`.
pub(crate) fn table_before(text: &str, at: usize) -> Option<String> {
    text.get(..at)?
        .lines()
        .rev()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .find(|l| l.starts_with('['))
        .map(|l| l.trim_matches(['[', ']']).trim().to_string())
}

/// The key written at byte `at` of the source (bare or quoted).
pub(crate) fn key_at(text: &str, at: usize) -> Option<String> {
    let rest = text.get(at..)?;
    let key: String = rest
        .trim_start_matches(['[', ' '])
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || "_-\"".contains(*c))
        .filter(|&c| c != '"')
        .collect();
    (!key.is_empty()).then_some(key)
}

/// The key of a `duplicate key` message.
pub(crate) fn duplicate_key(message: &str) -> Option<&str> {
    message.strip_prefix("duplicate key `")?.split('`').next()
}

/// The first line, before byte `before`, where `key` is assigned or opens a table.
pub(crate) fn first_line_of(text: &str, key: &str, before: Option<usize>) -> Option<usize> {
    let end = before.unwrap_or(text.len()).min(text.len());
    let mut offset = 0;
    for (n, line) in text.lines().enumerate() {
        if offset >= end {
            break;
        }
        offset += line.len() + 1;
        let t = line.split('#').next().unwrap_or("").trim();
        let head = t.trim_start_matches('[').trim_end_matches(']').trim();
        let assigned = t.split_once('=').map(|(k, _)| k.trim().trim_matches('"'));
        if assigned == Some(key) || (t.starts_with('[') && head == key) {
            return Some(n + 1);
        }
    }
    None
}

/// serde's and toml's words (`invalid type: string "x", expected f64`,
/// `expected struct RobotFile`, `wanted string or table`) in plain ones.
pub(crate) fn plain_message(message: &str) -> String {
    fn expected(what: &str) -> String {
        let what = what.trim();
        match what {
            "f64" | "f32" => "a number".into(),
            "u64" | "usize" => "a whole number ≥ 0".into(),
            "u32" => "a whole number from 0 to 4294967295".into(),
            "a boolean" | "bool" => "true or false".into(),
            "a sequence" => "an array [ ... ]".into(),
            "a string" => "a string in quotes".into(),
            _ if what.starts_with("struct LinkFaultFile") => {
                "a fault row, a table such as { node = 2, from = 10.0, to = 13.0 }".into()
            }
            _ if what.starts_with("struct ") => "a table ([name] or { key = value, ... })".into(),
            _ if what.starts_with("enum ") => "a name in quotes".into(),
            _ => what.to_string(),
        }
    }
    fn found(what: &str) -> String {
        let what = what.trim();
        match what {
            "unit variant" | "unit value" => "nothing (an empty value)".into(),
            "sequence" => "an array".into(),
            "map" => "a table".into(),
            _ => what
                .strip_prefix("integer ")
                .map(|v| format!("the whole number {}", v.trim_matches('`')))
                .or_else(|| what.strip_prefix("floating point ").map(|v| format!("the number {}", v.trim_matches('`'))))
                .or_else(|| what.strip_prefix("boolean ").map(|v| v.trim_matches('`').to_string()))
                .or_else(|| what.strip_prefix("string ").map(|v| format!("the string {v}")))
                .unwrap_or_else(|| what.to_string()),
        }
    }
    let m = message.trim();
    // An enum (kinematic, filter, …) given a table or an array.
    if m.starts_with("wanted exactly 1 element") || m.ends_with("expected string only") {
        return "expected a name in quotes (for example \"bio\" or \"asif\"), found a table or an array".into();
    }
    for prefix in ["invalid type: ", "invalid value: "] {
        if let Some(rest) = m.strip_prefix(prefix) {
            if let Some((what, exp)) = rest.rsplit_once(", expected ") {
                return format!("expected {}, found {}", expected(exp), found(what));
            }
        }
    }
    if m == "wanted string or table" {
        return "expected a name in quotes (for example \"bio\")".into();
    }
    if let Some(rest) = m.strip_prefix("unknown field `") {
        if let Some((key, others)) = rest.split_once("`, expected ") {
            return format!("unknown key `{key}` (the keys here are {})", others.replace("one of ", ""));
        }
        if let Some((key, _)) = rest.split_once("`, there are no fields") {
            return format!("unknown key `{key}` (this table has no keys)");
        }
    }
    if let Some(rest) = m.strip_prefix("missing field `") {
        return format!("missing key `{}`", rest.trim_end_matches('`'));
    }
    if let Some(rest) = m.strip_prefix("unknown variant `") {
        if let Some((v, others)) = rest.split_once("`, expected ") {
            return format!("`{v}` is not one of: {}", others.replace("one of ", "").replace('`', ""));
        }
    }
    if let Some(rest) = m.strip_prefix("expected ") {
        if !exact::is_length_error(m) && !rest.contains(',') {
            return format!("expected {}", expected(rest));
        }
    }
    m.to_string()
}

/// The dotted field (`followers[2].offset`, `edges[1]`) of the innermost
/// value that spans byte `at` of the TOML source.
pub(crate) fn field_at(source: &str, at: usize) -> Option<String> {
    fn path_to(value: &toml::Spanned<toml::de::DeValue<'_>>, at: usize, path: &mut String) -> bool {
        let len = path.len();
        let found = match value.get_ref() {
            toml::de::DeValue::Table(t) => t.iter().any(|(key, v)| {
                path.truncate(len);
                path.push_str(&format!(".{}", key.get_ref()));
                path_to(v, at, path)
            }),
            toml::de::DeValue::Array(a) => a.iter().enumerate().any(|(i, v)| {
                path.truncate(len);
                path.push_str(&format!("[{i}]"));
                path_to(v, at, path)
            }),
            _ => false,
        };
        if !found {
            path.truncate(len);
        }
        found || value.span().contains(&at)
    }
    let document = toml::de::DeTable::parse(source).ok()?;
    let mut path = String::new();
    let root = toml::Spanned::new(document.span(), toml::de::DeValue::Table(document.into_inner()));
    (path_to(&root, at, &mut path) && !path.is_empty()).then(|| path.trim_start_matches('.').to_string())
}

/// The 1-based line of a dotted field (`robot.mass`, `followers[2].offset`,
/// `edges[1]`) in the TOML source, when it can be found by its key.
pub(crate) fn find_line(source: &str, field: &str) -> Option<usize> {
    let target = field.split('[').next().unwrap_or(field);
    let index: Option<usize> = field.split_once('[').and_then(|(_, rest)| rest.split(']').next()?.parse().ok());
    let mut context = String::new();
    let mut array_counts = std::collections::HashMap::<String, usize>::new();
    let mut best = None;
    for (n, raw) in source.lines().enumerate() {
        let line = raw.trim();
        if let Some(h) = line.strip_prefix("[[") {
            let name = h.split("]]").next().unwrap_or("").trim().to_string();
            let count = array_counts.entry(name.clone()).or_insert(0);
            context = format!("{name}[{count}]");
            *count += 1;
            if field == context {
                return Some(n + 1);
            }
            continue;
        }
        if let Some(h) = line.strip_prefix('[') {
            context = h.split(']').next().unwrap_or("").trim().to_string();
            if field == context || field.starts_with(&format!("{context}.")) && best.is_none() {
                best = Some(n + 1);
            }
            continue;
        }
        let Some((key, _)) = line.split_once('=') else { continue };
        let key = key.trim().trim_matches('"');
        let full = if context.is_empty() { key.to_string() } else { format!("{context}.{key}") };
        if full == field || (index.is_some() && full == target) {
            return Some(n + 1);
        }
        if field.starts_with(&format!("{full}.")) {
            best = Some(n + 1);
        }
    }
    best
}
