//! No import circle between the files of any crate: each crate's module files form a layered
//! graph, so that each can be read, tested and moved without the ones that depend on it.
//!
//! The graph is read from the sources. Its nodes are module files (`src/a.rs` or
//! `src/a/mod.rs` is `a`, `src/a/b.rs` is `a::b`; the crate root is left out, as it declares
//! every module). A file depends on the module a path in its non-test code resolves to: the
//! longest prefix of `crate::…`, `super::…` or a child module's `child::…` that names a module
//! file — or, where that module re-exports the next name from one of its children (`pub use
//! child::Name`), that child. The re-exporting `pub use` itself is no dependency. Comments and
//! `#[cfg(test)]` modules are left out: tests may reach anywhere.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

/// The workspace's crates with a library or binary root under `src/`.
fn crate_roots() -> Vec<PathBuf> {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut roots = vec![workspace.join("src")];
    for entry in fs::read_dir(workspace).expect("the workspace directory") {
        let src = entry.expect("a directory entry").path().join("src");
        if src.join("lib.rs").is_file() {
            roots.push(src);
        }
    }
    roots.sort();
    roots
}

/// The code of a file without comments and without its `#[cfg(test)]` items (a test module runs
/// to the end of the file in this workspace's style, or to its closing brace at column 0).
fn code_of(text: &str) -> String {
    let mut code = String::new();
    let mut in_tests = false;
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        if in_tests {
            in_tests = line != "}";
            continue;
        }
        if line.trim_start().starts_with("#[cfg(test)]") {
            in_tests = lines.peek().is_some_and(|next| next.trim_start().starts_with("mod "));
            continue;
        }
        let without_comment = match line.find("//") {
            Some(at) => &line[..at],
            None => line,
        };
        code.push_str(without_comment);
        code.push('\n');
    }
    code
}

/// Every module file of the crate at `src`: module path (`""` for the root) → file.
fn module_files(src: &Path) -> BTreeMap<String, PathBuf> {
    let mut files = BTreeMap::new();
    let mut dirs = vec![src.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in fs::read_dir(&dir).expect("a source directory") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let relative = path.strip_prefix(src).expect("under src").with_extension("");
            let mut parts: Vec<String> = relative.iter().map(|p| p.to_string_lossy().into_owned()).collect();
            if parts.last().is_some_and(|p| p == "mod") || (parts.len() == 1 && (parts[0] == "lib" || parts[0] == "main")) {
                parts.pop();
            }
            files.insert(parts.join("::"), path);
        }
    }
    files
}

/// Whether `c` can be part of an identifier.
fn ident_char(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// The paths of a use tree written at the start of `text` (`a::b`, `{a, b::{c, d}}`, `a::*`),
/// each as its segments; a segment that is no identifier (`*`, `self`) ends its path.
fn use_tree(text: &str) -> Vec<Vec<String>> {
    fn parse(chars: &[char], at: &mut usize) -> Vec<Vec<String>> {
        let mut prefix = Vec::new();
        loop {
            while *at < chars.len() && chars[*at].is_whitespace() {
                *at += 1;
            }
            if *at < chars.len() && chars[*at] == '{' {
                *at += 1;
                let mut paths = Vec::new();
                loop {
                    for mut sub in parse(chars, at) {
                        let mut full = prefix.clone();
                        full.append(&mut sub);
                        paths.push(full);
                    }
                    while *at < chars.len() && chars[*at].is_whitespace() {
                        *at += 1;
                    }
                    match chars.get(*at) {
                        Some(',') => *at += 1,
                        Some('}') => {
                            *at += 1;
                            return paths;
                        }
                        _ => return paths,
                    }
                }
            }
            let start = *at;
            while *at < chars.len() && ident_char(chars[*at]) {
                *at += 1;
            }
            let segment: String = chars[start..*at].iter().collect();
            if segment.is_empty() || segment == "self" {
                return vec![prefix];
            }
            prefix.push(segment);
            if chars.get(*at) == Some(&':') && chars.get(*at + 1) == Some(&':') {
                *at += 2;
            } else {
                return vec![prefix];
            }
        }
    }
    let chars: Vec<char> = text.chars().collect();
    parse(&chars, &mut 0)
}

/// The absolute paths (segments from the crate root) that `code` of module `module` names
/// through `crate::`, `super::` or one of `children`'s names.
fn named_paths(code: &str, module: &str, children: &BTreeSet<String>) -> Vec<Vec<String>> {
    let here: Vec<String> = if module.is_empty() { Vec::new() } else { module.split("::").map(str::to_string).collect() };
    let mut paths = Vec::new();
    let mut at = 0;
    while at < code.len() {
        let rest = &code[at..];
        let before = code[..at].chars().next_back();
        if before.is_some_and(|c| ident_char(c) || c == ':') {
            at += rest.chars().next().map_or(1, char::len_utf8);
            continue;
        }
        let (base, tree) = if let Some(tree) = rest.strip_prefix("crate::") {
            (Vec::new(), tree)
        } else if rest.starts_with("super::") {
            let mut base = here.clone();
            let mut tree = rest;
            while let Some(next) = tree.strip_prefix("super::") {
                base.pop();
                tree = next;
            }
            (base, tree)
        } else if children.iter().any(|c| rest.strip_prefix(c.as_str()).is_some_and(|r| r.starts_with("::"))) {
            (here.clone(), rest)
        } else {
            at += rest.chars().next().map_or(1, char::len_utf8);
            continue;
        };
        for mut path in use_tree(tree) {
            let mut full = base.clone();
            full.append(&mut path);
            paths.push(full);
        }
        at += 1;
    }
    paths
}

/// What `code` re-exports from child modules of `module` (`pub use child::…::Name`): name → child.
fn re_exports(code: &str, module: &str, modules: &BTreeMap<String, PathBuf>) -> BTreeMap<String, String> {
    let mut map = BTreeMap::new();
    for statement in code.split(';') {
        let Some(tree) = statement.trim().strip_prefix("pub use ") else { continue };
        let tree = tree.strip_prefix("self::").unwrap_or(tree);
        for path in use_tree(tree) {
            let (Some(first), Some(name)) = (path.first(), path.last()) else { continue };
            let child = if module.is_empty() { first.clone() } else { format!("{module}::{first}") };
            if path.len() > 1 && modules.contains_key(&child) {
                map.insert(name.clone(), child);
            }
        }
    }
    map
}

/// Module file → the module files it depends on, for the crate at `src`.
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let files = module_files(src);
    let codes: BTreeMap<&String, String> =
        files.iter().map(|(m, f)| (m, code_of(&fs::read_to_string(f).expect("a module file")))).collect();
    let children = |module: &str| -> BTreeSet<String> {
        let prefix = if module.is_empty() { String::new() } else { format!("{module}::") };
        files.keys().filter_map(|m| m.strip_prefix(&prefix).filter(|c| !c.is_empty() && !c.contains("::"))).map(str::to_string).collect()
    };
    let exports: BTreeMap<&String, BTreeMap<String, String>> = codes.iter().map(|(m, code)| (*m, re_exports(code, m, &files))).collect();
    let resolve = |path: &[String]| -> Option<String> {
        let mut target = None;
        for n in (1..=path.len()).rev() {
            let candidate = path[..n].join("::");
            if files.contains_key(&candidate) {
                target = Some((candidate, n));
                break;
            }
        }
        let (module, n) = target.unwrap_or((String::new(), 0));
        // A name the module re-exports from a child is that child's.
        let through = path.get(n).and_then(|name| exports.get(&module).and_then(|e| e.get(name)).cloned());
        through.or(Some(module)).filter(|m| !m.is_empty())
    };
    let mut graph = BTreeMap::new();
    for (module, code) in &codes {
        if module.is_empty() {
            continue;
        }
        let own_exports: String = code.split(';').filter(|s| !s.trim().starts_with("pub use ")).collect::<Vec<_>>().join(";");
        let uses: BTreeSet<String> = named_paths(&own_exports, module, &children(module))
            .iter()
            .filter_map(|path| resolve(path))
            .filter(|target| target != *module)
            .collect();
        graph.insert((*module).clone(), uses);
    }
    graph
}

/// A cycle through the graph, if there is one (depth-first search, colours by path).
fn find_cycle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(start) = path.iter().position(|n| n == node) {
            let mut cycle = path[start..].to_vec();
            cycle.push(node.to_string());
            return Some(cycle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, graph, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node.to_string());
        None
    }
    let mut done = BTreeSet::new();
    graph.keys().find_map(|node| visit(node, graph, &mut Vec::new(), &mut done))
}

#[test]
fn no_crate_has_an_import_circle_between_its_files() {
    let mut circles = Vec::new();
    for src in crate_roots() {
        let graph = module_graph(&src);
        if let Some(cycle) = find_cycle(&graph) {
            circles.push(format!("{}: {}", src.display(), cycle.join(" → ")));
        }
    }
    assert!(circles.is_empty(), "import circles:\n{}", circles.join("\n"));
}

/// The checker itself sees a circle when there is one: between top-level modules through a
/// group import and a root re-export, and between files of one directory through `super::`.
#[test]
fn the_checker_finds_circles_through_groups_re_exports_and_super() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let src = dir.path();
    fs::write(src.join("lib.rs"), "pub mod a;\npub mod b;\nmod c;\npub mod d;\npub use c::Thing;\n").expect("write");
    fs::write(src.join("a.rs"), "use crate::{b::B, other};\n// crate::c in a comment\n").expect("write");
    fs::write(src.join("b.rs"), "fn f() -> crate::Thing { todo!() }\n#[cfg(test)]\nmod tests {\n    use crate::a;\n}\n").expect("write");
    fs::write(src.join("c.rs"), "pub struct Thing;\n").expect("write");
    fs::create_dir(src.join("d")).expect("mkdir");
    fs::write(src.join("d/mod.rs"), "pub mod e;\npub mod f;\npub use e::E;\npub fn g() {}\n").expect("write");
    fs::write(src.join("d/e.rs"), "pub struct E;\nfn h() { super::g() }\n").expect("write");
    fs::write(src.join("d/f.rs"), "use super::{E, e::E as Again};\n").expect("write");
    let graph = module_graph(src);
    assert_eq!(graph["a"], BTreeSet::from(["b".to_string()]));
    assert_eq!(graph["b"], BTreeSet::from(["c".to_string()]));
    assert_eq!(graph["d::e"], BTreeSet::from(["d".to_string()]));
    assert_eq!(graph["d::f"], BTreeSet::from(["d::e".to_string()]), "a name d re-exports is e's");
    assert_eq!(graph["d"], BTreeSet::new(), "a re-export is no dependency");
    assert_eq!(find_cycle(&graph), None, "a test module's imports do not count");
    fs::write(src.join("c.rs"), "use crate::a::*;\npub struct Thing;\n").expect("write");
    let cycle = find_cycle(&module_graph(src)).expect("a → b → c → a");
    assert_eq!(cycle.first(), cycle.last());
    assert_eq!(cycle.len(), 4, "{cycle:?}");
    fs::write(src.join("c.rs"), "pub struct Thing;\n").expect("write");
    fs::write(src.join("d/mod.rs"), "pub mod e;\npub mod f;\npub use e::E;\npub fn g() { f::x() }\n").expect("write");
    fs::write(src.join("d/f.rs"), "pub fn x() { super::g() }\n").expect("write");
    let cycle = find_cycle(&module_graph(src)).expect("d → d::f → d");
    assert_eq!(cycle.len(), 3, "{cycle:?}");
}
