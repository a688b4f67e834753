//! Claiming one run directory, so that several `dronerace experiment run` processes — on one
//! machine or on several sharing a file system — split a grid instead of training the same run
//! twice.
//!
//! The claim is a file `run.lock` holding `host pid`, made by hard-linking a written draft to
//! that name (atomic, and failing if the name exists, on local file systems and NFS). It is removed when the claim is dropped. A process
//! killed with `-9` leaves it behind: on the same host a claim whose process is gone is stale and
//! is taken over; a claim from another host is never second-guessed (the message names the file
//! to delete once that host is known to be done).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The file name of a run directory's claim.
pub const LOCK_FILE: &str = "run.lock";

/// An exclusive claim on a run directory, released on drop.
#[derive(Debug)]
pub struct RunLock {
    path: PathBuf,
}

/// Why a run directory could not be claimed.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// A live process (or one on another host) holds it.
    #[error("{path} is held by {holder} (another runner is training this run; delete the file if that runner is gone)")]
    Held {
        /// The lock file.
        path: String,
        /// Its `host pid` line.
        holder: String,
    },
    /// The lock file could not be written or read.
    #[error("{path}: {message}")]
    Io {
        /// The lock file.
        path: String,
        /// What failed.
        message: String,
    },
}

impl LockError {
    /// The claim at `path` is held by the process its `holder` line names.
    fn held(path: &Path, holder: &str) -> Self {
        Self::Held { path: path.display().to_string(), holder: holder.trim().to_owned() }
    }

    /// Reading or writing the claim at `path` failed.
    fn io(path: &Path, error: std::io::Error) -> Self {
        Self::Io { path: path.display().to_string(), message: error.to_string() }
    }
}

impl RunLock {
    /// Claims `dir` (which must exist) for this process, taking over a stale claim of a dead
    /// process on this host.
    pub fn acquire(dir: &Path) -> Result<Self, LockError> {
        let path = dir.join(LOCK_FILE);
        let me = format!("{} {}", this_host(), std::process::id());
        // The claim appears with its contents in one step (a hard link of a written file, which
        // fails if the name exists), so another runner never reads a half-written claim.
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let draft = dir.join(format!("{LOCK_FILE}.{}.{}", std::process::id(), NEXT.fetch_add(1, Ordering::Relaxed)));
        std::fs::write(&draft, me.as_bytes()).map_err(|e| LockError::io(&path, e))?;
        let result = Self::link(&draft, &path);
        let _ = std::fs::remove_file(&draft);
        result
    }

    /// Links `draft` to `path`, taking over a stale claim once.
    fn link(draft: &Path, path: &Path) -> Result<Self, LockError> {
        // Two attempts: the second after removing a stale claim (if another runner removes it
        // and claims first, the second attempt reports that runner as the holder).
        for _ in 0..2 {
            match std::fs::hard_link(draft, path) {
                Ok(()) => return Ok(Self { path: path.to_path_buf() }),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let holder = std::fs::read_to_string(path).unwrap_or_default();
                    if !is_stale(&holder) {
                        return Err(LockError::held(path, &holder));
                    }
                    match std::fs::remove_file(path) {
                        Ok(()) => {}
                        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                        Err(e) => return Err(LockError::io(path, e)),
                    }
                }
                Err(e) => return Err(LockError::io(path, e)),
            }
        }
        Err(LockError::held(path, &std::fs::read_to_string(path).unwrap_or_default()))
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        // Nothing to do if it is already gone; a leftover file is taken over as stale later.
        let _ = std::fs::remove_file(&self.path);
    }
}

/// This machine's host name (empty if the kernel does not say).
fn this_host() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname").map(|h| h.trim().to_owned()).unwrap_or_default()
}

/// Whether a claim's `host pid` line names a process of this host that no longer exists; a line
/// that is not `host pid` (claims are never written partly) counts as stale.
fn is_stale(holder: &str) -> bool {
    let mut words = holder.split_whitespace();
    let (Some(host), Some(pid)) = (words.next(), words.next().and_then(|p| p.parse::<u32>().ok())) else {
        return true;
    };
    host == this_host() && !Path::new(&format!("/proc/{pid}")).exists()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_claim_is_refused_until_the_first_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let first = RunLock::acquire(dir.path()).unwrap();
        let refused = RunLock::acquire(dir.path()).unwrap_err();
        assert!(matches!(refused, LockError::Held { .. }), "{refused}");
        assert!(refused.to_string().contains(&std::process::id().to_string()), "names the holder: {refused}");
        drop(first);
        assert!(!dir.path().join(LOCK_FILE).exists());
        RunLock::acquire(dir.path()).unwrap();
    }

    #[test]
    fn a_dead_process_claim_on_this_host_is_taken_over_but_another_hosts_is_not() {
        let dir = tempfile::tempdir().unwrap();
        // A pid above the kernel's pid_max (4,194,304) never exists.
        std::fs::write(dir.path().join(LOCK_FILE), format!("{} 4999999", this_host())).unwrap();
        let taken = RunLock::acquire(dir.path()).unwrap();
        let line = std::fs::read_to_string(dir.path().join(LOCK_FILE)).unwrap();
        assert!(line.ends_with(&format!(" {}", std::process::id())), "{line}");
        drop(taken);

        std::fs::write(dir.path().join(LOCK_FILE), "some-other-host 4999999").unwrap();
        assert!(matches!(RunLock::acquire(dir.path()), Err(LockError::Held { .. })));
    }
}
