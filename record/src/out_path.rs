//! The paths a command writes (`--out`), checked before anything runs: a
//! name the file system would refuse with "File name too long" is one line
//! of bad input, not a failure deep in a run.

use std::path::{Component, Path};

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
pub fn check_out_path(flag: &str, path: &Path, leaf_most: usize) -> Result<(), String> {
    if path.file_name().is_none() {
        return Err(format!("{flag} {}: name the folder or file to write (not `.`, `..` or `/`)", path.display()));
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
            return Err(format!("{flag}: the name `{}…` is {} bytes long, at most {most}", start(name), name.len()));
        }
    }
    if total > MAX_PATH_BYTES {
        return Err(format!(
            "{flag} {}…: the path is {total} bytes long, at most {MAX_PATH_BYTES}",
            start(path.as_os_str())
        ));
    }
    Ok(())
}
