//! Track files: TOML, one track per file (SPEC §6), read strictly and written back exactly.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sim::nalgebra::Vector3;
use sim::{Arena, Gate, Pose, Track};

/// A track file that could not be read, parsed or validated.
#[derive(Debug, thiserror::Error)]
pub enum TrackFileError {
    /// The file could not be read or written.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The TOML is malformed or has unknown, missing or mistyped fields.
    #[error("{file}: {message}")]
    Syntax {
        /// The file.
        file: PathBuf,
        /// The parser's description, naming the key and line.
        message: String,
    },
    /// The values parse but break a rule of SPEC §6.
    #[error("{file}: {field}: {message}")]
    Invalid {
        /// The file.
        file: PathBuf,
        /// Field path, e.g. `gate[2].position`.
        field: String,
        /// What is wrong.
        message: String,
    },
}

/// On-disk layout of a track file.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct TrackToml {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    name: Option<String>,
    #[serde(rename = "gate", default)]
    gates: Vec<PoseToml>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    start: Option<PoseToml>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    arena: Option<ArenaToml>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct PoseToml {
    position: [f64; 3],
    yaw_deg: f64,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ArenaToml {
    min: [f64; 3],
    max: [f64; 3],
}

impl PoseToml {
    fn to_pose(&self) -> Pose {
        Pose { position: Vector3::from(self.position), yaw: self.yaw_deg.to_radians() }
    }

    fn from_pose(position: &Vector3<f64>, yaw: f64) -> Self {
        Self { position: (*position).into(), yaw_deg: yaw.to_degrees() }
    }
}

/// Largest track file (bytes): a track of [`sim::track::MAX_GATES`] gates takes ~5 kB.
pub const MAX_TRACK_FILE_BYTES: usize = 64 << 10;

/// Parses track TOML; `file` names the source in errors and gives the default name (its stem).
pub fn parse_track(text: &str, file: &Path) -> Result<Track, TrackFileError> {
    if text.len() > MAX_TRACK_FILE_BYTES {
        return Err(TrackFileError::Syntax {
            file: file.to_path_buf(),
            message: format!("{} bytes, more than the {MAX_TRACK_FILE_BYTES} a track file may have", text.len()),
        });
    }
    let raw: TrackToml = toml::from_str(text)
        .map_err(|e| TrackFileError::Syntax { file: file.to_path_buf(), message: e.to_string().trim_end().to_owned() })?;
    let name = raw.name.unwrap_or_else(|| file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default());
    let gates = raw.gates.iter().map(|g| {
        let p = g.to_pose();
        Gate::new(p.position, p.yaw)
    });
    let arena = raw.arena.map_or_else(Arena::default, |a| Arena { min: a.min.into(), max: a.max.into() });
    Track::new(name, gates.collect(), raw.start.as_ref().map(PoseToml::to_pose), arena).map_err(|e| TrackFileError::Invalid {
        file: file.to_path_buf(),
        field: e.field,
        message: e.message,
    })
}

/// A track from a CSV of gate poses, one gate a row in racing order: `x,y,z,yaw_deg` (m, world;
/// the gate's flight direction in degrees from +x); a header row and `#` comments are skipped.
/// The arena is SPEC §6's when every gate fits in it, else the gates' bounding box widened by
/// 4 m sideways and reaching from the ground to 3 m above the highest gate; the start pose is
/// SPEC's default behind the first gate. `file` names the CSV in errors (`row N`).
pub fn track_from_csv(name: &str, text: &str, file: &Path) -> Result<Track, TrackFileError> {
    let invalid = |field: String, message: String| TrackFileError::Invalid { file: file.to_path_buf(), field, message };
    let mut gates = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || (gates.is_empty() && line.chars().next().is_some_and(char::is_alphabetic)) {
            continue;
        }
        let values: Vec<f64> = line
            .split(',')
            .map(|cell| cell.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| invalid(format!("row {}", i + 1), format!("{line:?}: {e}")))?;
        let [x, y, z, yaw_deg] = values[..] else {
            return Err(invalid(format!("row {}", i + 1), format!("{} values; a gate is x,y,z,yaw_deg", values.len())));
        };
        gates.push(Gate::new(Vector3::new(x, y, z), yaw_deg.to_radians()));
    }
    // The gates and the default start behind gate 0 must fit in the arena.
    let mut points: Vec<Vector3<f64>> = gates.iter().map(|g| g.position).collect();
    if let Some(g0) = gates.first() {
        points.push(g0.position - g0.normal() * sim::track::START_BEHIND_FIRST_GATE);
    }
    let default = Arena::default();
    let inside = |p: &Vector3<f64>| (0..3).all(|k| p[k] > default.min[k] && p[k] < default.max[k]);
    let arena = if points.iter().all(inside) {
        default
    } else {
        let low = |k: usize| points.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min);
        let high = |k: usize| points.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max);
        Arena {
            min: Vector3::new(low(0) - 4.0, low(1) - 4.0, low(2).min(0.0)),
            max: Vector3::new(high(0) + 4.0, high(1) + 4.0, high(2) + 3.0),
        }
    };
    Track::new(name, gates, None, arena).map_err(|e| invalid(e.field, e.message))
}

/// Reads and validates a track file.
pub fn read_track(path: &Path) -> Result<Track, TrackFileError> {
    let text = durable::read_text_limited(path, MAX_TRACK_FILE_BYTES as u64)
        .map_err(|source| TrackFileError::Io { file: path.to_path_buf(), source })?;
    parse_track(&text, path)
}

/// Reads every `*.toml` in `dir`, sorted by file name.
pub fn read_track_dir(dir: &Path) -> Result<Vec<Track>, TrackFileError> {
    let io = |source| TrackFileError::Io { file: dir.to_path_buf(), source };
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir).map_err(io)?.map(|e| e.map(|e| e.path())).collect::<Result<_, _>>().map_err(io)?;
    paths.retain(|p| p.extension().is_some_and(|e| e == "toml"));
    paths.sort();
    paths.iter().map(|p| read_track(p)).collect()
}

/// Serialises a track to TOML that [`parse_track`] reads back to the same track.
#[allow(clippy::expect_used, reason = "a track always serialises")]
pub fn track_to_toml(track: &Track) -> String {
    let raw = TrackToml {
        name: Some(track.name.clone()),
        gates: track.gates.iter().map(|g| PoseToml::from_pose(&g.position, g.yaw)).collect(),
        start: Some(PoseToml::from_pose(&track.start.position, track.start.yaw)),
        arena: Some(ArenaToml { min: track.arena.min.into(), max: track.arena.max.into() }),
    };
    toml::to_string(&raw).expect("a track always serialises")
}

/// Writes a track file atomically.
pub fn write_track(track: &Track, path: &Path) -> Result<(), TrackFileError> {
    durable::write_atomic(path, track_to_toml(track).as_bytes()).map_err(|source| TrackFileError::Io { file: path.to_path_buf(), source })
}

#[cfg(test)]
mod tests {
    use super::*;

    const VALID: &str = r#"
name = "Pair"
[[gate]]
position = [0.0, 0.0, 2.0]
yaw_deg = 0.0
[[gate]]
position = [6.0, 3.0, 2.5]
yaw_deg = 90.0
"#;

    /// A valid-looking file of `n` gates in a row, 2.5 m apart, in an arena that holds them.
    fn many_gates(n: usize) -> String {
        let gates: String = (0..n).map(|i| format!("[[gate]]\nposition = [{}.0, 0.0, 2.0]\nyaw_deg = 0.0\n", 3 * i)).collect();
        format!("{gates}[arena]\nmin = [-10.0, -10.0, 0.0]\nmax = [{}.0, 10.0, 6.0]\n", 3 * n + 10)
    }

    fn err(text: &str) -> String {
        parse_track(text, Path::new("tracks/bad.toml")).unwrap_err().to_string()
    }

    #[test]
    fn a_valid_file_parses_with_defaults() {
        let t = parse_track(VALID, Path::new("x.toml")).unwrap();
        assert_eq!(t.name, "Pair");
        assert_eq!(t.gates.len(), 2);
        assert!((t.gates[1].yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((t.start.position - Vector3::new(-2.0, 0.0, 2.0)).norm() < 1e-12);
        assert_eq!(t.arena, Arena::default());
    }

    #[test]
    fn the_name_defaults_to_the_file_stem() {
        let t = parse_track(&VALID.replace("name = \"Pair\"", ""), Path::new("dir/my_track.toml")).unwrap();
        assert_eq!(t.name, "my_track");
    }

    #[test]
    fn write_then_read_gives_the_same_track() {
        let dir = tempfile::tempdir().unwrap();
        let t = parse_track(VALID, Path::new("x.toml")).unwrap();
        let path = dir.path().join("pair.toml");
        write_track(&t, &path).unwrap();
        let back = read_track(&path).unwrap();
        assert_eq!(back.name, t.name);
        assert_eq!(back.start.position, t.start.position);
        for (a, b) in back.gates.iter().zip(&t.gates) {
            assert_eq!(a.position, b.position);
            assert!((a.yaw - b.yaw).abs() < 1e-15);
        }
    }

    #[test]
    fn every_invalid_case_names_the_file_and_the_field() {
        let cases: Vec<(String, &str)> = vec![
            (VALID.replace("yaw_deg = 90.0", "yaw_deg = 90.0\ncolour = \"red\""), "colour"),
            (format!("{VALID}\nlaps = 3\n"), "laps"),
            (VALID.replace("yaw_deg = 90.0", ""), "yaw_deg"),
            (VALID.replace("[6.0, 3.0, 2.5]", "[6.0, 3.0]"), "length 2"),
            (VALID.replace("[6.0, 3.0, 2.5]", "[6.0, \"3\", 2.5]"), "position"),
            (VALID.replace("[6.0, 3.0, 2.5]", "[6.0, nan, 2.5]"), "gate[1].position"),
            (VALID.replace("yaw_deg = 90.0", "yaw_deg = inf"), "gate[1].yaw_deg"),
            ("name = \"one\"\n[[gate]]\nposition = [0.0, 0.0, 2.0]\nyaw_deg = 0.0\n".into(), "at least 2 gates"),
            ("name = \"none\"\n".into(), "at least 2 gates"),
            (VALID.replace("[6.0, 3.0, 2.5]", "[13.0, 3.0, 2.5]"), "gate[1].position"),
            (VALID.replace("[6.0, 3.0, 2.5]", "[0.5, 0.0, 2.5]"), "overlaps"),
            (format!("{VALID}[start]\nposition = [0.0, -12.5, 2.0]\nyaw_deg = 0.0\n"), "start.position"),
            (format!("{VALID}[start]\nposition = [0.0, -1.0, nan]\nyaw_deg = 0.0\n"), "start"),
            (format!("{VALID}[arena]\nmin = [0.0, 0.0, 0.0]\nmax = [0.0, 10.0, 6.0]\n"), "arena"),
            (format!("{VALID}[arena]\nmin = [-5.0, -5.0, 0.0]\nmax = [5.0, 5.0, 6.0]\n"), "gate[1].position"),
            ("name = \"Pair\"\n[[gate]\n".into(), "line 2"),
            (format!("{VALID}[arena]\nmin = [-1e308, -5.0, 0.0]\nmax = [5.0, 5.0, 6.0]\n"), "±1000 m"),
            (many_gates(65), "at most 64 gates, found 65"),
            (format!("{VALID}# {}\n", "x".repeat(MAX_TRACK_FILE_BYTES)), "more than the 65536"),
        ];
        for (text, field) in cases {
            let message = err(&text);
            assert!(message.starts_with("tracks/bad.toml: "), "{message}");
            assert!(message.contains(field), "expected {field:?} in: {message}");
        }
    }

    #[test]
    fn a_track_of_max_gates_parses_and_one_more_is_refused_naming_the_bound() {
        assert_eq!(parse_track(&many_gates(sim::track::MAX_GATES), Path::new("m.toml")).unwrap().gates.len(), 64);
        let message = err(&many_gates(sim::track::MAX_GATES + 1));
        assert!(message.contains("gate: a track has at most 64 gates"), "{message}");
    }

    #[test]
    fn stacked_gates_like_split_s_are_valid() {
        let text = VALID.replace("[6.0, 3.0, 2.5]", "[0.0, 0.2, 4.36]").replace("yaw_deg = 90.0", "yaw_deg = 180.0");
        assert!(parse_track(&text, Path::new("s.toml")).is_ok());
    }

    #[test]
    fn a_csv_of_gate_poses_imports_to_the_track_it_describes_and_bad_rows_are_named() {
        let figure8 = crate::library_track("Figure8").unwrap().unwrap();
        let rows: Vec<String> =
            figure8.gates.iter().map(|g| format!("{},{},{},{}", g.position.x, g.position.y, g.position.z, g.yaw.to_degrees())).collect();
        let csv = format!("x,y,z,yaw_deg\n# figure eight\n{}\n", rows.join("\n"));
        let imported = track_from_csv("Mine", &csv, Path::new("gates.csv")).unwrap();
        assert_eq!(imported.gates.len(), figure8.gates.len());
        for (a, b) in imported.gates.iter().zip(&figure8.gates) {
            assert!((a.position - b.position).norm() < 1e-9 && (a.yaw - b.yaw).abs() < 1e-9);
        }
        assert_eq!(imported.arena, Arena::default(), "its gates fit SPEC's arena");
        // Back through a track file, the same track.
        let back = parse_track(&track_to_toml(&imported), Path::new("mine.toml")).unwrap();
        assert_eq!(back, imported);
        // A layout larger than SPEC's arena gets one around its gates.
        let hall = track_from_csv("Hall", "0,0,2,0\n30,0,2,180\n30,20,3,180\n0,20,2,0\n", Path::new("hall.csv")).unwrap();
        // (its start, 2 m behind gate 0 at x = 0, sets the low x)
        assert_eq!((hall.arena.min.x, hall.arena.max.x, hall.arena.max.z), (-6.0, 34.0, 6.0));
        let e = track_from_csv("Bad", "1,2,3,0\n4,5,x,0\n", Path::new("bad.csv")).unwrap_err().to_string();
        assert!(e.starts_with("bad.csv: row 2:"), "{e}");
        let e = track_from_csv("Bad", "1,2,3\n", Path::new("bad.csv")).unwrap_err().to_string();
        assert!(e.contains("row 1") && e.contains("x,y,z,yaw_deg"), "{e}");
    }
}
