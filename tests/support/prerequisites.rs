//! What a test needs from the machine beyond the Rust toolchain: tools, Python packages, root.
//!
//! On an ordinary machine a test whose prerequisite is missing says so in one line on stderr and
//! passes without running; with the environment variable `CI` set (as `tests/run.sh` and CI set
//! it) a missing prerequisite fails the test instead, so CI never skips silently.

use std::io::Write;
use std::os::unix::fs::MetadataExt;
use std::process::{Command, Stdio};

/// One thing a test needs.
pub enum Need {
    /// A program on PATH, and how to install it.
    Program { name: &'static str, install: &'static str },
    /// `python3` on PATH importing these modules, and the pip packages that provide them.
    Python { modules: &'static [&'static str], packages: &'static str },
    /// Running as root (network namespaces, rootful podman).
    Root,
}

impl Need {
    /// Why the need is unmet, with how to meet it; `None` when it is met.
    fn missing(&self) -> Option<String> {
        match self {
            Need::Program { name, install } => (!on_path(name)).then(|| format!("`{name}` ({install})")),
            Need::Python { modules, packages } => {
                let imports = format!("import {}", modules.join(", "));
                let ok = Command::new("python3")
                    .args(["-c", &imports])
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .status()
                    .is_ok_and(|s| s.success());
                (!ok).then(|| format!("python3 with {} (pip install {packages}, e.g. in tests/run.sh's .venv)", modules.join(", ")))
            }
            // /proc/self belongs to the process's effective user.
            Need::Root => {
                (std::fs::metadata("/proc/self").map(|m| m.uid()).ok() != Some(0)).then(|| "root (run as root, as CI does)".to_string())
            }
        }
    }
}

/// Whether `name` is an executable file in a PATH directory.
fn on_path(name: &str) -> bool {
    let Some(path) = std::env::var_os("PATH") else { return false };
    std::env::split_paths(&path).any(|dir| dir.join(name).metadata().is_ok_and(|m| m.is_file() && m.mode() & 0o111 != 0))
}

/// True when every need of `test` is met. Otherwise: under `CI`, panics naming what is missing;
/// elsewhere writes one line naming it (past the test harness's output capture, so it shows)
/// and returns false, and the test returns early.
pub fn available(test: &str, needs: &[Need]) -> bool {
    let missing: Vec<String> = needs.iter().filter_map(Need::missing).collect();
    if missing.is_empty() {
        return true;
    }
    let missing = format!("{test} needs {}", missing.join(", "));
    assert!(std::env::var_os("CI").is_none(), "CI is set, so a missing prerequisite fails: {missing}");
    let _ = writeln!(std::io::stderr(), "skipped: {missing}");
    false
}
