//! `dronerace tracks …`: draw and validate track files.

use std::path::PathBuf;

use clap::Subcommand;

use super::load_tracks;

/// Track subcommands.
#[derive(Subcommand)]
pub enum TracksCommand {
    /// Draw top and side views of tracks into one PNG.
    Show {
        /// Track files or directories; the built-in library when omitted.
        files: Vec<PathBuf>,
        /// PNG to write.
        #[arg(long)]
        out: PathBuf,
    },
}

/// Runs a track subcommand.
pub fn run(command: TracksCommand) -> anyhow::Result<()> {
    match command {
        TracksCommand::Show { files, out } => {
            let tracks = load_tracks(&files)?;
            crate::plot::draw_tracks(&tracks, &out)?;
            println!("wrote {} ({} tracks)", out.display(), tracks.len());
            Ok(())
        }
    }
}
