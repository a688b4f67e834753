//! Checkpoints: one file of named sections (weights, optimiser, counters, actor and task
//! controller state), written atomically with a CRC-32; the last N are kept, plus the best.
//!
//! Layout: `DRCKPT01`, section count u32, then per section: name length u32, name, data
//! length u64, data; finally the CRC-32 of everything before it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"DRCKPT01";

/// A checkpoint that could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Reading or writing failed.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file is not an intact checkpoint.
    #[error("{file}: refusing a corrupt checkpoint: {reason}")]
    Corrupt {
        /// The file.
        file: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A required section is missing.
    #[error("{file}: checkpoint has no {section:?} section")]
    Missing {
        /// The file.
        file: PathBuf,
        /// Section name.
        section: String,
    },
}

/// Named byte sections.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Checkpoint {
    sections: BTreeMap<String, Vec<u8>>,
    origin: PathBuf,
}

impl Checkpoint {
    /// Adds or replaces a section.
    pub fn put(&mut self, name: &str, data: Vec<u8>) {
        self.sections.insert(name.to_owned(), data);
    }

    /// A section's bytes.
    pub fn get(&self, name: &str) -> Result<&[u8], CheckpointError> {
        self.sections
            .get(name)
            .map(Vec::as_slice)
            .ok_or_else(|| CheckpointError::Missing { file: self.origin.clone(), section: name.to_owned() })
    }

    /// Encodes all sections.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&(self.sections.len() as u32).to_le_bytes());
        for (name, data) in &self.sections {
            out.extend_from_slice(&(name.len() as u32).to_le_bytes());
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&(data.len() as u64).to_le_bytes());
            out.extend_from_slice(data);
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Decodes and verifies; `origin` names the source in errors.
    pub fn from_bytes(bytes: &[u8], origin: &Path) -> Result<Self, CheckpointError> {
        let corrupt = |reason: &str| CheckpointError::Corrupt { file: origin.to_path_buf(), reason: reason.to_owned() };
        if bytes.len() < MAGIC.len() + 8 || &bytes[..MAGIC.len()] != MAGIC {
            return Err(corrupt("not a dronerace checkpoint"));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body).to_le_bytes() != crc {
            return Err(corrupt("checksum mismatch (truncated or altered)"));
        }
        let mut at = MAGIC.len();
        let mut take = |n: usize| -> Result<&[u8], CheckpointError> {
            // A corrupt length may be near usize::MAX: the end is computed without overflow.
            let end = at.checked_add(n).filter(|&end| end <= body.len()).ok_or_else(|| corrupt("section runs past the end"))?;
            let slice = &body[at..end];
            at = end;
            Ok(slice)
        };
        let count = le_u32(take(4)?);
        let mut sections = BTreeMap::new();
        for _ in 0..count {
            let len = le_u32(take(4)?) as usize;
            let name = String::from_utf8(take(len)?.to_vec()).map_err(|_| corrupt("section name is not UTF-8"))?;
            let len = le_u64(take(8)?) as usize;
            sections.insert(name, take(len)?.to_vec());
        }
        Ok(Self { sections, origin: origin.to_path_buf() })
    }

    /// Writes atomically (a crash leaves the previous file intact).
    pub fn write(&self, path: &Path) -> Result<(), CheckpointError> {
        racetracks::files::write_atomic(path, &self.to_bytes()).map_err(|source| CheckpointError::Io { file: path.to_path_buf(), source })
    }

    /// Reads and verifies a checkpoint file.
    pub fn read(path: &Path) -> Result<Self, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io { file: path.to_path_buf(), source })?;
        Self::from_bytes(&bytes, path)
    }
}

/// Checkpoint files of a run directory: `ckpt-<iteration>.bin` and `best.bin`.
pub struct CheckpointDir {
    dir: PathBuf,
    keep: usize,
}

impl CheckpointDir {
    /// Manages `dir`, keeping the last `keep` periodic checkpoints.
    pub fn new(dir: PathBuf, keep: usize) -> Result<Self, CheckpointError> {
        std::fs::create_dir_all(&dir).map_err(|source| CheckpointError::Io { file: dir.clone(), source })?;
        Ok(Self { dir, keep: keep.max(1) })
    }

    /// Periodic checkpoints, oldest first.
    pub fn periodic(&self) -> Vec<PathBuf> {
        let mut files: Vec<PathBuf> =
            std::fs::read_dir(&self.dir).map(|entries| entries.filter_map(|e| e.ok().map(|e| e.path())).collect()).unwrap_or_default();
        files.retain(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("ckpt-") && n.ends_with(".bin")));
        files.sort();
        files
    }

    /// The newest periodic checkpoint.
    pub fn latest(&self) -> Option<PathBuf> {
        self.periodic().pop()
    }

    /// Path of the best checkpoint.
    pub fn best(&self) -> PathBuf {
        self.dir.join("best.bin")
    }

    /// Writes the checkpoint of `iteration` and removes periodic ones beyond the last N.
    pub fn save(&self, checkpoint: &Checkpoint, iteration: u64) -> Result<PathBuf, CheckpointError> {
        let path = self.dir.join(format!("ckpt-{iteration:09}.bin"));
        checkpoint.write(&path)?;
        let files = self.periodic();
        for old in &files[..files.len().saturating_sub(self.keep)] {
            std::fs::remove_file(old).map_err(|source| CheckpointError::Io { file: old.clone(), source })?;
        }
        Ok(path)
    }
}

/// A little-endian u32 from exactly 4 bytes.
fn le_u32(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// A little-endian u64 from exactly 8 bytes.
fn le_u64(b: &[u8]) -> u64 {
    u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])
}

/// The policy in a checkpoint file or a bare weights blob file.
pub fn read_policy(path: &Path) -> Result<policy::WeightsBlob, CheckpointError> {
    let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io { file: path.to_path_buf(), source })?;
    let corrupt = |reason: String| CheckpointError::Corrupt { file: path.to_path_buf(), reason };
    if bytes.starts_with(MAGIC) {
        let checkpoint = Checkpoint::from_bytes(&bytes, path)?;
        policy::WeightsBlob::from_bytes(checkpoint.get("weights")?).map_err(|e| corrupt(e.to_string()))
    } else {
        policy::WeightsBlob::from_bytes(&bytes).map_err(|e| corrupt(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sections_round_trip_and_corruption_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut c = Checkpoint::default();
        c.put("weights", vec![1, 2, 3]);
        c.put("counters", b"{}".to_vec());
        let path = dir.path().join("c.bin");
        c.write(&path).unwrap();
        let back = Checkpoint::read(&path).unwrap();
        assert_eq!(back.get("weights").unwrap(), &[1, 2, 3]);
        assert!(back.get("nothing").unwrap_err().to_string().contains("\"nothing\""));
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        assert!(Checkpoint::read(&path).unwrap_err().to_string().contains("checksum"));
    }

    #[test]
    fn keeps_only_the_last_n_periodic_checkpoints() {
        let dir = tempfile::tempdir().unwrap();
        let d = CheckpointDir::new(dir.path().join("ck"), 2).unwrap();
        for i in [5, 10, 15, 20] {
            d.save(&Checkpoint::default(), i).unwrap();
        }
        let names: Vec<String> = d.periodic().iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["ckpt-000000015.bin", "ckpt-000000020.bin"]);
        assert!(d.latest().unwrap().ends_with("ckpt-000000020.bin"));
    }
}
