//! Track families the generalist never trained on (SPEC §13's project decisions): more gates
//! than training ever draws, steep tracks in a tall arena, tight arenas, and hand-made layouts
//! in the style of real races. Generated families draw from seeds of the held-out range, apart
//! from the validation and test sets' tracks.

use std::path::Path;
use std::str::FromStr;

use sim::Track;
use sim::nalgebra::Vector3;

use crate::track_file::{TrackFileError, parse_track};
use crate::{GenerateError, TrackGenParams, TrackGenerator};

/// First seed of the generated families (inside the held-out range, past the test set's).
pub const OOD_SEED: u64 = 9_500_000;

/// The hand-made layouts, compiled in (the files under `tracks/ood/`).
const RACES: &[(&str, &str)] = &[
    ("tracks/ood/dive.toml", include_str!("../../tracks/ood/dive.toml")),
    ("tracks/ood/crossing.toml", include_str!("../../tracks/ood/crossing.toml")),
    ("tracks/ood/dragstrip.toml", include_str!("../../tracks/ood/dragstrip.toml")),
    ("tracks/ood/chicane.toml", include_str!("../../tracks/ood/chicane.toml")),
];

/// An out-of-distribution family.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Family {
    /// 8 to 12 gates a track (training: 6).
    ManyGates,
    /// A 14 m tall arena (training: 6 m): altitude changes of up to ~12 m between gates.
    Steep,
    /// A 14 × 14 m floor (training: 24 × 24 m).
    Tight,
    /// Hand-made layouts in the style of real races: a dive, a stacked crossing, a drag strip,
    /// a chicane.
    Races,
}

impl Family {
    /// Every family, in table order.
    pub const ALL: [Family; 4] = [Family::ManyGates, Family::Steep, Family::Tight, Family::Races];

    /// Its name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Family::ManyGates => "many-gates",
            Family::Steep => "steep",
            Family::Tight => "tight",
            Family::Races => "races",
        }
    }

    /// The generator of a generated family (`None` for the hand-made one).
    pub fn generator(self) -> Option<TrackGenerator> {
        let params = TrackGenParams::default();
        let params = match self {
            Family::ManyGates => TrackGenParams { gates: 8, gates_max: Some(12), ..params },
            Family::Steep => TrackGenParams { bounds: sim::Arena { max: Vector3::new(12.0, 12.0, 14.0), ..params.bounds }, ..params },
            Family::Tight => {
                let bounds = sim::Arena { min: Vector3::new(-7.0, -7.0, 0.0), max: Vector3::new(7.0, 7.0, 6.0) };
                TrackGenParams { bounds, ..params }
            }
            Family::Races => return None,
        };
        Some(TrackGenerator { params, ..TrackGenerator::default() })
    }
}

impl FromStr for Family {
    type Err = String;

    fn from_str(name: &str) -> Result<Self, String> {
        Family::ALL.into_iter().find(|f| f.name() == name).ok_or_else(|| {
            let names: Vec<&str> = Family::ALL.iter().map(|f| f.name()).collect();
            format!("{name:?} is not a family ({})", names.join(", "))
        })
    }
}

/// Why a family could not be built.
#[derive(Debug, thiserror::Error)]
pub enum OodError {
    /// A generated member failed.
    #[error(transparent)]
    Generate(#[from] GenerateError),
    /// A hand-made layout did not parse.
    #[error(transparent)]
    File(#[from] TrackFileError),
}

/// The family's tracks: `count` generated ones from [`OOD_SEED`] on, or the hand-made layouts
/// (all of them, whatever `count`).
pub fn family_tracks(family: Family, count: usize) -> Result<Vec<Track>, OodError> {
    let Some(generator) = family.generator() else {
        return Ok(RACES.iter().map(|(file, text)| parse_track(text, Path::new(file))).collect::<Result<_, _>>()?);
    };
    let seeds = OOD_SEED..OOD_SEED + count as u64;
    Ok(seeds.map(|seed| generator.generate(seed, &format!("{}-{seed}", family.name())).map(|g| g.track)).collect::<Result<_, _>>()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_family_builds_and_differs_from_training_as_named() {
        let many = family_tracks(Family::ManyGates, 4).unwrap();
        assert!(many.iter().all(|t| (8..=12).contains(&t.gates.len())));
        let steep = family_tracks(Family::Steep, 4).unwrap();
        assert!(steep.iter().any(|t| t.gates.iter().any(|g| g.position.z > 6.0)), "gates above training's ceiling");
        let tight = family_tracks(Family::Tight, 4).unwrap();
        assert!(tight.iter().all(|t| t.gates.iter().all(|g| g.position.x.abs() <= 7.0 && g.position.y.abs() <= 7.0)));
        let races = family_tracks(Family::Races, 0).unwrap();
        assert_eq!(races.iter().map(|t| t.name.as_str()).collect::<Vec<_>>(), ["Dive", "Crossing", "DragStrip", "Chicane"]);
        assert!(crate::track_sets::is_held_out(OOD_SEED) && OOD_SEED >= crate::track_sets::TEST_SEED + 1000);
        assert_eq!("steep".parse::<Family>(), Ok(Family::Steep));
        assert!("hilly".parse::<Family>().unwrap_err().contains("many-gates"));
    }
}
