//! The house has one direction: no module of `src/` names (`crate::...`) a module above it in
//! the layering of docs/design.md §7, and modules on one level do not name each other, so there
//! is no import cycle between modules. The rooms inside `render/`, `render/exact/` and `sample/`
//! keep the same rule among themselves ([`ROOMS`]), and their front doors (`mod.rs`) are above
//! every room: a room names its siblings, never an item of the front door (a name the front door
//! re-exports counts as the sibling that defines it). Over the whole tree, no two files (front doors aside)
//! name each other. Scans the source text, so a new upward import fails here.

use std::path::Path;

/// The levels, from the leaves up (see docs/design.md §7 and CONTRIBUTING.md, "Layout").
const LEVELS: &[&[&str]] = &[
    &["buf", "failure", "geometry", "hash", "isa", "rng"],
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

/// The rooms of the modules with a front door, from the leaves up (see docs/design.md §7).
const ROOMS: &[(&str, &[&[&str]])] = &[
    (
        "render",
        &[
            &["types", "simd"],
            &["real", "window"],
            &["tap"],
            &["band", "guard", "store"],
            &["mip", "occupancy", "resample"],
            &["exact", "reference"],
            &["cut"],
        ],
    ),
    (
        "render/exact",
        &[
            &["plane"],
            &["row16", "source_lanes"],
            &["activity", "geometry", "sampler", "source"],
            &["kernel", "lanes"],
            &["target_band"],
            &["target"],
        ],
    ),
    (
        "sample",
        &[
            &["inpaint", "motion", "object", "preblend"],
            &["error", "reveal", "types"],
            &["merge", "noise"],
            &["background"],
            &["config"],
            &["augment", "holes"],
            &["crop"],
            &["recipe"],
            &["pipeline"],
        ],
    ),
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

/// The first identifier of every path that follows `prefix` in `text`; a group
/// (`prefix{a, b::c}`) gives the first identifier of each of its items. `prefix` must not be
/// preceded by `::` or an identifier character (so `super::` does not match in `super::super::`).
fn names_after<'a>(text: &'a str, prefix: &str) -> Vec<&'a str> {
    let ident = |t: &'a str| &t[..t.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(t.len())];
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(i) = text[from..].find(prefix) {
        let at = from + i;
        from = at + prefix.len();
        let before = text[..at].chars().next_back();
        if before.is_some_and(|c| c == ':' || c.is_ascii_alphanumeric() || c == '_') {
            continue;
        }
        let tail = &text[from..];
        if let Some(group) = tail.strip_prefix('{') {
            let (mut depth, mut item_start) = (0, true);
            for (k, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => item_start = true,
                    c if item_start && (c.is_ascii_alphanumeric() || c == '_') => {
                        out.push(ident(&group[k..]));
                        item_start = false;
                    }
                    _ => {}
                }
            }
        } else {
            out.push(ident(tail));
        }
    }
    out
}

/// The names a room of `dir` gives to its siblings or its front door: `crate::DIR::NAME` and
/// `super::NAME` (`super::super::NAME` in its inline test module, where `super::` is the room).
fn room_refs<'a>(text: &'a str, dir: &str) -> Vec<&'a str> {
    let (main, tests) = text.split_at(text.find("mod tests {").unwrap_or(text.len()));
    let mut out = names_after(text, &format!("crate::{dir}::"));
    out.extend(names_after(main, "super::"));
    out.extend(names_after(tests, "super::super::"));
    out.retain(|n| !n.is_empty() && *n != "self" && *n != "super");
    out
}

/// The names the front door `mod.rs` re-exports (`pub use ROOM::...`), with their room.
fn front_door_exports(text: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    for stmt in text.split(';') {
        let Some(rest) = stmt.trim().strip_prefix("pub use ") else { continue };
        let Some((room, items)) = rest.split_once("::") else { continue };
        for name in items.trim_matches(|c: char| c == '{' || c == '}' || c.is_whitespace()).split(',') {
            let name = name.trim();
            if !name.is_empty() {
                out.push((name.to_string(), room.to_string()));
            }
        }
    }
    out
}

#[test]
fn rooms_name_only_the_rooms_below_them() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut bad = Vec::new();
    let mut checked = 0;
    for (dir, levels) in ROOMS {
        let level = |room: &str| levels.iter().position(|l| l.contains(&room));
        let front = std::fs::read_to_string(src.join(dir).join("mod.rs")).unwrap();
        let exports = front_door_exports(&front);
        let mut rooms = Vec::new();
        for e in std::fs::read_dir(src.join(dir)).unwrap() {
            let p = e.unwrap().path();
            let stem = p.file_stem().unwrap().to_string_lossy().to_string();
            if stem != "mod" {
                rooms.push((stem, p));
            }
        }
        for (room, path) in &rooms {
            let own = level(room).unwrap_or_else(|| panic!("src/{dir}/{room}: not in ROOMS"));
            if path.is_dir() {
                continue;
            }
            let text = std::fs::read_to_string(path).unwrap();
            for name in room_refs(&text, dir) {
                let target = if rooms.iter().any(|(r, _)| r == name) {
                    name.to_string()
                } else if let Some((_, r)) = exports.iter().find(|(n, _)| n == name) {
                    r.clone()
                } else {
                    bad.push(format!("src/{dir}/{room}.rs names `{name}` of the front door (src/{dir}/mod.rs)"));
                    continue;
                };
                if target == *room {
                    continue;
                }
                checked += 1;
                let other = level(&target).unwrap_or_else(|| panic!("src/{dir}/{target}: not in ROOMS"));
                if other >= own {
                    bad.push(format!("src/{dir}/{room}.rs (level {own}) names `{name}` of `{target}` (level {other})"));
                }
            }
        }
    }
    assert!(checked > 50, "the scan found only {checked} references between rooms");
    assert!(bad.is_empty(), "imports against the rooms' order:\n{}", bad.join("\n"));
}

#[test]
fn the_room_scanner_sees_references() {
    let text = "use super::{exact, mip::{a, b}, Tap};\nuse super::super::x;\n/// [`crate::render::cut`]\n\
                mod tests {\n    use super::*;\n    use super::super::simd::f;\n}";
    assert_eq!(room_refs(text, "render"), ["cut", "exact", "mip", "Tap", "simd"]);
    assert_eq!(
        front_door_exports("pub use real::Real;\npub use types::{\n    Mode, View,\n};\nmod x;"),
        [("Real".into(), "real".into()), ("Mode".into(), "types".into()), ("View".into(), "types".into())]
    );
}

/// The module path of a file of `src/`: `scene/hub.rs` is `scene::hub`, `bench/accuracy/mod.rs`
/// is `bench::accuracy`, the crate roots (`lib.rs`, `main.rs`) are the empty path.
fn module_path(rel: &Path) -> Vec<String> {
    let mut out: Vec<String> = rel.iter().map(|c| c.to_string_lossy().to_string()).collect();
    let last = out.pop().unwrap_or_default();
    let stem = last.trim_end_matches(".rs");
    if !matches!(stem, "mod" | "lib" | "main") {
        out.push(stem.to_string());
    }
    out
}

/// Every path that starts with `crate::`, `self::` or `super::` in `text` (comments included, as
/// above), resolved against `module` (the path of the file's module; `in_tests`: the text is the
/// file's inline test module, one level down) into a path from the crate root. A group
/// (`super::{a::B, c}`) gives one path per item, nested groups included.
fn absolute_paths(text: &str, module: &[String], in_tests: bool) -> Vec<Vec<String>> {
    let ident_len = |t: &str| t.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(t.len());
    // the paths of a use-tree at the start of `t` (after a `::`), each a list of segments
    fn tree(t: &str, ident_len: &dyn Fn(&str) -> usize) -> Vec<Vec<String>> {
        let t = t.trim_start();
        if let Some(group) = t.strip_prefix('{') {
            let mut out = Vec::new();
            let (mut depth, mut start) = (0, 0);
            for (k, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => {
                        out.extend(tree(&group[start..k], ident_len));
                        break;
                    }
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        out.extend(tree(&group[start..k], ident_len));
                        start = k + 1;
                    }
                    _ => {}
                }
            }
            return out;
        }
        let n = ident_len(t);
        if n == 0 {
            return Vec::new();
        }
        let head = t[..n].to_string();
        match t[n..].strip_prefix("::") {
            Some(rest) => {
                let subs = tree(rest, ident_len);
                if subs.is_empty() {
                    vec![vec![head]]
                } else {
                    subs.into_iter().map(|s| std::iter::once(head.clone()).chain(s).collect()).collect()
                }
            }
            None => vec![vec![head]],
        }
    }
    let mut own: Vec<String> = module.to_vec();
    if in_tests {
        own.push("tests".into());
    }
    let mut out = Vec::new();
    let bytes = text.as_bytes();
    let mut i = 0;
    while i < text.len() {
        let at_start =
            i == 0 || !(bytes[i - 1].is_ascii_alphanumeric() || bytes[i - 1] == b'_' || bytes[i - 1] == b':');
        let rest = &text[i..];
        let (base, mut tail): (Vec<String>, &str) = if at_start && rest.starts_with("crate::") {
            (Vec::new(), &rest[7..])
        } else if at_start && rest.starts_with("self::") {
            (own.clone(), &rest[6..])
        } else if at_start && rest.starts_with("super::") {
            let mut base = own.clone();
            let mut t = rest;
            while let Some(r) = t.strip_prefix("super::") {
                base.pop();
                t = r;
            }
            (base, t)
        } else {
            i += rest.chars().next().map_or(1, char::len_utf8);
            continue;
        };
        for p in tree(tail, &ident_len) {
            out.push(base.iter().cloned().chain(p).collect());
        }
        tail = &tail[ident_len(tail).max(1).min(tail.len())..];
        i = text.len() - tail.len();
    }
    out
}

/// Two files that name each other are one room split in two, or two rooms with an arrow each way:
/// either way a reader cannot take one without the other. No two files of `src/` (front doors
/// aside: `mod.rs` and the crate roots, which name their rooms by definition) name each other.
/// A name reaches a file when its path, resolved from the crate root, runs through that file's
/// module (`super::hub::Hub` from `scene/registry.rs` reaches `scene/hub.rs`).
#[test]
fn no_two_files_name_each_other() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let rooms: Vec<(Vec<String>, String)> = files
        .iter()
        .map(|f| f.strip_prefix(&src).unwrap())
        .filter(|rel| !matches!(rel.file_name().and_then(|n| n.to_str()), Some("mod.rs" | "lib.rs" | "main.rs")))
        .map(|rel| (module_path(rel), rel.to_string_lossy().replace('\\', "/")))
        .collect();
    let mut edges = std::collections::BTreeSet::new();
    for f in &files {
        let rel = f.strip_prefix(&src).unwrap();
        let name = rel.to_string_lossy().replace('\\', "/");
        if !rooms.iter().any(|(_, n)| *n == name) {
            continue;
        }
        let module = module_path(rel);
        let text = std::fs::read_to_string(f).unwrap();
        let (main, tests) = text.split_at(text.find("mod tests {").unwrap_or(text.len()));
        let paths = absolute_paths(main, &module, false).into_iter().chain(absolute_paths(tests, &module, true));
        for path in paths {
            // the file whose module is the longest start of the path
            let target = rooms
                .iter()
                .filter(|(m, _)| !m.is_empty() && path.starts_with(m))
                .max_by_key(|(m, _)| m.len())
                .map(|(_, n)| n.clone());
            if let Some(t) = target.filter(|t| *t != name) {
                edges.insert((name.clone(), t));
            }
        }
    }
    assert!(edges.len() > 200, "the scan found only {} references between files", edges.len());
    let circles: Vec<String> = edges
        .iter()
        .filter(|(a, b)| a < b && edges.contains(&(b.clone(), a.clone())))
        .map(|(a, b)| format!("src/{a} <-> src/{b}"))
        .collect();
    assert!(circles.is_empty(), "files that name each other:\n{}", circles.join("\n"));
}

#[test]
fn the_path_scanner_resolves_paths() {
    let module = ["scene".to_string(), "registry".to_string()];
    let text = "use super::hub::{Hub, HubError};\nuse crate::io::{image::RgbImage, bounded};\n\
                /// [`super::super::render::cut`] and self::x::Y";
    let got: Vec<String> = absolute_paths(text, &module, false).iter().map(|p| p.join("::")).collect();
    assert_eq!(
        got,
        [
            "scene::hub::Hub",
            "scene::hub::HubError",
            "io::image::RgbImage",
            "io::bounded",
            "render::cut",
            "scene::registry::x::Y"
        ]
    );
    let tests: Vec<String> =
        absolute_paths("use super::*; use super::super::hub::f;", &module, true).iter().map(|p| p.join("::")).collect();
    assert_eq!(tests, ["scene::hub::f"]);
    assert_eq!(module_path(Path::new("bench/accuracy/mod.rs")), ["bench", "accuracy"]);
}
