//! The documentation stands on its own: README.md is short, every page
//! under docs/ is reachable from it by links, every relative link points to
//! a file that exists, and nothing cites material outside the project.

use std::collections::{BTreeSet, VecDeque};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The relative link targets of a Markdown file (`](target)`), without
/// anchors; web links and pure anchors left out.
fn links(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("](") {
        rest = &rest[i + 2..];
        let Some(end) = rest.find(')') else { break };
        let target = rest[..end].split_whitespace().next().unwrap_or("");
        let target = target.split('#').next().unwrap_or("");
        if !target.is_empty() && !target.contains("://") && !target.starts_with("mailto:") {
            out.push(target.to_string());
        }
    }
    out
}

fn docs_pages() -> Vec<PathBuf> {
    let mut pages: Vec<PathBuf> = std::fs::read_dir(root().join("docs"))
        .expect("docs/")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    pages.sort();
    pages
}

#[test]
fn the_readme_is_at_most_200_lines() {
    let text = std::fs::read_to_string(root().join("README.md")).expect("README.md");
    let n = text.lines().count();
    assert!(n <= 200, "README.md has {n} lines (at most 200: the rest belongs in docs/)");
}

#[test]
fn every_relative_link_points_to_a_file() {
    let mut broken = Vec::new();
    let mut files = vec![root().join("README.md")];
    files.extend(docs_pages());
    for f in &files {
        let text = std::fs::read_to_string(f).expect("markdown");
        let dir = f.parent().unwrap_or(Path::new("."));
        for l in links(&text) {
            if !dir.join(&l).exists() {
                broken.push(format!("{}: {l}", f.strip_prefix(root()).unwrap_or(f).display()));
            }
        }
    }
    assert!(broken.is_empty(), "links to nothing:\n{}", broken.join("\n"));
}

#[test]
fn every_docs_page_is_reachable_from_the_readme() {
    let readme = root().join("README.md");
    let mut seen: BTreeSet<PathBuf> = BTreeSet::new();
    let mut queue = VecDeque::from([readme]);
    while let Some(f) = queue.pop_front() {
        let Ok(f) = f.canonicalize() else { continue };
        if !seen.insert(f.clone()) || f.extension().is_none_or(|x| x != "md") {
            continue;
        }
        let text = std::fs::read_to_string(&f).unwrap_or_default();
        let dir = f.parent().unwrap_or(Path::new(".")).to_path_buf();
        queue.extend(links(&text).into_iter().map(|l| dir.join(l)));
    }
    let unreached: Vec<String> = docs_pages()
        .into_iter()
        .filter(|p| !p.canonicalize().is_ok_and(|c| seen.contains(&c)))
        .map(|p| p.display().to_string())
        .collect();
    assert!(unreached.is_empty(), "pages no link from README.md leads to:\n{}", unreached.join("\n"));
    for must in ["model.md", "architecture.md"] {
        let p = root().join("docs").join(must).canonicalize().expect(must);
        assert!(seen.contains(&p), "docs/{must} is not reachable from README.md");
    }
}

/// Every image under docs/ is shown on some page.
#[test]
fn every_image_is_used() {
    let mut text = std::fs::read_to_string(root().join("README.md")).expect("README.md");
    for p in docs_pages() {
        text += &std::fs::read_to_string(p).expect("page");
    }
    let unused: Vec<String> = std::fs::read_dir(root().join("docs"))
        .expect("docs/")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.ends_with(".png") && !text.contains(n.as_str()))
        .collect();
    assert!(unused.is_empty(), "images no page shows: {unused:?}");
}

/// The project's documents and code cite its own model (docs/model.md),
/// never a file outside the repository.
#[test]
fn nothing_cites_material_outside_the_project() {
    let needles = [concat!("../", "shared"), concat!("SPEC", ".md"), concat!("SPEC", " §")];
    let mut hits = Vec::new();
    let mut stack = vec![root()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            let name = e.file_name().to_string_lossy().to_string();
            if p.is_dir() {
                if !matches!(name.as_str(), "target" | "vendor" | ".git") {
                    stack.push(p);
                }
                continue;
            }
            if !matches!(p.extension().and_then(|x| x.to_str()), Some("rs" | "md" | "toml" | "html")) {
                continue;
            }
            let text = std::fs::read_to_string(&p).unwrap_or_default();
            for (i, line) in text.lines().enumerate() {
                if needles.iter().any(|n| line.contains(n)) {
                    hits.push(format!("{}:{}: {}", p.strip_prefix(root()).unwrap_or(&p).display(), i + 1, line.trim()));
                }
            }
        }
    }
    assert!(hits.is_empty(), "cites material outside the project:\n{}", hits.join("\n"));
}

/// docs/architecture.md's "The life of an estimate" names real code: every
/// `file:item` there is a file that defines the item (a function, a type,
/// or `Type::method`: the type and the method both in the file). A rename
/// that leaves the page behind fails here, naming what is gone.
#[test]
fn the_life_of_an_estimate_names_code_that_exists() {
    let page = std::fs::read_to_string(root().join("docs/architecture.md")).expect("architecture.md");
    let section = page.split("## The life of an estimate").nth(1).expect("the section").split("\n## ").next().unwrap();
    let defines = |text: &str, name: &str| {
        ["fn ", "struct ", "enum ", "trait ", "type "].iter().any(|kw| {
            text.match_indices(&format!("{kw}{name}")).any(|(i, m)| {
                let next = text[i + m.len()..].chars().next().unwrap_or(' ');
                !(next.is_alphanumeric() || next == '_')
            })
        })
    };
    let mut named = 0;
    let mut gone = Vec::new();
    for chunk in section.split('`').skip(1).step_by(2) {
        let Some((file, item)) = chunk.split_once(".rs:") else { continue };
        let path = root().join(format!("{file}.rs"));
        named += 1;
        let Ok(text) = std::fs::read_to_string(&path) else {
            gone.push(format!("{chunk}: no file {}", path.display()));
            continue;
        };
        let found = match item.split("::").collect::<Vec<_>>().as_slice() {
            [name] => defines(&text, name),
            // The method in the file, and the type's impl there.
            [ty, method] => {
                defines(&text, method)
                    && [format!("impl {ty} "), format!("impl {ty}<"), format!("> {ty}<"), format!("> {ty} ")]
                        .iter()
                        .any(|i| text.contains(i.as_str()) && text.contains("impl"))
            }
            _ => false,
        };
        if !found {
            gone.push(chunk.to_string());
        }
    }
    assert!(named >= 30, "only {named} names in the section: is it still there?");
    assert!(gone.is_empty(), "docs/architecture.md names code that is not there: {gone:?}");
}
