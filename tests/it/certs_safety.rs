//! `formation certs` changes nothing before it has checked everything: a
//! symbolic link, a file where a folder goes or a folder inside a node's
//! folder is refused in one line, exit 2, with every file of the old folder
//! (the authority's key first) and the link's target byte for byte as they
//! were. A run that passes the checks writes the new folders beside the old
//! ones and swaps them in: nothing half-written, nothing left behind.

use crate::common;

use std::collections::BTreeMap;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};

const NODES: [&str; 7] = ["router", "leader", "monitor", "agent-1", "agent-2", "agent-3", "agent-4"];

/// What a path under `root` is, never following a link: a file's bytes and
/// permissions, a link's target, a folder's permissions.
#[derive(Debug, PartialEq, Eq)]
enum Entry {
    File(Vec<u8>, u32),
    Link(PathBuf),
    Folder(u32),
}

/// Every path under `root` (hidden ones too) and what it is.
fn snapshot(root: &Path) -> BTreeMap<PathBuf, Entry> {
    fn walk(root: &Path, at: &Path, out: &mut BTreeMap<PathBuf, Entry>) {
        let m = std::fs::symlink_metadata(at).unwrap_or_else(|e| panic!("{}: {e}", at.display()));
        let rel = at.strip_prefix(root).expect("under root").to_path_buf();
        let mode = m.permissions().mode() & 0o7777;
        if m.file_type().is_symlink() {
            out.insert(rel, Entry::Link(std::fs::read_link(at).expect("read_link")));
        } else if m.is_dir() {
            out.insert(rel, Entry::Folder(mode));
            for e in std::fs::read_dir(at).expect("read_dir") {
                walk(root, &e.expect("entry").path(), out);
            }
        } else {
            out.insert(rel, Entry::File(std::fs::read(at).expect("read"), mode));
        }
    }
    let mut out = BTreeMap::new();
    walk(root, root, &mut out);
    out
}

/// Asserts that `certs EXTRA…` on `dir` is refused with one line, exit 2,
/// that the line says `says` and names `names`, and that neither `dir` nor
/// `outside` (a link's target) changed in any byte.
fn refused_and_unchanged(dir: &Path, outside: &Path, extra: &[&str], says: &str, names: &str) {
    let (before, outside_before) = (snapshot(dir), snapshot(outside));
    assert!(before.contains_key(Path::new("ca/ca.key")), "the test folder has no authority key to lose");
    let o = common::certs_with(dir, extra);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "certs {extra:?}: status {:?}, said: {err}", o.status.code());
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "certs {extra:?} said more than one line: {err}");
    assert!(lines[0].contains(says) && lines[0].contains(names), "certs {extra:?} said: {err}");
    assert!(o.stdout.is_empty(), "certs {extra:?} printed: {}", String::from_utf8_lossy(&o.stdout));
    let after = snapshot(dir);
    for (path, was) in &before {
        assert_eq!(after.get(path), Some(was), "certs {extra:?}: {} changed", path.display());
    }
    let new: Vec<_> = after.keys().filter(|p| !before.contains_key(*p)).collect();
    assert!(new.is_empty(), "certs {extra:?} left {new:?} behind");
    assert!(snapshot(outside) == outside_before, "certs {extra:?} changed the link's target {}", outside.display());
}

/// A link's target: a folder with a file of its own, and a copy of
/// `like`'s files (so it looks like a node's folder).
fn target(tmp: &Path, like: &Path) -> PathBuf {
    let elsewhere = tmp.join("elsewhere");
    std::fs::create_dir_all(&elsewhere).expect("mkdir");
    std::fs::write(elsewhere.join("unrelated.txt"), "not certs' to touch").expect("write");
    for e in std::fs::read_dir(like).expect("read_dir").flatten() {
        std::fs::copy(e.path(), elsewhere.join(e.file_name())).expect("copy");
    }
    elsewhere
}

#[test]
fn certs_with_a_linked_node_folder_changes_nothing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let elsewhere = target(tmp.path(), &dir.join("agent-3"));
    std::fs::remove_dir_all(dir.join("agent-3")).expect("rm agent-3");
    std::os::unix::fs::symlink(&elsewhere, dir.join("agent-3")).expect("symlink");
    let link = dir.join("agent-3").display().to_string();
    // --force (the issue: it removed ca/ and four node folders first), and
    // every other way of changing the folder.
    for extra in [
        &["--force"][..],
        &["--node", "agent-1"],
        &["--node", "agent-3"],
        &["--revoke", "agent-2"],
        &["--force", "--san", "10.0.0.9"],
    ] {
        refused_and_unchanged(&dir, &elsewhere, extra, "is a symbolic link", &link);
    }
    // The authority's folder as a link, too.
    let ca_elsewhere = tmp.path().join("ca-elsewhere");
    std::fs::rename(dir.join("ca"), &ca_elsewhere).expect("move ca");
    std::os::unix::fs::symlink(&ca_elsewhere, dir.join("ca")).expect("symlink ca");
    std::fs::remove_file(dir.join("agent-3")).expect("rm link");
    std::fs::rename(&elsewhere, dir.join("agent-3")).expect("agent-3 back");
    let before = snapshot(&ca_elsewhere);
    let o = common::certs_with(&dir, &["--force"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "--force with ca/ a link: {err}");
    let ca = dir.join("ca").display().to_string();
    assert!(err.trim().lines().count() == 1 && err.contains("symbolic link") && err.contains(&ca), "{err}");
    assert!(snapshot(&ca_elsewhere) == before, "--force changed the linked authority");
}

#[test]
fn certs_with_a_linked_file_in_a_node_folder_changes_nothing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let outside = tmp.path().join("outside");
    std::fs::create_dir(&outside).expect("mkdir");
    std::fs::write(outside.join("victim.txt"), "unrelated").expect("victim");
    let planted = dir.join("agent-2/policy.json5");
    std::fs::remove_file(&planted).expect("rm");
    std::os::unix::fs::symlink(outside.join("victim.txt"), &planted).expect("symlink");
    let link = planted.display().to_string();
    for extra in [&["--force"][..], &["--node", "agent-2"], &["--node", "agent-4"], &["--revoke", "agent-1"]] {
        refused_and_unchanged(&dir, &outside, extra, "is a symbolic link", &link);
    }
    // A link to a folder, with another name, in the authority's folder.
    std::fs::remove_file(&planted).expect("rm link");
    std::fs::copy(dir.join("agent-1/policy.json5"), &planted).expect("policy back");
    let planted = dir.join("ca/backup");
    std::os::unix::fs::symlink(&outside, &planted).expect("symlink");
    refused_and_unchanged(&dir, &outside, &["--force"], "is a symbolic link", &planted.display().to_string());
}

#[test]
fn certs_with_a_file_where_a_folder_goes_or_a_folder_in_a_node_folder_changes_nothing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    let outside = tmp.path().join("outside");
    std::fs::create_dir(&outside).expect("mkdir");
    std::fs::remove_dir_all(dir.join("agent-4")).expect("rm agent-4");
    std::fs::write(dir.join("agent-4"), "a file").expect("file");
    let file = dir.join("agent-4").display().to_string();
    refused_and_unchanged(&dir, &outside, &["--force"], "is a file, not a folder", &file);
    refused_and_unchanged(&dir, &outside, &["--revoke", "agent-1"], "is a file, not a folder", &file);
    std::fs::remove_file(dir.join("agent-4")).expect("rm");
    std::fs::create_dir(dir.join("agent-4")).expect("mkdir");
    let inner = dir.join("monitor/old");
    std::fs::create_dir(&inner).expect("mkdir");
    std::fs::write(inner.join("monitor.key"), "an old key").expect("write");
    refused_and_unchanged(&dir, &outside, &["--force"], "is a folder inside monitor/", &inner.display().to_string());
}

/// The identity of every node checks out against the folder's authority.
fn every_identity_checks(dir: &Path) {
    for n in NODES {
        formation_certs::identity(dir, n).unwrap_or_else(|e| panic!("{n}: {e}"));
        let key = dir.join(n).join(format!("{n}.key"));
        let mode = std::fs::metadata(&key).expect("key").permissions().mode() & 0o777;
        assert_eq!(mode, 0o600, "{}: {mode:o}", key.display());
    }
}

/// Nothing of the staging: no `.certs-new-…` or `.certs-old-…` in DIR.
fn no_leftovers(dir: &Path) {
    let left: Vec<_> = std::fs::read_dir(dir)
        .expect("read_dir")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".certs-"))
        .collect();
    assert!(left.is_empty(), "left in {}: {left:?}", dir.display());
}

#[test]
fn certs_force_node_and_revoke_replace_whole_folders_and_keep_what_they_do_not_write() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("certs");
    common::certs(&dir);
    no_leftovers(&dir);
    every_identity_checks(&dir);
    // Files certs does not write: one in DIR, one in a node's folder.
    std::fs::write(dir.join("README.txt"), "which robot is which").expect("write");
    std::fs::write(dir.join("agent-2/notes.txt"), "robot 2 is the red one").expect("write");
    std::fs::set_permissions(dir.join("agent-2"), std::fs::Permissions::from_mode(0o750)).expect("chmod");

    // --force after a refused --force: a new authority, every node's folder
    // valid under it, and the files certs does not write still there.
    let elsewhere = target(tmp.path(), &dir.join("agent-3"));
    std::fs::rename(dir.join("agent-3"), tmp.path().join("agent-3-aside")).expect("move");
    std::os::unix::fs::symlink(&elsewhere, dir.join("agent-3")).expect("symlink");
    let o = common::certs_with(&dir, &["--force"]);
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::remove_file(dir.join("agent-3")).expect("rm link");
    std::fs::rename(tmp.path().join("agent-3-aside"), dir.join("agent-3")).expect("back");
    let old = snapshot(&dir);
    let o = common::certs_with(&dir, &["--force"]);
    assert!(o.status.success(), "--force: {}", String::from_utf8_lossy(&o.stderr));
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(
        said.contains("made the authority") && said.contains(&dir.join("ca/ca.pem").display().to_string()),
        "{said}"
    );
    assert!(!said.contains(".certs-"), "--force named its staging folder: {said}");
    no_leftovers(&dir);
    every_identity_checks(&dir);
    let new = snapshot(&dir);
    for f in ["ca/ca.key", "ca/ca.pem", "agent-3/agent-3.key", "agent-3/agent-3.pem"] {
        assert_ne!(new.get(Path::new(f)), old.get(Path::new(f)), "--force kept {f}");
    }
    for f in ["README.txt", "agent-2/notes.txt", "agent-2"] {
        assert_eq!(new.get(Path::new(f)), old.get(Path::new(f)), "--force changed {f}");
    }

    // --node agent-3: its key and certificate new; the authority's key and
    // every other node's key and certificate byte for byte as they were.
    let old = new;
    let o = common::certs_with(&dir, &["--node", "agent-3"]);
    assert!(o.status.success(), "--node: {}", String::from_utf8_lossy(&o.stderr));
    no_leftovers(&dir);
    every_identity_checks(&dir);
    let new = snapshot(&dir);
    for n in NODES {
        for f in [format!("{n}/{n}.key"), format!("{n}/{n}.pem")] {
            let (a, b) = (old.get(Path::new(&f)), new.get(Path::new(&f)));
            assert!(a.is_some() && (a == b) == (n != "agent-3"), "--node agent-3: {f}");
        }
    }
    for f in ["ca/ca.key", "ca/ca.pem", "README.txt", "agent-2/notes.txt", "agent-2"] {
        assert_eq!(new.get(Path::new(f)), old.get(Path::new(f)), "--node agent-3 changed {f}");
    }

    // --revoke agent-1: no key or certificate changes; its certificate is refused.
    let old = new;
    let o = common::certs_with(&dir, &["--revoke", "agent-1"]);
    assert!(o.status.success(), "--revoke: {}", String::from_utf8_lossy(&o.stderr));
    no_leftovers(&dir);
    let new = snapshot(&dir);
    for (path, was) in &old {
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.ends_with(".key") || (name.ends_with(".pem") && name != "policy.pem") || name.ends_with(".txt") {
            if name != "revoked.txt" {
                assert_eq!(new.get(path), Some(was), "--revoke changed {}", path.display());
            }
        }
    }
    let e = formation_certs::identity(&dir, "agent-1").expect_err("a revoked certificate");
    assert!(e.0.contains("revoked"), "{e}");
}
