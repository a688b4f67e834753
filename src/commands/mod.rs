//! One module per subcommand: argument types and the glue that calls the crates.

pub mod bench;
pub mod chaos;
pub mod curves;
pub mod distill;
pub mod eval;
pub mod experiment;
pub mod processes;
pub mod render;
pub mod serve;
pub mod sim;
pub mod status;
pub mod tasks;
pub mod token;
pub mod tracks;
pub mod train;
pub mod transport_bench;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ::sim::Track;
use anyhow::Context;

/// Tracks from files and directories of `*.toml`; the built-in library when `paths` is empty.
pub fn load_tracks(paths: &[PathBuf]) -> anyhow::Result<Vec<Arc<Track>>> {
    let tracks = if paths.is_empty() { racetracks::library()? } else { racetracks::chosen_tracks(["--tracks"; 2], &[], paths)? };
    Ok(tracks.into_iter().map(Arc::new).collect())
}

/// A client's TLS and token settings: the `[network]` section of a run config, or none.
pub fn client_security(config: Option<&Path>) -> anyhow::Result<transport::Security> {
    let network = match config {
        Some(p) => runtime::TrainConfig::read(p)?.network,
        None => Default::default(),
    };
    Ok(transport::Security::load(&network)?)
}

/// Writes `contents` to `path` atomically, creating parent directories.
pub fn write_atomic(path: &Path, contents: &[u8]) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    durable::write_atomic(path, contents).with_context(|| format!("writing {}", path.display()))
}

/// A text file a command is given, read whole if it is a regular file of at most
/// [`durable::MAX_TEXT_FILE_BYTES`].
pub fn read_text(path: &Path) -> std::io::Result<String> {
    durable::read_text_limited(path, durable::MAX_TEXT_FILE_BYTES)
}
