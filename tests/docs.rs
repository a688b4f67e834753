//! The documents a newcomer reads hold together: every section of the spec that the code and
//! the docs cite ("SPEC §N") exists in `docs/spec.md`, and no comment or page points at an
//! "issue N" or "session N" that a reader of the repository has no way to look up.

// Test code: a panic is how a failure is reported.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

/// Files under `dir` whose names end in one of `extensions`, skipping build output, the
/// virtual environment and git's own files.
fn files(dir: &Path, extensions: &[&str], out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if path.is_dir() {
            if !matches!(name.as_str(), "target" | ".git" | ".venv") {
                files(&path, extensions, out);
            }
        } else if extensions.iter().any(|e| name.ends_with(e)) {
            out.push(path);
        }
    }
}

/// The section numbers cited as "SPEC §N" (also "SPEC's …" and "SPEC (§N)") in `text`.
fn cited_sections(text: &str) -> Vec<u32> {
    let mut sections = Vec::new();
    for line in text.lines().filter(|l| l.contains("SPEC")) {
        for (i, _) in line.match_indices('§') {
            let digits: String = line[i + '§'.len_utf8()..].chars().take_while(char::is_ascii_digit).collect();
            if let Ok(n) = digits.parse() {
                sections.push(n);
            }
        }
    }
    sections
}

#[test]
fn every_spec_section_the_repository_cites_exists_in_docs_spec() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let spec = std::fs::read_to_string(root.join("docs/spec.md")).unwrap();
    let mut paths = Vec::new();
    files(root, &[".rs", ".md", ".toml", ".py", ".proto"], &mut paths);
    let mut citing = 0;
    for path in paths {
        let text = std::fs::read_to_string(&path).unwrap();
        for n in cited_sections(&text) {
            citing += 1;
            assert!(spec.contains(&format!("\n## §{n} ")), "{} cites SPEC §{n}, which docs/spec.md lacks", path.display());
        }
    }
    assert!(citing > 100, "only {citing} citations found: the scan is broken");
}

#[test]
fn no_page_or_comment_points_at_an_issue_or_session_number() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut paths: Vec<PathBuf> = ["README.md", "ARCHITECTURE.md", "BENCHMARKS.md"].iter().map(|f| root.join(f)).collect();
    files(root, &[".rs"], &mut paths);
    for path in paths {
        let text = std::fs::read_to_string(&path).unwrap().to_lowercase();
        for word in ["issue ", "issues ", "session ", "sessions "] {
            for (i, _) in text.match_indices(word) {
                let next = text[i + word.len()..].chars().next();
                assert!(
                    !next.is_some_and(|c| c.is_ascii_digit()),
                    "{}: {:?}",
                    path.display(),
                    text[i..].chars().take(30).collect::<String>()
                );
            }
        }
    }
}
