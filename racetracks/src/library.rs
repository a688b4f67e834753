//! The hand-designed track library shipped with dronerace (the files under `tracks/`).

use std::path::Path;

use sim::Track;

use crate::track_file::{TrackFileError, parse_track};

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
}
