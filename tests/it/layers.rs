//! The workspace's layers, read from its own files: every crate depends
//! only on crates of lower layers; inside every crate no module imports one
//! that imports it, directly or around a circle; and exit statuses are the
//! `formation` binary crate's alone. Each failure names the files and the
//! path that breaks the rule.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The layers, lowest first: a crate may use only crates listed before it.
const LAYERS: [&str; 19] = [
    // How every command ends: the error kinds, exit statuses, the shutdown.
    "formation-exit",
    // ROS 2's wire and bags: uses no other formation crate.
    "formation-ros2",
    "formation-plant",
    "formation-leader",
    "formation-control",
    "formation-scenario",
    "formation-record",
    "formation-sim",
    "formation-protocol",
    "formation-certs",
    "formation-view",
    // The live run's record, health and watch; below the offline replay,
    // which writes its folder with the same Recorder.
    "formation-recorder",
    "formation-replay",
    // Reports, the paper's tables, calibration: no network, no runtime.
    "formation-report",
    // The Python package: the simulator, run folders, the paper's tables.
    "formation-python",
    "formation-net",
    // Nodes as processes: launch, the lab, their supervisor.
    "formation-launch",
    "formation-bench",
    "formation",
];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// (package name, folder) of every workspace member.
fn members() -> Vec<(String, PathBuf)> {
    let text = std::fs::read_to_string(root().join("Cargo.toml")).expect("Cargo.toml");
    let line = text.lines().find(|l| l.trim_start().starts_with("members")).expect("workspace members");
    let list = line.split_once('[').and_then(|(_, r)| r.split_once(']')).expect("members = [...]").0;
    list.split(',')
        .map(|m| m.trim().trim_matches('"'))
        .filter(|m| !m.is_empty())
        .map(|m| {
            let dir = root().join(m);
            let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).expect("member Cargo.toml");
            (package_name(&manifest), dir)
        })
        .collect()
}

fn package_name(manifest: &str) -> String {
    let mut in_package = false;
    for l in manifest.lines() {
        let l = l.trim();
        if l.starts_with('[') {
            in_package = l == "[package]";
        } else if in_package && l.starts_with("name") {
            return l.split('=').nth(1).unwrap_or("").trim().trim_matches('"').to_string();
        }
    }
    panic!("no [package] name")
}

/// The workspace crates a manifest names under [dependencies] (not dev-).
fn workspace_deps(manifest: &str) -> Vec<String> {
    let mut in_deps = false;
    let mut deps = Vec::new();
    for l in manifest.lines() {
        let l = l.trim();
        if l.starts_with('[') {
            in_deps = l == "[dependencies]";
        } else if in_deps {
            let name = l.split(['=', '.', ' ']).next().unwrap_or("");
            if name.starts_with("formation-") {
                deps.push(name.to_string());
            }
        }
    }
    deps
}

#[test]
fn every_crate_depends_only_on_lower_layers() {
    let mut wrong = Vec::new();
    let members = members();
    assert_eq!(members.len(), LAYERS.len(), "members {members:?} against the layers {LAYERS:?}");
    for (name, dir) in &members {
        let Some(rank) = LAYERS.iter().position(|l| l == name) else {
            wrong.push(format!("{name} ({}) is in no layer", dir.display()));
            continue;
        };
        let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).expect("Cargo.toml");
        for dep in workspace_deps(&manifest) {
            match LAYERS.iter().position(|l| *l == dep) {
                Some(r) if r < rank => {}
                _ => wrong.push(format!("{name} depends on {dep}, which is not below it")),
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// The libraries build without a command line: clap is the `formation`
/// crate's, and a library may offer its arguments to it only behind an
/// optional feature (formation-net's `clap`).
#[test]
fn no_library_needs_clap() {
    let mut wrong = Vec::new();
    for (name, dir) in members() {
        if name == "formation" {
            continue;
        }
        let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).expect("Cargo.toml");
        let mut in_deps = false;
        for l in manifest.lines() {
            let t = l.trim();
            if t.starts_with('[') {
                in_deps = t == "[dependencies]";
            } else if in_deps && t.starts_with("clap") && !t.contains("optional = true") {
                wrong.push(format!("{name}: {t}"));
            }
        }
    }
    assert!(wrong.is_empty(), "libraries that need clap to build:\n{}", wrong.join("\n"));
}

/// Every .rs file under `src` of a crate (binaries in src/bin excluded: each
/// is a crate root of its own with one `main`).
fn sources(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.join("src")];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() && p.file_name().is_some_and(|n| n != "bin") {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// A file's module path in its crate: src/lib.rs → [], src/a.rs → [a],
/// src/a/mod.rs → [a], src/a/b.rs → [a, b].
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).expect("under src");
    let mut parts: Vec<String> = rel.iter().map(|p| p.to_string_lossy().to_string()).collect();
    let last = parts.pop().unwrap_or_default();
    let stem = last.trim_end_matches(".rs");
    if stem != "lib" && stem != "mod" && stem != "main" {
        parts.push(stem.to_string());
    }
    parts
}

/// The code of a file without its comments, string contents and
/// `#[cfg(test)]` module.
fn code(text: &str) -> String {
    let cut = text.find("#[cfg(test)]\nmod ").map_or(text, |i| &text[..i]);
    let mut out = String::new();
    for line in cut.lines() {
        let l = line.trim_start();
        if l.starts_with("//") {
            continue;
        }
        let l = l.split(" // ").next().unwrap_or(l);
        // Drop string literals' contents (a message may read "crate::x").
        let mut in_str = false;
        for c in l.chars() {
            if c == '"' {
                in_str = !in_str;
                out.push(c);
            } else if !in_str {
                out.push(c);
            }
        }
        out.push('\n');
    }
    out
}

/// A file's code outside and inside inline `mod x { … }` blocks.
fn split_inline_modules(code: &str) -> (String, String) {
    let (mut outside, mut inside) = (String::new(), String::new());
    let mut depth = 0i64;
    let mut opened: Vec<i64> = Vec::new();
    for line in code.lines() {
        let t = line.trim_start();
        let t = t.strip_prefix("pub ").or_else(|| t.strip_prefix("pub(crate) ")).unwrap_or(t);
        if t.starts_with("mod ") && t.trim_end().ends_with('{') {
            opened.push(depth);
        }
        if opened.is_empty() {
            outside.push_str(line);
            outside.push('\n');
        } else {
            inside.push_str(line);
            inside.push('\n');
        }
        depth += line.matches('{').count() as i64 - line.matches('}').count() as i64;
        while opened.last().is_some_and(|&d| depth <= d) {
            opened.pop();
        }
    }
    (outside, inside)
}

/// The module paths a piece of code names: `crate::a::b`, `super::x`, and
/// `crate::{a, b::c}` / `super::{x, y}` groups, each as written after the prefix.
fn named_paths(code: &str, prefix: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find(prefix) {
        let before = rest[..i].chars().last();
        let nested = rest[..i].ends_with("super::");
        rest = &rest[i + prefix.len()..];
        if nested || before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        if let Some(group) = rest.strip_prefix('{') {
            let inner = group.split('}').next().unwrap_or("");
            for item in inner.split(',') {
                out.push(path_words(item.trim()));
            }
        } else {
            out.push(path_words(rest));
        }
    }
    out
}

fn path_words(s: &str) -> Vec<String> {
    let end = s.find(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':')).unwrap_or(s.len());
    s[..end].split("::").filter(|w| !w.is_empty()).map(str::to_string).collect()
}

/// The longest known module that a path starting at `base` names.
fn resolve(modules: &BTreeSet<Vec<String>>, base: &[String], words: &[String]) -> Option<Vec<String>> {
    let mut best = None;
    let mut path = base.to_vec();
    if modules.contains(&path) {
        best = Some(path.clone());
    }
    for w in words {
        path.push(w.clone());
        if modules.contains(&path) {
            best = Some(path.clone());
        } else {
            break;
        }
    }
    best
}

/// Every module's imports within its crate (edges to itself and to the
/// crate root's `mod` declarations are not imports).
fn module_graph(dir: &Path) -> BTreeMap<Vec<String>, (PathBuf, BTreeSet<Vec<String>>)> {
    let src = dir.join("src");
    let files = sources(dir);
    let modules: BTreeSet<Vec<String>> = files.iter().map(|f| module_of(&src, f)).collect();
    let mut graph = BTreeMap::new();
    for f in &files {
        let me = module_of(&src, f);
        let text = code(&std::fs::read_to_string(f).expect("source"));
        let mut to = BTreeSet::new();
        for words in named_paths(&text, "crate::") {
            if let Some(m) = resolve(&modules, &[], &words) {
                to.insert(m);
            }
        }
        // `super::` from a file module a/b.rs (or a/b/mod.rs) is module a.
        let parent: Vec<String> = me[..me.len().saturating_sub(1)].to_vec();
        // Inside an inline `mod x { … }` of this file, `super` is this file's module.
        let (file_level, inline) = split_inline_modules(&text);
        for (text, base_of_super) in [(&file_level, &parent), (&inline, &me)] {
            for words in named_paths(text, "super::") {
                let ups = words.iter().take_while(|w| *w == "super").count();
                let base = &base_of_super[..base_of_super.len().saturating_sub(ups)];
                if let Some(m) = resolve(&modules, base, &words[ups..]) {
                    to.insert(m);
                }
            }
        }
        // Plain `use x::…` of a child module declared here (`mod x;`).
        for l in text.lines() {
            let l = l.trim();
            if let Some(r) = l.strip_prefix("pub use ").or_else(|| l.strip_prefix("use ")) {
                let words = path_words(r.trim_start_matches("self::"));
                let mut child = me.clone();
                if let Some(w) = words.first() {
                    child.push(w.clone());
                    if modules.contains(&child) {
                        to.insert(child);
                    }
                }
            }
        }
        to.remove(&me);
        graph.insert(me, (f.clone(), to));
    }
    graph
}

/// A circle of the graph, as the files around it, if there is one.
fn circle(graph: &BTreeMap<Vec<String>, (PathBuf, BTreeSet<Vec<String>>)>) -> Option<Vec<PathBuf>> {
    // Depth-first search with colours: 1 on the stack, 2 done.
    fn visit(
        n: &Vec<String>,
        g: &BTreeMap<Vec<String>, (PathBuf, BTreeSet<Vec<String>>)>,
        colour: &mut BTreeMap<Vec<String>, u8>,
        stack: &mut Vec<Vec<String>>,
    ) -> Option<Vec<PathBuf>> {
        colour.insert(n.clone(), 1);
        stack.push(n.clone());
        for m in g.get(n).map(|x| &x.1).into_iter().flatten() {
            match colour.get(m).copied().unwrap_or(0) {
                1 => {
                    let from = stack.iter().position(|s| s == m).unwrap_or(0);
                    let mut files: Vec<PathBuf> = stack[from..].iter().map(|s| g[s].0.clone()).collect();
                    files.push(g[m].0.clone());
                    return Some(files);
                }
                0 => {
                    if let Some(c) = visit(m, g, colour, stack) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        stack.pop();
        colour.insert(n.clone(), 2);
        None
    }
    let mut colour = BTreeMap::new();
    for n in graph.keys() {
        if colour.get(n).copied().unwrap_or(0) == 0 {
            if let Some(c) = visit(n, graph, &mut colour, &mut Vec::new()) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn no_module_imports_one_that_imports_it() {
    let mut circles = Vec::new();
    let mut counted = 0;
    for (name, dir) in members() {
        let graph = module_graph(&dir);
        counted += graph.len();
        if let Some(files) = circle(&graph) {
            let names: Vec<String> =
                files.iter().map(|f| f.strip_prefix(root()).unwrap_or(f).display().to_string()).collect();
            circles.push(format!("{name}: {}", names.join(" -> ")));
        }
    }
    assert!(counted > 40, "read only {counted} modules: is the reader broken?");
    assert!(circles.is_empty(), "import circles:\n{}", circles.join("\n"));
}

/// The reader finds a circle where there is one (a test that cannot fail
/// would prove nothing).
#[test]
fn the_circle_reader_finds_a_planted_circle() {
    let dir = tempfile::tempdir().expect("tempdir");
    let src = dir.path().join("src");
    std::fs::create_dir_all(src.join("a")).expect("mkdir");
    std::fs::write(src.join("lib.rs"), "pub mod a;\npub mod b;\n").expect("write");
    std::fs::write(src.join("a/mod.rs"), "pub mod c;\nuse crate::b::X;\n").expect("write");
    std::fs::write(src.join("a/c.rs"), "// crate::b in a comment\nuse super::super::b;\n").expect("write");
    std::fs::write(src.join("b.rs"), "pub struct X;\nfn f() { crate::a::c::g(); }\n").expect("write");
    let graph = module_graph(dir.path());
    let c = circle(&graph).expect("a -> b -> a/c ... must be seen");
    assert!(c.len() >= 3, "{c:?}");
    // `super` inside an inline module of b is b itself, not b's parent.
    std::fs::write(src.join("b.rs"), "pub struct X;\nmod inner {\n    use super::X;\n}\n").expect("write");
    assert_eq!(circle(&module_graph(dir.path())), None, "no circle once b no longer names a");
}

/// Exit statuses are decided in one place: `formation_exit::Error::status`
/// gives the number, and only the `formation` crate turns it into the
/// process's exit code.
#[test]
fn only_the_binary_crate_knows_exit_statuses() {
    let mut wrong = Vec::new();
    for (name, dir) in members() {
        if name == "formation" {
            continue;
        }
        for f in sources(&dir) {
            let text = code(&std::fs::read_to_string(&f).expect("source"));
            for needle in ["ExitCode", "exit_code", "process::exit", "fn exit_status"] {
                if text.contains(needle) {
                    wrong.push(format!("{}: {needle}", f.display()));
                }
            }
        }
    }
    assert!(wrong.is_empty(), "below the binary crate:\n{}", wrong.join("\n"));
}

/// Every name is reached by its own crate's name: no library crate
/// re-exports another formation crate's items (`pub use formation_…`, nor
/// `pub use` of a path through one), and no module glob-merges another
/// crate's module into its own (`use formation_….::*` in a module that also
/// defines items under that name). A reader who sees `formation_net::x`
/// knows x needs the network crate.
#[test]
fn no_crate_re_exports_another_formation_crate() {
    let mut wrong = Vec::new();
    for (name, dir) in members() {
        for f in sources(&dir) {
            let text = code(&std::fs::read_to_string(&f).expect("source"));
            for (n, line) in text.lines().enumerate() {
                let l = line.trim_start();
                let reexport = l.starts_with("pub use formation_")
                    || (l.starts_with("pub use ")
                        && !l.starts_with("pub use crate::")
                        && !l.starts_with("pub use self::")
                        && !l.starts_with("pub use super::")
                        && l.contains("formation_"));
                let glob = l.starts_with("use formation_") && l.contains("::*;");
                if reexport || glob {
                    wrong.push(format!("{name}: {}:{}: {l}", f.display(), n + 1));
                }
            }
        }
    }
    assert!(wrong.is_empty(), "names reached through another crate's name:\n{}", wrong.join("\n"));
}

/// formation-report reads run folders and runs the simulator: with the
/// features it asks for (as Cargo resolves them, not as its manifest
/// reads), it builds without the network, an async runtime or a web
/// server, so that a user of the reports (or of Python) does not wait for
/// zenoh.
#[test]
fn the_report_crate_needs_no_network_and_no_runtime() {
    let out = std::process::Command::new(env!("CARGO"))
        .args(["tree", "--offline", "-p", "formation-report", "-e", "normal", "--prefix", "none", "--format", "{p}"])
        .current_dir(root())
        .output()
        .expect("cargo tree");
    assert!(out.status.success(), "cargo tree: {}", String::from_utf8_lossy(&out.stderr));
    let tree = String::from_utf8_lossy(&out.stdout);
    let names: BTreeSet<&str> = tree.lines().filter_map(|l| l.split_whitespace().next()).collect();
    assert!(
        names.contains("formation-replay") && names.contains("plotters"),
        "the tree is not the report's: {names:?}"
    );
    let banned: Vec<&&str> = ["zenoh", "tokio", "axum", "formation-net", "formation-view", "formation-launch"]
        .iter()
        .filter(|b| names.contains(**b))
        .collect();
    assert!(banned.is_empty(), "formation-report builds with {banned:?}");
}

/// formation-protocol holds the rules that tests drive on virtual time: its
/// manifest names no runtime and no network, and no source of it reads a
/// clock or sleeps (time is an argument).
#[test]
fn the_protocol_crate_has_no_runtime_no_network_and_reads_no_clock() {
    let dir = root().join("protocol");
    let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).expect("protocol/Cargo.toml");
    let deps = manifest.split("[dev-dependencies]").next().unwrap_or("");
    for banned in ["zenoh", "tokio", "axum", "futures", "async"] {
        assert!(!deps.lines().any(|l| l.trim_start().starts_with(banned)), "protocol/Cargo.toml depends on {banned}");
    }
    let mut readings = Vec::new();
    for entry in std::fs::read_dir(dir.join("src")).expect("protocol/src") {
        let path = entry.expect("entry").path();
        let text = std::fs::read_to_string(&path).expect("source");
        for (n, line) in text.lines().enumerate() {
            if ["Instant::now", "SystemTime::now", "thread::sleep", "Instant::elapsed", ".elapsed()"]
                .iter()
                .any(|c| line.contains(c))
            {
                readings.push(format!("{}:{}: {}", path.display(), n + 1, line.trim()));
            }
        }
    }
    assert!(readings.is_empty(), "the protocol reads a clock:\n{}", readings.join("\n"));
}

/// Cargo.toml builds the crates that run only inside the compiler
/// (proc-macros, their parsers, build scripts' helpers) at opt-level 0: a
/// clean test build 574 s → 434 s here (docs/performance.md). The list is
/// by name, so it must follow the dependencies: every crate it names is
/// still host-only (an optimised crate of the nodes' must not become an
/// unoptimised one), and every host-only crate is named (or its time at
/// opt-level 2 quietly comes back).
#[test]
fn the_crates_built_unoptimised_are_exactly_the_host_only_ones() {
    let names = |edges: &str| -> BTreeSet<String> {
        let out = std::process::Command::new(env!("CARGO"))
            .args(["tree", "--offline", "--workspace", "-e", edges, "--prefix", "none", "--format", "{p}"])
            .current_dir(root())
            .output()
            .expect("cargo tree");
        assert!(out.status.success(), "cargo tree -e {edges}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter_map(|l| l.split_whitespace().next())
            .map(String::from)
            .collect()
    };
    let (all, target) = (names("all"), names("normal,dev,no-proc-macro"));
    let host_only: BTreeSet<String> = all.difference(&target).cloned().collect();
    let text = std::fs::read_to_string(root().join("Cargo.toml")).expect("Cargo.toml");
    let listed: BTreeSet<String> =
        text.lines().filter_map(|l| l.strip_suffix(" = { opt-level = 0 }")).map(|n| n.trim().to_string()).collect();
    assert!(
        listed.len() > 40,
        "Cargo.toml lists only {} crates at opt-level 0: the list's form changed?",
        listed.len()
    );
    let not_host: Vec<&String> = listed.difference(&host_only).collect();
    assert!(not_host.is_empty(), "Cargo.toml builds {not_host:?} at opt-level 0, but a node links them (cargo tree)");
    let unlisted: Vec<&String> = host_only.difference(&listed).collect();
    assert!(
        unlisted.is_empty(),
        "{unlisted:?} run only inside the compiler: add them to Cargo.toml's [profile.dev.package] at opt-level 0"
    );
    // The crates linked but cold (Cargo.toml says why): each still linked.
    let cold: BTreeSet<String> = text
        .lines()
        .filter_map(|l| l.strip_suffix(" = { opt-level = 0 } # cold"))
        .map(|n| n.trim().to_string())
        .collect();
    assert!(cold.len() >= 5, "Cargo.toml lists only {} cold crates: the list's form changed?", cold.len());
    let gone: Vec<&String> = cold.difference(&target).collect();
    assert!(gone.is_empty(), "Cargo.toml builds {gone:?} unoptimised as linked but cold, but no node links them");
}

/// Every member's library sources with their code (comments, strings and
/// the test module removed), except those of `skip`.
fn member_code(skip: &[&str]) -> Vec<(PathBuf, String)> {
    let mut out = Vec::new();
    for (_, dir) in members() {
        for f in sources(&dir) {
            let rel = f.strip_prefix(root()).unwrap_or(&f).to_path_buf();
            if skip.iter().any(|s| rel == Path::new(s)) {
                continue;
            }
            out.push((rel, code(&std::fs::read_to_string(&f).expect("source"))));
        }
    }
    out
}

/// One shutdown: no source but `exit/src/shutdown.rs` installs a signal
/// handler (tokio's signal streams, `sigaction`, `libc::signal`, a crate
/// for it). A node, a launch, a lab and the simulator all stop on the
/// shutdown that module gives them.
#[test]
fn only_the_shutdown_module_installs_a_signal_handler() {
    let mut wrong = Vec::new();
    for (f, text) in member_code(&["exit/src/shutdown.rs"]) {
        for needle in ["tokio::signal", "sigaction", "libc::signal(", "signal_hook", "ctrlc::"] {
            if text.contains(needle) {
                wrong.push(format!("{}: {needle}", f.display()));
            }
        }
    }
    assert!(wrong.is_empty(), "a second shutdown handler:\n{}", wrong.join("\n"));
}

/// The enums of `code` (name, body) whose variants include every one of `kinds`.
fn enums_with(code: &str, kinds: &[&str]) -> Vec<String> {
    let mut found = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find("enum ") {
        let after = &rest[i + 5..];
        let name: String = after.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
        let Some(open) = after.find('{') else { break };
        let mut depth = 0;
        let mut end = after.len();
        for (j, c) in after[open..].char_indices() {
            depth += (c == '{') as i32 - (c == '}') as i32;
            if depth == 0 {
                end = open + j;
                break;
            }
        }
        let body: String = after[open..end].split_whitespace().collect();
        if kinds.iter().all(|k| body.contains(k)) {
            found.push(name);
        }
        rest = &after[open..];
    }
    found
}

/// One error kind: no enum but `formation_exit::Error` has both a bad-input
/// and a failed-run variant (`Input(String)`, `Run(String)`); the
/// libraries' own errors say what went wrong in their words and convert
/// into it.
#[test]
fn only_one_error_enum_has_the_kinds_every_command_reports() {
    let kinds = ["Input(String)", "Run(String)"];
    assert_eq!(
        enums_with("pub enum E { Input(String), Run(String), Other }", &kinds),
        ["E"],
        "the reader finds a planted enum"
    );
    let mut wrong = Vec::new();
    for (f, text) in member_code(&["exit/src/error.rs"]) {
        for name in enums_with(&text, &kinds) {
            wrong.push(format!("{}: enum {name}", f.display()));
        }
        // Nor its helpers, written again beside another crate's errors.
        if text.contains("fn at_least_one(") {
            wrong.push(format!("{}: fn at_least_one", f.display()));
        }
    }
    assert!(wrong.is_empty(), "a second error enum with the kinds of formation_exit::Error:\n{}", wrong.join("\n"));
}

/// One clock: a node's code reads the time only through `Clock`
/// (net/src/clock.rs) or its precise sleep (net/src/timer.rs), so that
/// every deadline in it (a time-out, a listening window) runs on
/// `Clock::mock` in a test.
#[test]
fn the_network_crate_reads_time_only_through_its_clock() {
    let mut wrong = Vec::new();
    for (f, text) in member_code(&["net/src/clock.rs", "net/src/timer.rs"]) {
        if !f.starts_with("net") {
            continue;
        }
        for needle in ["Instant::now", "SystemTime::now", ".elapsed()"] {
            if text.contains(needle) {
                wrong.push(format!("{}: {needle}", f.display()));
            }
        }
    }
    assert!(wrong.is_empty(), "a clock read outside Clock:\n{}", wrong.join("\n"));
}
