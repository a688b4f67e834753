//! No import circle between the modules of any crate: each crate's modules form a layered graph,
//! so that each can be read, tested and moved without the ones that depend on it.
//!
//! The graph is read from the sources: a top-level module `m` (`src/m.rs` with `src/m/**`)
//! depends on `n` when its non-test code names `crate::n` — directly, in a `use crate::{…}` group,
//! or through a name the crate root re-exports from `n`. Comments and `#[cfg(test)]` modules are
//! left out: tests may reach anywhere.

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

/// Every file of top-level module `name` of the crate at `src`.
fn files_of(src: &Path, name: &str) -> Vec<PathBuf> {
    let mut files = vec![src.join(format!("{name}.rs"))];
    let mut dirs = vec![src.join(name)];
    while let Some(dir) = dirs.pop() {
        let Ok(entries) = fs::read_dir(&dir) else { continue };
        for entry in entries {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                files.push(path);
            }
        }
    }
    files.retain(|f| f.is_file());
    files
}

/// The first path segments named after `crate::` in `code`, `use crate::{a, b::c}` groups
/// expanded.
fn crate_paths(code: &str) -> Vec<String> {
    let mut names = Vec::new();
    let ident = |s: &str| s.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect::<String>();
    for (at, _) in code.match_indices("crate::") {
        // `$crate::` in macros names the defining crate, as `crate::` does.
        let rest = &code[at + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let mut depth = 0;
            let mut item = String::new();
            for c in group.chars() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        names.push(ident(item.trim()));
                        item.clear();
                        continue;
                    }
                    _ => {}
                }
                if depth == 0 || c != '{' {
                    item.push(c);
                }
            }
            names.push(ident(item.trim()));
        } else {
            names.push(ident(rest));
        }
    }
    names.retain(|n| !n.is_empty());
    names
}

/// The crate root's re-exports: name → the top-level module it comes from.
fn re_exports(root_code: &str, modules: &BTreeSet<String>) -> BTreeMap<String, String> {
    let mut map = BTreeMap::new();
    for statement in root_code.split(';') {
        let statement = statement.trim();
        let Some(path) = statement.strip_prefix("pub use ") else { continue };
        let module: String = path.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
        if !modules.contains(&module) {
            continue;
        }
        let items = path[module.len()..].trim_start_matches("::");
        let items = items.trim_start_matches('{').trim_end_matches('}');
        for item in items.split(',') {
            let last = item.trim().rsplit("::").next().unwrap_or("").trim();
            let name = last.rsplit(" as ").next().unwrap_or(last).trim();
            if !name.is_empty() {
                map.insert(name.to_string(), module.clone());
            }
        }
    }
    map
}

/// Module → the modules it names, for the crate at `src`.
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let root_file = if src.join("lib.rs").is_file() { src.join("lib.rs") } else { src.join("main.rs") };
    let root_code = code_of(&fs::read_to_string(&root_file).expect("the crate root"));
    let modules: BTreeSet<String> = root_code
        .lines()
        .filter_map(|l| {
            let l = l.trim();
            l.strip_prefix("pub mod ").or_else(|| l.strip_prefix("mod ")).or_else(|| l.strip_prefix("pub(crate) mod "))
        })
        .filter_map(|rest| rest.strip_suffix(';'))
        .map(str::to_string)
        .collect();
    let exports = re_exports(&root_code, &modules);
    let mut graph = BTreeMap::new();
    for module in &modules {
        let mut uses = BTreeSet::new();
        for file in files_of(src, module) {
            let code = code_of(&fs::read_to_string(&file).expect("a module file"));
            for name in crate_paths(&code) {
                let target = if modules.contains(&name) { Some(name) } else { exports.get(&name).cloned() };
                if let Some(target) = target.filter(|t| t != module) {
                    uses.insert(target);
                }
            }
        }
        graph.insert(module.clone(), uses);
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
fn no_crate_has_an_import_circle_between_its_modules() {
    let mut circles = Vec::new();
    for src in crate_roots() {
        let graph = module_graph(&src);
        if let Some(cycle) = find_cycle(&graph) {
            circles.push(format!("{}: {}", src.display(), cycle.join(" → ")));
        }
    }
    assert!(circles.is_empty(), "import circles:\n{}", circles.join("\n"));
}

/// The checker itself sees a circle when there is one, through a group import and a re-export.
#[test]
fn the_checker_finds_a_circle_through_groups_and_re_exports() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let src = dir.path();
    fs::write(src.join("lib.rs"), "pub mod a;\npub mod b;\nmod c;\npub use c::Thing;\n").expect("write");
    fs::write(src.join("a.rs"), "use crate::{b::B, other};\n// crate::c in a comment\n").expect("write");
    fs::write(src.join("b.rs"), "fn f() -> crate::Thing { todo!() }\n#[cfg(test)]\nmod tests {\n    use crate::a;\n}\n").expect("write");
    fs::write(src.join("c.rs"), "pub struct Thing;\n").expect("write");
    let graph = module_graph(src);
    assert_eq!(graph["a"], BTreeSet::from(["b".to_string()]));
    assert_eq!(graph["b"], BTreeSet::from(["c".to_string()]));
    assert_eq!(find_cycle(&graph), None, "a test module's imports do not count");
    fs::write(src.join("c.rs"), "use crate::a::*;\npub struct Thing;\n").expect("write");
    let cycle = find_cycle(&module_graph(src)).expect("a → b → c → a");
    assert_eq!(cycle.first(), cycle.last());
    assert_eq!(cycle.len(), 4, "{cycle:?}");
}
