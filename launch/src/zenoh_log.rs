//! Zenoh's own log lines of the nodes a launch starts: each node writes
//! them to a file of its own (the node shell's `FORMATION_ZENOH_LOG`)
//! rather than onto the terminal; at the end they go into the run folder's
//! `zenoh-log/` and the launch says in one line how many errors and
//! warnings which nodes logged, with the first error.

use formation_exit::Error;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;

/// The folder the nodes of this process's launch log into, while it runs.
static DIR: Mutex<Option<PathBuf>> = Mutex::new(None);

/// The run folder's subfolder that keeps the logs.
pub const SUBDIR: &str = formation_net::session::ZENOH_LOG_SUBDIR;

/// Starts collecting beside the run folder `out` (the monitor replaces
/// `out` itself), in `<out>.zenoh-log`. One left there by a launch that
/// was killed is replaced; a folder there that holds anything but
/// zenoh logs is the user's, and refused.
pub fn start(out: &Path) -> Result<Option<PathBuf>, Error> {
    let dir = formation_record::folder::beside(out, formation_net::session::ZENOH_LOG_BESIDE);
    if let Ok(m) = std::fs::symlink_metadata(&dir) {
        let foreign = if m.is_dir() {
            formation_record::folder::names_in(&dir).unwrap_or_default().into_iter().find(|n| {
                let p = dir.join(n);
                !(n.to_string_lossy().ends_with(".log") && std::fs::symlink_metadata(p).is_ok_and(|m| m.is_file()))
            })
        } else {
            Some(std::ffi::OsString::new())
        };
        if let Some(name) = foreign {
            let what = if name.is_empty() {
                "exists and is not a folder".to_string()
            } else {
                format!("holds {}, which a launch does not write", name.to_string_lossy())
            };
            return Err(Error::Input(format!(
                "--out: {} (where a launch keeps zenoh's log lines while it runs) {what}: refusing to replace it \
                 (move it, or choose another --out)",
                dir.display()
            )));
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
    if std::fs::create_dir_all(&dir).is_err() {
        return Ok(None);
    }
    *DIR.lock().unwrap_or_else(|p| p.into_inner()) = Some(dir.clone());
    Ok(Some(dir))
}

/// Tells node `name`'s command where its zenoh lines go.
pub fn route(c: &mut Command, name: &str) {
    if let Some(dir) = DIR.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
        let file: String = name.chars().map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '-' }).collect();
        c.env(formation_net::node::ZENOH_LOG_ENV, dir.join(format!("{file}.log")));
    }
}

/// [`finish`], and its lines on stderr: the sum (not with `quiet`) and
/// the transports closed (always).
pub fn finish_and_say(dir: Option<PathBuf>, out: &Path, quiet: bool) {
    if let Some(said) = finish(dir, out) {
        if !quiet {
            eprintln!("{}", said.line);
        }
        if let Some(closed) = said.closed {
            eprintln!("{closed}");
        }
    }
}

/// What zenoh logged in a run, summed up.
pub struct Said {
    /// The line that sums it up.
    pub line: String,
    /// The transports zenoh closed, as one line (said even with `-q`).
    pub closed: Option<String>,
}

/// Moves what was logged into `out/zenoh-log/` (nothing logged: no
/// folder), adds `zenoh_log` to `out/network.json`, and answers what
/// sums it up, if anything was logged.
pub fn finish(dir: Option<PathBuf>, out: &Path) -> Option<Said> {
    *DIR.lock().unwrap_or_else(|p| p.into_inner()) = None;
    let dir = dir?;
    let mut zids = Vec::new();
    let mut files: Vec<(String, String)> = std::fs::read_dir(&dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let text = std::fs::read_to_string(e.path()).ok()?;
            let name = e.path().file_stem()?.to_string_lossy().into_owned();
            Some((name, text))
        })
        .collect();
    files.sort();
    // The nodes' own notes of their zids are not zenoh's lines.
    for (name, text) in &mut files {
        let (notes, rest): (Vec<&str>, Vec<&str>) =
            text.lines().partition(|l| l.starts_with(formation_net::session::ZID_NOTE));
        zids.extend(notes.iter().map(|l| (l[formation_net::session::ZID_NOTE.len()..].to_string(), name.clone())));
        *text = rest.iter().map(|l| format!("{l}\n")).collect();
    }
    files.retain(|(_, t)| !t.is_empty());
    if files.is_empty() {
        let _ = std::fs::remove_dir_all(&dir);
        return None;
    }
    // Into the run folder; where there is none (the monitor failed) they stay beside it.
    let kept = out.join(SUBDIR);
    let _ = std::fs::remove_dir_all(&kept);
    let kept = if out.is_dir() && std::fs::rename(&dir, &kept).is_ok() { kept } else { dir };
    let closed = closed_transports(&files, &zids);
    add_to_network_json(out, &files, &closed);
    Some(Said { line: summary(&files, &kept), closed: closed_line(&closed) })
}

/// (by, to, count) of zenoh's "Unable to push non droppable network
/// message to ZID. Closing transport!", `to` named by the zids the
/// nodes noted.
pub fn closed_transports(files: &[(String, String)], zids: &[(String, String)]) -> Vec<(String, String, usize)> {
    let mut out: Vec<(String, String, usize)> = Vec::new();
    for (by, text) in files {
        for l in text.lines().filter(|l| l.contains("Closing transport")) {
            let zid = l.split_once(" message to ").map(|(_, r)| r.split(['.', ' ']).next().unwrap_or(""));
            let to = zid.map(|z| zids.iter().find(|(id, _)| id == z).map_or(format!("zid {z}"), |(_, n)| n.clone()));
            let to = to.unwrap_or_else(|| "a peer".to_string());
            match out.iter_mut().find(|(b, t, _)| b == by && *t == to) {
                Some(e) => e.2 += 1,
                None => out.push((by.clone(), to, 1)),
            }
        }
    }
    out
}

fn closed_line(closed: &[(String, String, usize)]) -> Option<String> {
    if closed.is_empty() {
        return None;
    }
    let n: usize = closed.iter().map(|c| c.2).sum();
    let each: Vec<String> = closed
        .iter()
        .map(|(by, to, k)| if *k == 1 { format!("{by} → {to}") } else { format!("{by} → {to} ({k} times)") })
        .collect();
    Some(format!(
        "warning: zenoh closed {n} transport{} ({}): a message that may not be dropped found the queue to that \
         node full for zenoh's 5 s (the node starved of CPU, or its link stalled); it reconnected, and what it \
         missed meanwhile is in network.json (isolated, telemetry_resent)",
        if n == 1 { "" } else { "s" },
        each.join(", ")
    ))
}

/// `network.json`'s `zenoh_log`: errors and warnings per node, the
/// transports closed, the folder.
fn add_to_network_json(out: &Path, files: &[(String, String)], closed: &[(String, String, usize)]) {
    let path = out.join("network.json");
    let Some(mut v) =
        std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
    else {
        return;
    };
    let count = |text: &str, level: &str| text.lines().filter(|l| l.contains(level)).count();
    let nodes: serde_json::Map<String, serde_json::Value> = files
        .iter()
        .map(|(n, t)| (n.clone(), serde_json::json!({ "errors": count(t, " ERROR "), "warnings": count(t, " WARN ") })))
        .collect();
    let closed: Vec<serde_json::Value> =
        closed.iter().map(|(by, to, k)| serde_json::json!({ "by": by, "to": to, "count": k })).collect();
    if let Some(o) = v.as_object_mut() {
        o.insert(
            "zenoh_log".into(),
            serde_json::json!({ "folder": SUBDIR, "nodes": nodes, "transports_closed": closed }),
        );
    }
    if let Ok(text) = serde_json::to_string_pretty(&v) {
        let _ = std::fs::write(&path, text + "\n");
    }
}

/// "zenoh logged 3 errors and 1 warning (agent-3: 3 errors; router: 1
/// warning); the first error: …; every line is in OUT/zenoh-log/".
pub fn summary(files: &[(String, String)], kept: &Path) -> String {
    let count = |text: &str, level: &str| text.lines().filter(|l| l.contains(level)).count();
    let mut per_node = Vec::new();
    let (mut errors, mut warnings) = (0, 0);
    for (name, text) in files {
        let (e, w) = (count(text, " ERROR "), count(text, " WARN "));
        errors += e;
        warnings += w;
        if e + w > 0 {
            per_node.push(format!("{name}: {}", counted(e, w)));
        }
    }
    let first = files.iter().flat_map(|(_, t)| t.lines()).find(|l| l.contains(" ERROR "));
    let first = first.map_or(String::new(), |l| {
        let msg = l.split_once(" ERROR ").map_or(l, |(_, m)| m).trim();
        let short: String = msg.chars().take(200).collect();
        format!("; the first error: {short}")
    });
    if per_node.is_empty() {
        let lines: usize = files.iter().map(|(_, t)| t.lines().count()).sum();
        return format!("zenoh logged {lines} lines, no errors or warnings; they are in {}", kept.display());
    }
    format!(
        "zenoh logged {} ({}){first}; every line is in {}",
        counted(errors, warnings),
        per_node.join("; "),
        kept.display()
    )
}

fn counted(errors: usize, warnings: usize) -> String {
    let plural = |n: usize, w: &str| format!("{n} {w}{}", if n == 1 { "" } else { "s" });
    match (errors, warnings) {
        (e, 0) => plural(e, "error"),
        (0, w) => plural(w, "warning"),
        (e, w) => format!("{} and {}", plural(e, "error"), plural(w, "warning")),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_summary_counts_errors_and_warnings_per_node_and_quotes_the_first_error() {
        let files = vec![
            ("agent-3".to_string(), "2026 ERROR zenoh::net: Unable to push non droppable network message. Closing transport!\n2026 ERROR zenoh::net: again\n".to_string()),
            ("router".to_string(), "2026  WARN zenoh::x: slow\n".to_string()),
        ];
        let line = super::summary(&files, std::path::Path::new("runs/x/zenoh-log"));
        assert_eq!(
            line,
            "zenoh logged 2 errors and 1 warning (agent-3: 2 errors; router: 1 warning); the first error: \
             zenoh::net: Unable to push non droppable network message. Closing transport!; every line is in \
             runs/x/zenoh-log"
        );
    }

    /// The transports zenoh closed, by the node that closed them and
    /// the node they went to (named by the zids the nodes noted).
    #[test]
    fn closed_transports_name_both_nodes() {
        let push = |zid: &str| {
            format!("2026-11-26T00:55:13Z ERROR zenoh_transport::unicast::universal::tx: Unable to push non droppable network message to {zid}. Closing transport!\n")
        };
        let files = vec![
            ("router".to_string(), push("893eaf0a") + &push("893eaf0a") + &push("77aa")),
            ("agent-1".to_string(), "2026 WARN zenoh::x: slow\n".to_string()),
        ];
        let zids = vec![("893eaf0a".to_string(), "agent-4".to_string())];
        let closed = super::closed_transports(&files, &zids);
        assert_eq!(
            closed,
            vec![("router".to_string(), "agent-4".to_string(), 2), ("router".to_string(), "zid 77aa".to_string(), 1)]
        );
        let line = super::closed_line(&closed).expect("a line");
        assert!(
            line.starts_with("warning: zenoh closed 3 transports (router → agent-4 (2 times), router → zid 77aa)"),
            "{line}"
        );
        assert_eq!(super::closed_line(&[]), None);
    }
}
