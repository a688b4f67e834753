//! Track generators (SPEC §7, thesis §2.2.3 and A.1): the informed spline generator and the
//! uniform baseline of the ablation. Seeded and deterministic: one seed, one track.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sim::nalgebra::Vector3;
use sim::track::TrackGeometryError;
use sim::track::{GATE_HALF_OUTER, START_BEHIND_FIRST_GATE};
use sim::{Arena, Gate, Pose, Track};

use crate::spline::{BSplineCurve, SplineError, fit_closed_curve};

/// Parameters of both generators; `Default` is SPEC §7 (thesis Table A.3).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackGenParams {
    /// World bounds B; also the arena of every generated track.
    pub bounds: Arena,
    /// Control points N_c of the informed generator. Default 6.
    pub control_points: usize,
    /// Gates N_g per track. Default 6.
    pub gates: usize,
    /// When set, each track's gate count is drawn uniformly from `gates..=gates_max` (one draw
    /// from the track's seed, before its first attempt): denser tracks beside SPEC's. Default
    /// unset = SPEC §7's fixed N_g, the same tracks bit for bit.
    pub gates_max: Option<usize>,
    /// Spline smoothing factor s. Default 4.0.
    pub smoothing: f64,
    /// Padding δ_b kept from the x and y bounds by control points and gates (m). Default 2.0.
    pub boundary_padding: f64,
    /// Smallest horizontal distance between control points d_min (m). Default 3.0.
    pub min_control_spacing: f64,
    /// Smallest distance between gate centres d_g^min (m). Default 2.0.
    pub min_gate_spacing: f64,
    /// Attempts M before giving up. Default 100.
    pub max_attempts: usize,
}

impl Default for TrackGenParams {
    fn default() -> Self {
        Self {
            bounds: Arena::default(),
            control_points: 6,
            gates: 6,
            gates_max: None,
            smoothing: 4.0,
            boundary_padding: 2.0,
            min_control_spacing: 3.0,
            min_gate_spacing: 2.0,
            max_attempts: 100,
        }
    }
}

/// Which generator.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GeneratorKind {
    /// Spline through sampled control points, gates at equal arc length (the thesis' method).
    #[default]
    Informed,
    /// Gate positions and yaws drawn uniformly (the ablation baseline).
    Uniform,
}

/// No valid track within the attempt budget.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("no valid {kind:?} track from seed {seed} after {attempts} attempts (last rejection: {last_reason})")]
pub struct GenerateError {
    /// Generator used.
    pub kind: GeneratorKind,
    /// Seed given.
    pub seed: u64,
    /// Attempts made.
    pub attempts: usize,
    /// Why the last candidate was rejected.
    pub last_reason: Rejection,
}

/// Why a candidate track (or the parameters themselves) was rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Rejection {
    /// `gates_max` is set below `gates`, so no gate count can be drawn.
    #[error("gates_max ({max}) is below gates ({gates})")]
    GatesMaxBelowGates {
        /// `gates_max` given.
        max: usize,
        /// `gates` given.
        gates: usize,
    },
    /// A gate count outside 2..=[`sim::track::MAX_GATES`].
    #[error("{field} = {value}: a track has 2 to {} gates", sim::track::MAX_GATES)]
    GateCount {
        /// `gates` or `gates_max`.
        field: &'static str,
        /// The count given.
        value: usize,
    },
    /// `max_attempts` is 0.
    #[error("no attempt made (max_attempts is 0)")]
    NoAttempt,
    /// Rejection sampling could not fit the control points into the padded box.
    #[error("could not place {count} control points {spacing} m apart")]
    CrowdedControlPoints {
        /// Control points wanted.
        count: usize,
        /// Their smallest horizontal spacing (m).
        spacing: f64,
    },
    /// The smoothing spline could not be fitted through the control points.
    #[error("spline: {0}")]
    Spline(#[from] SplineError),
    /// Two gate centres are closer than `min_gate_spacing`.
    #[error("gates {first} and {second} are {distance:.2} m apart")]
    GatesTooClose {
        /// Index of the first gate.
        first: usize,
        /// Index of the second gate.
        second: usize,
        /// Their distance (m).
        distance: f64,
    },
    /// A gate centre lies outside the padded x–y box.
    #[error("gate {0} is outside the padded box")]
    GateOutsideBox(usize),
    /// The start pose behind gate 0 lies outside the bounds.
    #[error("the start is outside the bounds")]
    StartOutsideBounds,
    /// The track breaks a track-file rule (e.g. overlapping frames).
    #[error(transparent)]
    Geometry(#[from] TrackGeometryError),
}

/// Why [`TrackGenerator::write_tracks`] stopped.
#[derive(Debug, thiserror::Error)]
pub enum WriteTracksError {
    /// A seed gave no track.
    #[error(transparent)]
    Generate(#[from] GenerateError),
    /// A file or the directory could not be written.
    #[error(transparent)]
    File(#[from] crate::TrackFileError),
}

/// A generated track and how it came about.
#[derive(Clone, Debug, PartialEq)]
pub struct Generated {
    /// The accepted track.
    pub track: Track,
    /// Candidates drawn, the accepted one included.
    pub attempts: usize,
    /// The re-centred control points of the informed generator (empty for the uniform one).
    pub control_points: Vec<Vector3<f64>>,
}

/// A seeded track generator.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct TrackGenerator {
    /// Informed or uniform.
    pub kind: GeneratorKind,
    /// Shared parameters.
    pub params: TrackGenParams,
}

impl TrackGenerator {
    /// Writes the tracks of seeds `first..first + count` into `dir` (created if missing) as
    /// `<generator>-<seed>.toml`, each named so; returns the candidates drawn for them.
    pub fn write_tracks(&self, first: u64, count: usize, dir: &std::path::Path) -> Result<usize, WriteTracksError> {
        std::fs::create_dir_all(dir).map_err(|source| crate::TrackFileError::Io { file: dir.to_path_buf(), source })?;
        let mut attempts = 0;
        for seed in first..first + count as u64 {
            let name = format!("{:?}-{seed}", self.kind).to_lowercase();
            let g = self.generate(seed, &name)?;
            attempts += g.attempts;
            crate::write_track(&g.track, &dir.join(format!("{name}.toml")))?;
        }
        Ok(attempts)
    }

    /// Generates the track of `seed`, named `name`.
    pub fn generate(&self, seed: u64, name: &str) -> Result<Generated, GenerateError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let counts = [("gates", Some(self.params.gates)), ("gates_max", self.params.gates_max)];
        if let Some((field, Some(value))) = counts.into_iter().find(|(_, n)| n.is_some_and(|n| !(2..=sim::track::MAX_GATES).contains(&n))) {
            return Err(GenerateError { kind: self.kind, seed, attempts: 0, last_reason: Rejection::GateCount { field, value } });
        }
        let gates = match self.params.gates_max {
            None => self.params.gates,
            Some(max) if max >= self.params.gates => rng.random_range(self.params.gates..=max),
            Some(max) => {
                let last_reason = Rejection::GatesMaxBelowGates { max, gates: self.params.gates };
                return Err(GenerateError { kind: self.kind, seed, attempts: 0, last_reason });
            }
        };
        let mut last_reason = Rejection::NoAttempt;
        for attempt in 1..=self.params.max_attempts {
            let candidate = match self.kind {
                GeneratorKind::Informed => self.informed_candidate(&mut rng, gates),
                GeneratorKind::Uniform => Ok((self.uniform_candidate(&mut rng, gates), Vec::new())),
            };
            let accepted = candidate.and_then(|(gates, points)| Ok((self.accept(gates, name)?, points)));
            match accepted {
                Ok((track, control_points)) => return Ok(Generated { track, attempts: attempt, control_points }),
                Err(reason) => last_reason = reason,
            }
        }
        Err(GenerateError { kind: self.kind, seed, attempts: self.params.max_attempts, last_reason })
    }

    /// x, y range of the padded box.
    fn padded_xy(&self) -> ([f64; 2], [f64; 2]) {
        let (b, pad) = (&self.params.bounds, self.params.boundary_padding);
        ([b.min.x + pad, b.max.x - pad], [b.min.y + pad, b.max.y - pad])
    }

    /// Allowed gate-centre heights: the whole frame inside the bounds.
    fn gate_z_range(&self) -> [f64; 2] {
        let b = &self.params.bounds;
        [b.min.z + GATE_HALF_OUTER, b.max.z - GATE_HALF_OUTER]
    }

    /// Steps 1–3 of SPEC §7: control points, spline, `gates` gates (with the control points).
    fn informed_candidate(&self, rng: &mut ChaCha8Rng, gates: usize) -> Result<(Vec<Gate>, Vec<Vector3<f64>>), Rejection> {
        let p = &self.params;
        let ([x0, x1], [y0, y1]) = self.padded_xy();
        let (z0, z1) = (p.bounds.min.z, p.bounds.max.z);
        let mut points: Vec<Vector3<f64>> = Vec::with_capacity(p.control_points);
        // Rejection sampling of each point; a crowded box ends the attempt rather than looping.
        let mut draws = 0;
        while points.len() < p.control_points {
            draws += 1;
            if draws > 1000 * p.control_points {
                return Err(Rejection::CrowdedControlPoints { count: p.control_points, spacing: p.min_control_spacing });
            }
            let q = Vector3::new(rng.random_range(x0..=x1), rng.random_range(y0..=y1), rng.random_range(z0..=z1));
            if points.iter().all(|o| (o.xy() - q.xy()).norm() >= p.min_control_spacing) {
                points.push(q);
            }
        }
        let mean = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        let shift = p.bounds.centre() - mean;
        points.iter_mut().for_each(|q| *q += shift);
        let fit = fit_closed_curve(&points, p.smoothing)?;
        Ok((place_gates(&fit.curve, gates, self.gate_z_range()), points))
    }

    /// The baseline: `gates` positions uniform in the padded box (heights as gates allow), yaws uniform.
    fn uniform_candidate(&self, rng: &mut ChaCha8Rng, gates: usize) -> Vec<Gate> {
        let ([x0, x1], [y0, y1]) = self.padded_xy();
        let [z0, z1] = self.gate_z_range();
        (0..gates)
            .map(|_| {
                let position = Vector3::new(rng.random_range(x0..=x1), rng.random_range(y0..=y1), rng.random_range(z0..=z1));
                Gate::new(position, rng.random_range(-std::f64::consts::PI..std::f64::consts::PI))
            })
            .collect()
    }

    /// Steps 4–5: start pose and the constraints C, then the track-file rules (no overlapping
    /// frames), so every generated track is also a valid track file.
    fn accept(&self, gates: Vec<Gate>, name: &str) -> Result<Track, Rejection> {
        let p = &self.params;
        for i in 0..gates.len() {
            for j in i + 1..gates.len() {
                let d = (gates[i].position - gates[j].position).norm();
                if d < p.min_gate_spacing {
                    return Err(Rejection::GatesTooClose { first: i, second: j, distance: d });
                }
            }
        }
        let ([x0, x1], [y0, y1]) = self.padded_xy();
        if let Some(i) = gates.iter().position(|g| !(x0..=x1).contains(&g.position.x) || !(y0..=y1).contains(&g.position.y)) {
            return Err(Rejection::GateOutsideBox(i));
        }
        let g0 = &gates[0];
        let start = Pose { position: g0.position - g0.normal() * START_BEHIND_FIRST_GATE, yaw: g0.yaw };
        if !p.bounds.contains(&start.position) {
            return Err(Rejection::StartOutsideBounds);
        }
        Ok(Track::new(name, gates, Some(start), p.bounds)?)
    }
}

/// `count` gates at equal arc length along a closed curve starting at its first parameter,
/// facing along the tangent (yaw only), heights clamped into `z_range`.
pub fn place_gates(curve: &BSplineCurve, count: usize, z_range: [f64; 2]) -> Vec<Gate> {
    let velocity = curve.derivative();
    curve
        .equal_arc_parameters(count)
        .into_iter()
        .map(|u| {
            let mut position = curve.point(u);
            position.z = position.z.clamp(z_range[0], z_range[1]);
            let tangent = velocity.point(u);
            Gate::new(position, tangent.y.atan2(tangent.x))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_track_and_different_seeds_differ() {
        let g = TrackGenerator::default();
        let a = g.generate(7, "a").unwrap().track;
        assert_eq!(a, g.generate(7, "a").unwrap().track);
        assert_ne!(a.gates, g.generate(8, "a").unwrap().track.gates);
    }

    #[test]
    fn a_gate_range_draws_every_count_in_it_and_unset_keeps_the_spec_tracks() {
        let spec = TrackGenerator::default();
        let params = TrackGenParams { gates_max: Some(8), ..TrackGenParams::default() };
        let ranged = TrackGenerator { kind: GeneratorKind::Informed, params };
        let counts: Vec<usize> = (0..60).map(|seed| ranged.generate(seed, "r").unwrap().track.gates.len()).collect();
        for n in 6..=8 {
            assert!(counts.contains(&n), "no track with {n} gates in {counts:?}");
        }
        assert!(counts.iter().all(|n| (6..=8).contains(n)), "{counts:?}");
        let same = TrackGenParams { gates_max: Some(6), ..TrackGenParams::default() };
        let pinned = TrackGenerator { kind: GeneratorKind::Informed, params: same }.generate(5, "r").unwrap().track;
        assert_eq!(pinned.gates.len(), 6);
        assert_eq!(spec.generate(5, "r").unwrap().track.gates.len(), 6);
        let below = TrackGenParams { gates_max: Some(5), ..TrackGenParams::default() };
        let err = TrackGenerator { kind: GeneratorKind::Uniform, params: below }.generate(1, "x").unwrap_err();
        assert!(err.to_string().contains("gates_max (5) is below gates (6)"), "{err}");
    }

    #[test]
    fn a_gate_count_beyond_the_bound_is_refused_before_anything_is_allocated() {
        for (gates, gates_max, field) in [(1_000_000_000_000, None, "gates"), (0, None, "gates"), (6, Some(1 << 62), "gates_max")] {
            let params = TrackGenParams { gates, gates_max, ..TrackGenParams::default() };
            for kind in [GeneratorKind::Informed, GeneratorKind::Uniform] {
                let err = TrackGenerator { kind, params }.generate(0, "x").unwrap_err();
                assert_eq!(err.attempts, 0);
                assert!(matches!(err.last_reason, Rejection::GateCount { field: f, .. } if f == field), "{err}");
                assert!(err.to_string().contains("a track has 2 to 64 gates"), "{err}");
            }
        }
    }

    #[test]
    fn an_impossible_budget_fails_with_a_clear_error() {
        let params = TrackGenParams { min_gate_spacing: 50.0, max_attempts: 5, ..TrackGenParams::default() };
        let err = TrackGenerator { kind: GeneratorKind::Informed, params }.generate(3, "x").unwrap_err();
        assert_eq!(err.attempts, 5);
        let text = err.to_string();
        assert!(text.contains("seed 3") && text.contains("5 attempts") && text.contains("apart"), "{text}");
    }
}
