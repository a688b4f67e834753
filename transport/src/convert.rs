//! Tracks between `sim::Track` and `dronerace.v1.Track`; an incoming track is checked by the
//! same rules as a track file.

use sim::nalgebra::Vector3;
use sim::{Arena, Gate, Pose, Track};

use proto::v1;

fn vec3(v: &Vector3<f64>) -> v1::Vec3 {
    v1::Vec3 { x: v.x, y: v.y, z: v.z }
}

/// A track message that is not a valid track.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TrackMessageError {
    /// A required field is absent (e.g. `track.gates[1].position`).
    #[error("{0} is missing")]
    Missing(String),
    /// The values break a rule of SPEC §6, as a track file's would.
    #[error("track {name:?}: {source}")]
    Invalid {
        /// The track's name.
        name: String,
        /// The rule broken, naming the field.
        source: sim::track::TrackGeometryError,
    },
}

fn vector(v: Option<&v1::Vec3>, field: &str) -> Result<Vector3<f64>, TrackMessageError> {
    let v = v.ok_or_else(|| TrackMessageError::Missing(field.to_owned()))?;
    Ok(Vector3::new(v.x, v.y, v.z))
}

/// The message form of a track.
pub fn track_to_proto(track: &Track) -> v1::Track {
    v1::Track {
        name: track.name.clone(),
        gates: track.gates.iter().map(|g| v1::Gate { position: Some(vec3(&g.position)), yaw: g.yaw }).collect(),
        start_position: Some(vec3(&track.start.position)),
        start_yaw: track.start.yaw,
        arena_min: Some(vec3(&track.arena.min)),
        arena_max: Some(vec3(&track.arena.max)),
    }
}

/// A track from its message, validated (finite numbers, gates inside the arena, …); the error
/// names the offending field.
pub fn track_from_proto(track: &v1::Track) -> Result<Track, TrackMessageError> {
    let gates = track
        .gates
        .iter()
        .enumerate()
        .map(|(i, g)| Ok(Gate::new(vector(g.position.as_ref(), &format!("track.gates[{i}].position"))?, g.yaw)))
        .collect::<Result<Vec<_>, _>>()?;
    let start = Pose { position: vector(track.start_position.as_ref(), "track.start_position")?, yaw: track.start_yaw };
    let arena =
        Arena { min: vector(track.arena_min.as_ref(), "track.arena_min")?, max: vector(track.arena_max.as_ref(), "track.arena_max")? };
    Track::new(track.name.clone(), gates, Some(start), arena)
        .map_err(|source| TrackMessageError::Invalid { name: track.name.clone(), source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn library_tracks_round_trip_and_broken_ones_are_named() {
        let figure8 = sim::Track::new(
            "two",
            vec![Gate::new(Vector3::new(-3.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(3.0, 0.0, 2.0), std::f64::consts::PI)],
            None,
            Arena::default(),
        )
        .unwrap();
        let message = track_to_proto(&figure8);
        assert_eq!(track_from_proto(&message).unwrap(), figure8);
        let mut broken = message.clone();
        broken.gates[1].position = None;
        assert_eq!(track_from_proto(&broken).unwrap_err(), TrackMessageError::Missing("track.gates[1].position".into()));
        let mut outside = message;
        outside.gates[0].position.as_mut().unwrap().x = f64::NAN;
        let invalid = track_from_proto(&outside).unwrap_err();
        assert!(matches!(&invalid, TrackMessageError::Invalid { source, .. } if source.field.starts_with("gate[0]")), "{invalid}");
    }
}
