//! Checkpoints: named sections (weights, optimiser, counters, actor and task controller state)
//! in one safetensors file, written atomically; the last N are kept, plus the best.
//!
//! The file is the policy file of the `weights` section (its tensors and metadata, see
//! `policyfile::blob`) with every other section added: text sections of at most 64 KiB (counters,
//! run progress) as metadata `section.<name>`, the rest as `U8` tensors `section.<name>`; and
//! metadata `checkpoint_format` = `dronerace-checkpoint`, `checkpoint_format_version`. So a
//! checkpoint opens in Python like a policy file, and `WeightsBlob::from_bytes` reads its
//! policy directly. One layout is read: this build's.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use policyfile::safetensors::{Tensor, TensorData, TensorFile};

/// `checkpoint_format` in the metadata.
const FORMAT_NAME: &str = "dronerace-checkpoint";
/// `checkpoint_format_version` this build writes and reads.
const FORMAT: &str = "2";
/// Prefix of section entries (metadata or tensors).
const SECTION: &str = "section.";
/// Longest text section kept in the metadata header (larger ones go in the data).
const MAX_TEXT_SECTION: usize = 64 << 10;

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

    /// Encodes all sections as one safetensors file.
    pub fn to_bytes(&self) -> Vec<u8> {
        // The policy's tensors and metadata become the file's own (a blob of the earlier layout
        // is converted); anything else under that name stays an opaque section.
        let weights = self.sections.get("weights").and_then(|w| {
            if TensorFile::sniff(w) {
                TensorFile::from_bytes(w).ok()
            } else {
                policy::WeightsBlob::from_bytes(w).ok().map(|b| b.to_tensor_file())
            }
        });
        let mut file = weights.clone().unwrap_or_default();
        for (name, data) in &self.sections {
            if name == "weights" && weights.is_some() {
                continue;
            }
            match std::str::from_utf8(data) {
                Ok(text) if data.len() <= MAX_TEXT_SECTION => {
                    file.metadata.insert(format!("{SECTION}{name}"), text.to_owned());
                }
                _ => {
                    file.tensors.insert(format!("{SECTION}{name}"), Tensor::bytes(data.clone()));
                }
            }
        }
        file.metadata.insert("checkpoint_format".into(), FORMAT_NAME.into());
        file.metadata.insert("checkpoint_format_version".into(), FORMAT.into());
        file.to_bytes()
    }

    /// Decodes and verifies; `origin` names the source in errors.
    pub fn from_bytes(bytes: &[u8], origin: &Path) -> Result<Self, CheckpointError> {
        let corrupt = |reason: String| CheckpointError::Corrupt { file: origin.to_path_buf(), reason };
        if !TensorFile::sniff(bytes) {
            return Err(corrupt("not a dronerace checkpoint".into()));
        }
        let mut file = TensorFile::from_bytes(bytes).map_err(|e| corrupt(e.to_string()))?;
        if file.metadata.remove("checkpoint_format").as_deref() != Some(FORMAT_NAME) {
            return Err(corrupt("not a dronerace checkpoint (a policy file?)".into()));
        }
        let version = file.metadata.remove("checkpoint_format_version").unwrap_or_default();
        if version != FORMAT {
            return Err(corrupt(format!("checkpoint format {version:?}; this build reads {FORMAT}")));
        }
        let mut sections = BTreeMap::new();
        for key in file.metadata.keys().filter(|k| k.starts_with(SECTION)).cloned().collect::<Vec<_>>() {
            let text = file.metadata.remove(&key).unwrap_or_default();
            sections.insert(key[SECTION.len()..].to_owned(), text.into_bytes());
        }
        for key in file.tensors.keys().filter(|k| k.starts_with(SECTION)).cloned().collect::<Vec<_>>() {
            match file.tensors.remove(&key).map(|t| t.data) {
                Some(TensorData::U8(data)) => sections.insert(key[SECTION.len()..].to_owned(), data),
                _ => return Err(corrupt(format!("{key} is not a U8 tensor"))),
            };
        }
        // What remains is the policy file of the `weights` section, bit for bit as it was written.
        if !file.tensors.is_empty() || !file.metadata.is_empty() {
            sections.insert("weights".into(), file.to_bytes());
        }
        Ok(Self { sections, origin: origin.to_path_buf() })
    }

    /// Writes atomically (a crash leaves the previous file intact).
    pub fn write(&self, path: &Path) -> Result<(), CheckpointError> {
        durable::write_atomic(path, &self.to_bytes()).map_err(|source| CheckpointError::Io { file: path.to_path_buf(), source })
    }

    /// Reads and verifies a checkpoint file.
    pub fn read(path: &Path) -> Result<Self, CheckpointError> {
        let bytes =
            durable::read_limited(path, MAX_FILE_BYTES).map_err(|source| CheckpointError::Io { file: path.to_path_buf(), source })?;
        Self::from_bytes(&bytes, path)
    }
}

/// Largest checkpoint or policy file read (bytes): today's are 0.6–3 MB, a checkpoint of the
/// paper network with its optimiser state ~10 MB.
pub const MAX_FILE_BYTES: u64 = 256 << 20;

/// Checkpoint files of a run directory: `ckpt-<iteration>.bin`, `best.bin`, and the last
/// validated policies in `validated/`.
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

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Periodic checkpoints, oldest first.
    pub fn periodic(&self) -> Vec<PathBuf> {
        numbered_files(&self.dir, "ckpt-").unwrap_or_default()
    }

    /// The newest periodic checkpoint.
    pub fn latest(&self) -> Option<PathBuf> {
        self.periodic().pop()
    }

    /// Path of `best.bin`, the run's policy.
    pub fn best(&self) -> PathBuf {
        self.dir.join("best.bin")
    }

    /// Writes the policy validated after `iteration` as `validated/v-<iteration>.bin`, removes
    /// all but the newest `keep` there, and returns those kept, oldest first. Files of later
    /// iterations (a run resumed from an earlier checkpoint left them) are removed too.
    pub fn save_validated(&self, policy: &policy::WeightsBlob, iteration: u64, keep: usize) -> Result<Vec<PathBuf>, CheckpointError> {
        let dir = self.dir.join("validated");
        std::fs::create_dir_all(&dir).map_err(|source| CheckpointError::Io { file: dir.clone(), source })?;
        let path = dir.join(format!("v-{iteration:09}.bin"));
        durable::write_atomic(&path, &policy.to_bytes()).map_err(|source| CheckpointError::Io { file: path.clone(), source })?;
        let mut files = numbered_files(&dir, "v-").map_err(|source| CheckpointError::Io { file: dir.clone(), source })?;
        let later = files.split_off(files.iter().position(|p| *p > path).unwrap_or(files.len()));
        let stale = files.len().saturating_sub(keep.max(1));
        for old in later.iter().chain(&files[..stale]) {
            std::fs::remove_file(old).map_err(|source| CheckpointError::Io { file: old.clone(), source })?;
        }
        Ok(files.split_off(stale))
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

/// The `<prefix><iteration>.bin` files of `dir`, oldest first (iterations are zero-padded).
fn numbered_files(dir: &Path, prefix: &str) -> std::io::Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    files.retain(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with(prefix) && n.ends_with(".bin")));
    files.sort();
    Ok(files)
}

/// The policy in a checkpoint file or a bare weights blob file.
pub fn read_policy(path: &Path) -> Result<policy::WeightsBlob, CheckpointError> {
    let bytes = durable::read_limited(path, MAX_FILE_BYTES).map_err(|source| CheckpointError::Io { file: path.to_path_buf(), source })?;
    // A checkpoint is a policy file with more in it: read as one, the rest is ignored.
    policy::WeightsBlob::from_bytes(&bytes)
        .map_err(|reason| CheckpointError::Corrupt { file: path.to_path_buf(), reason: reason.to_string() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validated_policies_keep_the_newest_and_drop_later_ones() {
        let dir = tempfile::tempdir().unwrap();
        let checkpoints = CheckpointDir::new(dir.path().to_path_buf(), 3).unwrap();
        let policy = crate::Learner::new(crate::Profile::cpu().default_learner(), 1000, 0).weights();
        let names = |kept: Vec<PathBuf>| kept.iter().map(|p| p.file_name().unwrap().to_str().unwrap().to_owned()).collect::<Vec<_>>();
        for iteration in 1..=4 {
            checkpoints.save_validated(&policy, iteration, 2).unwrap();
        }
        let listed = |d: &Path| {
            let mut n: Vec<String> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
            n.sort();
            n
        };
        assert_eq!(listed(&dir.path().join("validated")), ["v-000000003.bin", "v-000000004.bin"]);
        // A run resumed before iteration 3 validates iteration 2 again: 3 and 4 are its future.
        let kept = checkpoints.save_validated(&policy, 2, 2).unwrap();
        assert_eq!(names(kept), ["v-000000002.bin"]);
        assert_eq!(listed(&dir.path().join("validated")), ["v-000000002.bin"]);
        assert_eq!(read_policy(&dir.path().join("validated/v-000000002.bin")).unwrap().to_bytes(), policy.to_bytes());
    }

    #[test]
    fn sections_round_trip_and_corruption_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut c = Checkpoint::default();
        c.put("weights", vec![0xff, 2, 3]);
        c.put("counters", b"{}".to_vec());
        let path = dir.path().join("c.bin");
        c.write(&path).unwrap();
        let back = Checkpoint::read(&path).unwrap();
        assert_eq!(back.get("weights").unwrap(), &[0xff, 2, 3]);
        assert_eq!(back.get("counters").unwrap(), b"{}");
        assert!(back.get("nothing").unwrap_err().to_string().contains("\"nothing\""));
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        assert!(Checkpoint::read(&path).unwrap_err().to_string().contains("outside the data"));
        let mut altered = bytes.clone();
        *altered.last_mut().unwrap() ^= 1;
        std::fs::write(&path, &altered).unwrap();
        assert!(Checkpoint::read(&path).unwrap_err().to_string().contains("checksum"));
    }

    #[test]
    fn a_checkpoint_holds_its_policy_tensors_and_round_trips_every_section() {
        let arch = policy::Architecture { hidden: vec![8], ..policy::Architecture::paper() };
        let net = policy::ActorCritic::new(&arch, -0.5, 1, &policy::Device::flex());
        let blob =
            <policy::WeightsBlob as policy::NetworkBlob>::from_model(2, &arch, &policy::ObsNormalizer::new(arch.observation_dim), &net);
        let mut c = Checkpoint::default();
        c.put("weights", blob.to_bytes());
        c.put("learner", br#"{"version":2}"#.to_vec());
        c.put("optimizer", vec![7; 70 << 10]);
        c.put("binary", vec![0xff, 0, 1]);
        let bytes = c.to_bytes();
        assert_eq!(Checkpoint::from_bytes(&bytes, Path::new("c")).unwrap(), Checkpoint { origin: "c".into(), ..c });
        assert_eq!(policy::WeightsBlob::from_bytes(&bytes).unwrap(), blob, "a checkpoint reads as its policy");
        let file = TensorFile::from_bytes(&bytes).unwrap();
        assert!(file.tensors.contains_key("actor.0.weight") && file.tensors.contains_key("section.optimizer"));
        assert!(file.metadata.contains_key("section.learner"), "counters travel in the header");
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
