//! The hand-designed track library shipped with dronerace (the files under `tracks/`).

use std::path::{Path, PathBuf};

use sim::Track;

use crate::track_file::{TrackFileError, parse_track, read_track, read_track_dir};

/// The library's files, compiled in so every command has them whatever the working directory.
const LIBRARY: &[(&str, &str)] = &[
    ("tracks/figure8.toml", include_str!("../../tracks/figure8.toml")),
    ("tracks/bigs.toml", include_str!("../../tracks/bigs.toml")),
    ("tracks/kidney.toml", include_str!("../../tracks/kidney.toml")),
    ("tracks/twist.toml", include_str!("../../tracks/twist.toml")),
    ("tracks/splits.toml", include_str!("../../tracks/splits.toml")),
    ("tracks/hairpin.toml", include_str!("../../tracks/hairpin.toml")),
    ("tracks/slalom.toml", include_str!("../../tracks/slalom.toml")),
    ("tracks/ladder.toml", include_str!("../../tracks/ladder.toml")),
    ("tracks/tilted.toml", include_str!("../../tracks/tilted.toml")),
];

/// Every library track, in library order.
pub fn library() -> Result<Vec<Track>, TrackFileError> {
    LIBRARY.iter().map(|(file, text)| parse_track(text, Path::new(file))).collect()
}

/// The library track with this name (case-insensitive).
pub fn library_track(name: &str) -> Result<Option<Track>, TrackFileError> {
    Ok(library()?.into_iter().find(|t| t.name.eq_ignore_ascii_case(name)))
}

/// Tracks chosen by a config or the command line, by library name or from a user's files.
#[derive(Debug, thiserror::Error)]
pub enum ChosenTracksError {
    /// A name the library does not have.
    #[error("{field}: no library track {name:?} (the library: {known}); a track file is named by its path")]
    UnknownName {
        /// Where the name was given, e.g. `tracks.names`.
        field: String,
        /// The name.
        name: String,
        /// The library's names.
        known: String,
    },
    /// A file or directory that could not be read as tracks.
    #[error("{field}: {source}")]
    File {
        /// Where the file was given, e.g. `tracks.files`.
        field: String,
        /// What is wrong with it (naming the file).
        source: TrackFileError,
    },
    /// A directory without track files.
    #[error("{field}: {dir}: no *.toml track files in this directory")]
    EmptyDirectory {
        /// Where the directory was given.
        field: String,
        /// The directory.
        dir: PathBuf,
    },
}

/// The library tracks `names` (case-insensitive) then the tracks in `files` (track files, or
/// directories of them read in file-name order), in the order given; `fields` names where each
/// list was given (e.g. `tracks.names` and `tracks.files`, or `--tracks` for both) for errors.
pub fn chosen_tracks(fields: [&str; 2], names: &[String], files: &[PathBuf]) -> Result<Vec<Track>, ChosenTracksError> {
    let [names_field, files_field] = fields;
    let file_error = |source| ChosenTracksError::File { field: files_field.to_string(), source };
    let library = library().map_err(file_error)?;
    let mut tracks = Vec::new();
    for name in names {
        let track = library.iter().find(|t| t.name.eq_ignore_ascii_case(name)).ok_or_else(|| ChosenTracksError::UnknownName {
            field: names_field.to_string(),
            name: name.clone(),
            known: library.iter().map(|t| t.name.as_str()).collect::<Vec<_>>().join(", "),
        })?;
        tracks.push(track.clone());
    }
    for path in files {
        if path.is_dir() {
            let found = read_track_dir(path).map_err(file_error)?;
            if found.is_empty() {
                return Err(ChosenTracksError::EmptyDirectory { field: files_field.to_string(), dir: path.clone() });
            }
            tracks.extend(found);
        } else {
            tracks.push(read_track(path).map_err(file_error)?);
        }
    }
    Ok(tracks)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_library_has_the_named_tracks_and_all_are_valid() {
        let tracks = library().unwrap();
        assert!(tracks.len() >= 9);
        for name in ["Figure8", "BigS", "Kidney", "Twist", "SplitS"] {
            assert!(tracks.iter().any(|t| t.name == name), "{name} missing");
        }
    }

    #[test]
    fn the_compiled_library_matches_the_files_on_disk() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tracks");
        let on_disk = crate::track_file::read_track_dir(&dir).unwrap();
        assert_eq!(on_disk.len(), LIBRARY.len(), "every file under tracks/ is in the library");
        for t in library().unwrap() {
            assert!(on_disk.contains(&t), "{} differs from its file", t.name);
        }
    }

    #[test]
    fn chosen_tracks_mix_library_names_files_and_directories_and_name_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let mine = library_track("Kidney").unwrap().unwrap();
        let mine = Track { name: "Mine".into(), ..mine };
        crate::write_track(&mine, &dir.path().join("mine.toml")).unwrap();
        let tracks =
            chosen_tracks(["tracks.names", "tracks.files"], &["figure8".into()], &[dir.path().join("mine.toml"), dir.path().to_path_buf()])
                .unwrap();
        let names: Vec<&str> = tracks.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(names, ["Figure8", "Mine", "Mine"]);
        let e = chosen_tracks(["tracks.names", "tracks.files"], &["Nowhere".into()], &[]).unwrap_err().to_string();
        assert!(e.starts_with("tracks.names: no library track \"Nowhere\"") && e.contains("Figure8"), "{e}");
        let e = chosen_tracks(["eval.library", "eval.files"], &[], &[dir.path().join("missing.toml")]).unwrap_err().to_string();
        assert!(e.starts_with("eval.files:") && e.contains("missing.toml"), "{e}");
        std::fs::write(dir.path().join("bad.toml"), "name = \"Bad\"\n").unwrap();
        let e = chosen_tracks(["tracks.names", "tracks.files"], &[], &[dir.path().join("bad.toml")]).unwrap_err().to_string();
        assert!(e.contains("bad.toml"), "{e}");
    }
}
