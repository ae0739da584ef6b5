//! The house has one direction: no module of `src/` names (`crate::...`) a module above it in
//! the layering of docs/design.md §7, and modules on one level do not name each other, so there
//! is no import cycle between modules. Scans the source text, so a new upward import fails here.

use std::path::Path;

/// The levels, from the leaves up (see docs/design.md §7 and CONTRIBUTING.md, "Layout").
const LEVELS: &[&[&str]] = &[
    &["buf", "failure", "geometry", "hash", "rng"],
    &["io"],
    &["raster"],
    &["mpi"],
    &["render"],
    &["source"],
    &["scene"],
    &["sample"],
    &["export", "service"],
    &["bench"],
];

fn level(module: &str) -> Option<usize> {
    LEVELS.iter().position(|l| l.contains(&module))
}

fn rust_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// Every `crate::NAME` in `text` (comments included: a doc link upward is a reader's arrow too).
fn crate_refs(text: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("crate::") {
        let tail = &rest[i + 7..];
        let end = tail.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(tail.len());
        out.push(&tail[..end]);
        rest = &tail[end..];
    }
    out
}

#[test]
fn no_module_names_a_module_above_it_or_beside_it() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut bad = Vec::new();
    let mut checked = 0;
    for f in &files {
        let rel = f.strip_prefix(&src).unwrap();
        let top = rel.components().next().unwrap().as_os_str().to_string_lossy().trim_end_matches(".rs").to_string();
        // the crate root and the binary (`main.rs`, `cli/`) sit above everything
        if top == "lib" || top == "main" || top == "cli" {
            continue;
        }
        let own = level(&top).unwrap_or_else(|| panic!("{}: module `{top}` is not in LEVELS", rel.display()));
        let text = std::fs::read_to_string(f).unwrap();
        for name in crate_refs(&text) {
            if name == top {
                continue;
            }
            let Some(other) = level(name) else { continue };
            checked += 1;
            if other >= own {
                bad.push(format!("{}: `{top}` (level {own}) names `crate::{name}` (level {other})", rel.display()));
            }
        }
    }
    assert!(checked > 50, "the scan found only {checked} cross-module references");
    assert!(bad.is_empty(), "imports against the layering:\n{}", bad.join("\n"));
}

#[test]
fn the_scanner_sees_references() {
    assert_eq!(crate_refs("use crate::mpi::Mpi; // see crate::render"), ["mpi", "render"]);
    assert_eq!(level("render"), Some(4));
    assert!(level("render") > level("mpi"));
}
