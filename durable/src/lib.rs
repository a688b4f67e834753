//! Crash-safe file writing shared by every file dronerace produces, and bounded reading of
//! every file it is given.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// The temporary sibling `write_atomic` writes `path` through.
fn temporary(path: &Path) -> PathBuf {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    PathBuf::from(tmp)
}

/// Writes `bytes` to `path` so that a crash leaves either the old file or the new one, never a
/// torn one: a temporary sibling, fsync, rename, then fsync of the directory (without it, the
/// rename itself may not survive a power cut). A failed write removes its temporary file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = temporary(path);
    let written = (|| {
        let mut file = std::fs::File::create(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
        return written;
    }
    sync_directory(path)
}

/// Largest text file dronerace reads (a run configuration, an experiment, a CSV of gates): a
/// generous multiple of any real one.
pub const MAX_TEXT_FILE_BYTES: u64 = 1 << 20;

/// Reads `path` whole if it is a regular file of at most `max` bytes; anything else (a device
/// such as `/dev/zero`, a pipe, a file too large) is refused before it can fill memory.
pub fn read_limited(path: &Path, max: u64) -> std::io::Result<Vec<u8>> {
    // Asked before opening: opening a FIFO would wait for a writer.
    if !std::fs::metadata(path)?.is_file() {
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a regular file"));
    }
    let file = std::fs::File::open(path)?;
    let metadata = file.metadata()?;
    let too_large =
        |size: u64| std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{size} bytes, more than the {max} this file may have"));
    if metadata.len() > max {
        return Err(too_large(metadata.len()));
    }
    // The file may grow between the check and the read: read one byte past the bound at most.
    let mut bytes = Vec::with_capacity(metadata.len() as usize);
    file.take(max + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// [`read_limited`] as UTF-8 text.
pub fn read_text_limited(path: &Path, max: u64) -> std::io::Result<String> {
    String::from_utf8(read_limited(path, max)?).map_err(|_| std::io::Error::new(std::io::ErrorKind::InvalidData, "not UTF-8 text"))
}

/// fsyncs the directory holding `path`, making a rename into it durable.
fn sync_directory(path: &Path) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::File::open(dir)?.sync_all()
}

/// Removes the temporary file a write of `path` cut off by a kill left behind, if any; returns
/// its path. Call it only where no other process is writing `path`.
pub fn remove_stale_temporary(path: &Path) -> std::io::Result<Option<PathBuf>> {
    let tmp = temporary(path);
    match std::fs::remove_file(&tmp) {
        Ok(()) => Ok(Some(tmp)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e),
    }
}

/// Removes every temporary file of `write_atomic` in `dir` (`*.tmp`); returns their paths.
/// Call it only where no other process writes into `dir`.
pub fn remove_stale_temporaries(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut removed = Vec::new();
    for entry in std::fs::read_dir(dir)? {
        let path = entry?.path();
        if path.extension().is_some_and(|e| e == "tmp") && path.is_file() {
            std::fs::remove_file(&path)?;
            removed.push(path);
        }
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_the_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.bin");
        write_atomic(&path, b"one").unwrap();
        write_atomic(&path, b"two").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_failed_write_and_a_killed_one_leave_no_temporary_behind() {
        let dir = tempfile::tempdir().unwrap();
        // Renaming onto a directory fails after the temporary file was written.
        let blocked = dir.path().join("taken");
        std::fs::create_dir(&blocked).unwrap();
        std::fs::write(blocked.join("x"), b"").unwrap();
        assert!(write_atomic(&blocked, b"data").is_err());
        assert!(!temporary(&blocked).exists(), "the failed write removed its temporary file");
        // What a kill between create and rename leaves: removed by the next start.
        let path = dir.path().join("b.bin");
        std::fs::write(temporary(&path), b"half").unwrap();
        std::fs::write(dir.path().join("c.bin.tmp"), b"half").unwrap();
        assert_eq!(remove_stale_temporary(&path).unwrap(), Some(temporary(&path)));
        assert_eq!(remove_stale_temporary(&path).unwrap(), None);
        assert_eq!(remove_stale_temporaries(dir.path()).unwrap(), vec![dir.path().join("c.bin.tmp")]);
        assert!(dir.path().join("taken").is_dir(), "only temporaries go");
    }

    #[test]
    fn a_device_or_an_oversized_file_is_refused_before_it_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.toml");
        std::fs::write(&path, b"0123456789").unwrap();
        assert_eq!(read_limited(&path, 10).unwrap(), b"0123456789");
        assert!(read_limited(&path, 9).unwrap_err().to_string().contains("10 bytes, more than the 9"));
        assert!(read_limited(Path::new("/dev/zero"), 1 << 30).unwrap_err().to_string().contains("not a regular file"));
        let fifo = dir.path().join("fifo");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        assert!(read_limited(&fifo, 10).unwrap_err().to_string().contains("not a regular file"), "a FIFO is refused, not waited on");
        std::fs::write(&path, [0xff, 0xfe]).unwrap();
        assert!(read_text_limited(&path, 10).unwrap_err().to_string().contains("UTF-8"));
    }
}
