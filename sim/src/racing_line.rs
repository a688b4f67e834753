//! The racing line: a closed cubic Hermite path through a track's gate centres (tangent = gate
//! normal), kept clear of the frames and the arena walls (through a detour waypoint where one
//! segment a leg cannot), with a speed profile limited by lateral and longitudinal acceleration.
//! The reference pilot flies it ([`crate::reference_pilot`]); the race environment reads it for the line
//! observation ([`RacingLine`]).

use nalgebra::Vector3;

use crate::track::{Arena, Gate, Track};

/// The limits a path's shape and speed profile obey (the path half of the pilot's tuning,
/// [`crate::PilotParams`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathLimits {
    /// Top speed on straights (m/s).
    pub max_speed: f64,
    /// Lateral acceleration allowed in turns (m/s²).
    pub max_lateral_accel: f64,
    /// Longitudinal acceleration and braking allowed (m/s²).
    pub max_longitudinal_accel: f64,
    /// Shortest Hermite tangent (m): gives tight reversals room to turn.
    pub min_tangent: f64,
}

impl Default for PathLimits {
    /// The default pilot's limits: the racing line every environment observes is shaped by them.
    fn default() -> Self {
        Self { max_speed: 9.0, max_lateral_accel: 10.0, max_longitudinal_accel: 7.0, min_tangent: 5.0 }
    }
}

/// One sample of a pilot path.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PathPoint {
    pub(crate) position: Vector3<f64>,
    pub(crate) tangent: Vector3<f64>,
    /// Curvature vector d²p/ds² (1/m, points to the centre of the turn).
    pub(crate) curvature: Vector3<f64>,
    /// Planned speed (m/s).
    pub(crate) speed: f64,
}

/// A sampled reference path: the closed loop through the gates, or an open lead-in.
#[derive(Clone, Debug)]
pub(crate) struct PilotPath {
    pub(crate) points: Vec<PathPoint>,
    closed: bool,
}

/// Samples per Hermite segment.
const SAMPLES_PER_SEGMENT: usize = 200;
/// Tangent lengths tried for a segment, as multiples of its chord, in order of preference.
const TANGENT_SCALES: [f64; 8] = [1.0, 0.75, 1.25, 1.5, 0.5, 2.0, 2.5, 3.0];
/// Slowest turn-limited speed a segment may demand before a wider shape is preferred (m/s).
const MIN_TURN_SPEED: f64 = 2.5;
/// Clearance the path keeps from every gate frame and the arena walls (m).
const FRAME_CLEARANCE: f64 = 0.45;

impl PilotPath {
    /// The closed loop through every gate centre along the gate normals.
    pub(crate) fn through_gates(track: &Track, p: &PathLimits) -> Self {
        let mut points = Vec::with_capacity(track.gates.len() * SAMPLES_PER_SEGMENT);
        for (i, a) in track.gates.iter().enumerate() {
            let b = &track.gates[track.next_index(i)];
            points.extend(clear_segment(track, (&a.position, &a.normal()), (&b.position, &b.normal()), p.min_tangent, p));
        }
        Self::from_points(points, true, p)
    }

    /// An open path from `from` (leaving along `heading`) through gate 0 and 2 m beyond, at
    /// `end_speed` from gate 0 on.
    pub(crate) fn lead_in(track: &Track, from: &Vector3<f64>, heading: &Vector3<f64>, end_speed: f64, p: &PathLimits) -> Self {
        let g0 = &track.gates[0];
        let (centre, normal) = (g0.position, g0.normal());
        let beyond = centre + normal * 2.0;
        let mut points = clear_segment(track, (from, heading), (&centre, &normal), 1.0, p);
        points.extend(hermite_samples((&centre, &normal), (&beyond, &normal), 2.0, SAMPLES_PER_SEGMENT / 4));
        // The start may be offset sideways from the gate by most of its opening: take the
        // resulting S-bend gently, since overshooting it means the frame.
        let gentle = PathLimits { max_lateral_accel: p.max_lateral_accel / 2.0, ..*p };
        let mut path = Self::from_points(points, false, &gentle);
        path.cap_speed_from(path.points.len() - SAMPLES_PER_SEGMENT / 4, end_speed, p);
        path
    }

    fn from_points(points: Vec<PathPoint>, closed: bool, p: &PathLimits) -> Self {
        let mut path = Self { points, closed };
        for q in &mut path.points {
            let turn_limit = (p.max_lateral_accel / q.curvature.norm().max(1e-9)).sqrt();
            q.speed = p.max_speed.min(turn_limit);
        }
        path.limit_acceleration(p);
        path
    }

    /// Caps the speed from sample `from` on and re-plans braking before it.
    fn cap_speed_from(&mut self, from: usize, cap: f64, p: &PathLimits) {
        for q in &mut self.points[from..] {
            q.speed = q.speed.min(cap);
        }
        self.limit_acceleration(p);
    }

    /// Lowers speeds so that forward and backward they change no faster than the longitudinal
    /// limit allows (twice around a closed loop so its seam settles). Only ever lowers.
    fn limit_acceleration(&mut self, p: &PathLimits) {
        let n = self.points.len();
        let limit = |v: f64, ds: f64| (v * v + 2.0 * p.max_longitudinal_accel * ds).sqrt();
        let (passes, pairs) = if self.closed { (2, n) } else { (1, n - 1) };
        for _ in 0..passes {
            for i in 0..pairs {
                let (a, b) = (i, (i + 1) % n);
                let ds = (self.points[b].position - self.points[a].position).norm();
                self.points[b].speed = self.points[b].speed.min(limit(self.points[a].speed, ds));
            }
            for i in (0..pairs).rev() {
                let (a, b) = (i, (i + 1) % n);
                let ds = (self.points[b].position - self.points[a].position).norm();
                self.points[a].speed = self.points[a].speed.min(limit(self.points[b].speed, ds));
            }
        }
    }

    /// The sample after `i`, or `None` at the end of an open path.
    fn next(&self, i: usize) -> Option<usize> {
        match (i + 1 < self.points.len(), self.closed) {
            (true, _) => Some(i + 1),
            (false, true) => Some(0),
            (false, false) => None,
        }
    }

    /// Index `distance` metres of arc after `from` (the last sample of an open path at most).
    pub(crate) fn ahead(&self, from: usize, distance: f64) -> usize {
        let (mut i, mut travelled) = (from, 0.0);
        while let Some(next) = self.next(i) {
            travelled += (self.points[next].position - self.points[i].position).norm();
            if travelled > distance || next == from {
                break;
            }
            i = next;
        }
        i
    }

    /// Nearest sample to `p` from a few samples behind `from` to `distance` metres ahead.
    pub(crate) fn nearest_ahead(&self, p: &Vector3<f64>, from: usize, distance: f64) -> usize {
        let n = self.points.len();
        let mut i = if self.closed { (from + n - 5) % n } else { from.saturating_sub(5) };
        let end = self.ahead(from, distance);
        let mut best = (f64::INFINITY, from);
        loop {
            let d = (self.points[i].position - p).norm_squared();
            if d < best.0 {
                best = (d, i);
            }
            if i == end {
                return best.1;
            }
            i = self.next(i).unwrap_or(end);
        }
    }
}

/// Samples of the cubic Hermite curve between two (position, unit direction) ends with
/// tangent length `scale`.
fn hermite_samples(
    (p0, d0): (&Vector3<f64>, &Vector3<f64>),
    (p1, d1): (&Vector3<f64>, &Vector3<f64>),
    scale: f64,
    samples: usize,
) -> Vec<PathPoint> {
    let (m0, m1) = (d0 * scale, d1 * scale);
    (0..samples)
        .map(|k| {
            let u = k as f64 / samples as f64;
            let (u2, u3) = (u * u, u * u * u);
            let position = p0 * (2.0 * u3 - 3.0 * u2 + 1.0) + m0 * (u3 - 2.0 * u2 + u) + p1 * (-2.0 * u3 + 3.0 * u2) + m1 * (u3 - u2);
            let first =
                p0 * (6.0 * u2 - 6.0 * u) + m0 * (3.0 * u2 - 4.0 * u + 1.0) + p1 * (-6.0 * u2 + 6.0 * u) + m1 * (3.0 * u2 - 2.0 * u);
            let second = p0 * (12.0 * u - 6.0) + m0 * (6.0 * u - 4.0) + p1 * (-12.0 * u + 6.0) + m1 * (6.0 * u - 2.0);
            // A zero-length curve (a gate to itself) still needs a direction.
            let speed = first.norm();
            let tangent = if speed > 1e-12 { first / speed } else { *d0 };
            let curvature = if speed > 1e-12 { (second - tangent * second.dot(&tangent)) / (speed * speed) } else { Vector3::zeros() };
            PathPoint { position, tangent, curvature, speed: 0.0 }
        })
        .collect()
}

/// The way from one (position, unit direction) end to the next: the Hermite segment with the
/// first tangent length (in [`TANGENT_SCALES`] order) that stays clear of every gate frame and
/// inside the arena without a near-cusp turn; failing that, the one with the fewest samples too
/// close, then without a cusp. When no single segment keeps clear of the frames, two segments
/// through a detour waypoint ([`detour_waypoints`]; each with half the shortest tangent) replace
/// it if they come closer to clear; either way the leg has [`SAMPLES_PER_SEGMENT`] samples.
fn clear_segment(
    track: &Track,
    from: (&Vector3<f64>, &Vector3<f64>),
    to: (&Vector3<f64>, &Vector3<f64>),
    min_tangent: f64,
    p: &PathLimits,
) -> Vec<PathPoint> {
    let margin = Vector3::repeat(FRAME_CLEARANCE);
    let inside = Arena { min: track.arena.min + margin, max: track.arena.max - margin };
    let touches_frame = |q: &PathPoint| track.gates.iter().any(|g| g.frame_touches_sphere(&q.position, FRAME_CLEARANCE));
    let too_close = |q: &PathPoint| !inside.contains(&q.position) || touches_frame(q);
    // A turn so tight that the drone must nearly stop in it.
    let cusp = |q: &PathPoint| p.max_lateral_accel / q.curvature.norm().max(1e-9) < MIN_TURN_SPEED.powi(2);
    let score = |points: &[PathPoint]| (points.iter().filter(|q| too_close(q)).count(), points.iter().any(cusp));
    let (direct_score, direct) = best_hermite(from, to, min_tangent, SAMPLES_PER_SEGMENT, &score);
    // Only a frame is gone round; a leg near a wall or the floor keeps its single segment.
    if !direct.iter().any(touches_frame) {
        return direct;
    }
    // A short piece with a long tangent can run back along itself, where the curvature (across
    // the line) reads zero: count that as a cusp.
    let turns_back = |points: &[PathPoint]| points.windows(2).any(|q| q[0].tangent.dot(&q[1].tangent) < 0.0);
    let piece_score = |points: &[PathPoint]| {
        let (close, cusp) = score(points);
        (close, cusp || turns_back(points))
    };
    // Where the direct segment comes closest to a frame: the detour's anchor.
    let (anchor, frame_point) = closest_frame_approach(direct.iter().map(|q| &q.position), &track.gates)
        .map_or((direct[0], direct[0].position), |a| (direct[a.sample], a.frame_point));
    let half = SAMPLES_PER_SEGMENT / 2;
    detour_waypoints(from, to, &anchor, &frame_point)
        .into_iter()
        .map(|(w, d)| {
            let (first_score, mut points) = best_hermite(from, (&w, &d), min_tangent / 2.0, half, &piece_score);
            let (second_score, second) = best_hermite((&w, &d), to, min_tangent / 2.0, SAMPLES_PER_SEGMENT - half, &piece_score);
            points.extend(second);
            let length: f64 = points.windows(2).map(|q| (q[1].position - q[0].position).norm()).sum();
            ((first_score.0 + second_score.0, first_score.1 || second_score.1, length), points)
        })
        .filter(|((close, _, _), _)| *close < direct_score.0)
        .min_by(|(a, _), (b, _)| (a.0, a.1).cmp(&(b.0, b.1)).then(a.2.total_cmp(&b.2)))
        .map_or(direct, |(_, points)| points)
}

/// The Hermite segment of `samples` samples with the first tangent length (in
/// [`TANGENT_SCALES`] order) whose `score` is least, with that score.
#[allow(clippy::expect_used, reason = "TANGENT_SCALES is a non-empty constant")]
fn best_hermite(
    from: (&Vector3<f64>, &Vector3<f64>),
    to: (&Vector3<f64>, &Vector3<f64>),
    min_tangent: f64,
    samples: usize,
    score: &impl Fn(&[PathPoint]) -> (usize, bool),
) -> ((usize, bool), Vec<PathPoint>) {
    let chord = (to.0 - from.0).norm().max(min_tangent);
    let mut best: Option<((usize, bool), Vec<PathPoint>)> = None;
    for s in TANGENT_SCALES {
        let points = hermite_samples(from, to, s * chord, samples);
        let key = score(&points);
        // Clear and without a cusp cannot be beaten: the remaining lengths need not be tried.
        if key == (0, false) {
            return (key, points);
        }
        if best.as_ref().is_none_or(|(least, _)| key < *least) {
            best = Some((key, points));
        }
    }
    best.expect("at least one tangent scale")
}

/// Waypoints (position, unit direction) a leg from `from` to `to` may detour through when its
/// direct segment runs into a frame at `frame_point` near its sample `anchor`: points beside the
/// frame, round it in the plane across the leg, flown in the leg's direction there; and points
/// straight behind the gate ahead or beyond the gate behind, flown along their normals — the
/// way round a gate approached from its side.
fn detour_waypoints(
    from: (&Vector3<f64>, &Vector3<f64>),
    to: (&Vector3<f64>, &Vector3<f64>),
    anchor: &PathPoint,
    frame_point: &Vector3<f64>,
) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let along = anchor.tangent;
    // A basis across the leg built from the vertical, so a track and its mirror image get
    // mirror-image candidates.
    let up = {
        let u = Vector3::z() - along * along.z;
        if u.norm() > 1e-6 { u.normalize() } else { Vector3::x() }
    };
    let side = along.cross(&up);
    // Eight directions 45° apart, exact, so that mirror-image candidates are exact mirror images.
    let r = std::f64::consts::FRAC_1_SQRT_2;
    let round = [(1.0, 0.0), (r, r), (0.0, 1.0), (-r, r), (-1.0, 0.0), (-r, -r), (0.0, -1.0), (r, -r)];
    let mut waypoints = Vec::new();
    for radius in DETOUR_RADII {
        for (cos, sin) in round {
            waypoints.push((frame_point + (up * cos + side * sin) * radius, along));
        }
    }
    for distance in DETOUR_GATE_DISTANCES {
        waypoints.push((to.0 - to.1 * distance, *to.1));
        waypoints.push((from.0 + from.1 * distance, *from.1));
    }
    waypoints
}

/// Where a sequence of positions comes closest to a gate frame ([`closest_frame_approach`]).
struct FrameApproach {
    /// Index of the position.
    sample: usize,
    /// Index of the gate whose frame it is.
    gate: usize,
    /// The frame's point nearest to that position.
    frame_point: Vector3<f64>,
    /// Their distance (m).
    distance: f64,
}

/// The first of `positions` that comes closest to the frame of any of `gates`; `None` when there
/// are no positions or no gates.
fn closest_frame_approach<'a>(positions: impl Iterator<Item = &'a Vector3<f64>>, gates: &[Gate]) -> Option<FrameApproach> {
    let mut nearest: Option<FrameApproach> = None;
    for (sample, position) in positions.enumerate() {
        for (gate, g) in gates.iter().enumerate() {
            let frame_point = g.nearest_frame_point(position);
            let distance = (frame_point - position).norm();
            if nearest.as_ref().is_none_or(|n| distance < n.distance) {
                nearest = Some(FrameApproach { sample, gate, frame_point, distance });
            }
        }
    }
    nearest
}

/// How far from the frame a detour waypoint beside it is placed (m).
const DETOUR_RADII: [f64; 4] = [1.0, 1.5, 2.0, 3.0];
/// How far behind the gate ahead, or beyond the gate behind, a detour waypoint is placed (m).
const DETOUR_GATE_DISTANCES: [f64; 3] = [1.5, 2.5, 4.0];

/// A sample of the reference pilot's closed racing line with the gate it leads to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinePoint {
    /// Position (m).
    pub position: Vector3<f64>,
    /// Unit direction of travel.
    pub direction: Vector3<f64>,
    /// The default pilot's planned speed here (m/s).
    pub speed: f64,
    /// The next gate along the line.
    pub target: usize,
}

/// Where a racing line comes closest to a gate frame ([`RacingLine::frame_clearance`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameClearance {
    /// Distance from the line's nearest sample to the frame (m); 0 where the line runs through it.
    pub distance: f64,
    /// The gate whose frame it is.
    pub gate: usize,
    /// The gate the line is flying to there.
    pub target: usize,
}

/// The default-tuned reference pilot's closed racing line through a track's gates, sample by
/// sample (each leg from gate i to gate i + 1 has the same number of samples), with its arc
/// length: what the line observation reads ([`crate::ObservationLayout::line_points`]).
#[derive(Clone, Debug)]
pub struct RacingLine {
    points: Vec<LinePoint>,
    /// Arc length from sample 0 to each sample (m).
    arc: Vec<f64>,
    /// Length of the closed loop (m).
    length: f64,
}

impl RacingLine {
    /// The line the default-tuned pilot would fly round `track`.
    pub fn new(track: &Track) -> Self {
        let path = PilotPath::through_gates(track, &PathLimits::default());
        let points: Vec<LinePoint> = path
            .points
            .iter()
            .enumerate()
            .map(|(k, q)| LinePoint {
                position: q.position,
                direction: q.tangent,
                speed: q.speed,
                target: track.next_index(k / SAMPLES_PER_SEGMENT),
            })
            .collect();
        let mut arc = Vec::with_capacity(points.len());
        let mut length = 0.0;
        for (k, q) in points.iter().enumerate() {
            arc.push(length);
            length += (points[(k + 1) % points.len()].position - q.position).norm();
        }
        Self { points, arc, length }
    }

    /// Its samples in racing order, starting at gate 0.
    pub fn points(&self) -> &[LinePoint] {
        &self.points
    }

    /// The line's closest approach to the frame of any of `gates`. The line goes through each
    /// gate it races, so this is at most the opening's half-width; the planner keeps 0.45 m where
    /// it can, and policies that read the line fly few tracks where it comes within ~0.2 m of a
    /// frame (docs/notebook/generalist.md).
    pub fn frame_clearance(&self, gates: &[Gate]) -> FrameClearance {
        closest_frame_approach(self.points.iter().map(|p| &p.position), gates).map_or(
            FrameClearance { distance: f64::INFINITY, gate: 0, target: 0 },
            |a| FrameClearance { distance: a.distance, gate: a.gate, target: self.points[a.sample].target },
        )
    }

    /// Index of the sample nearest to `p` on the leg that leads into gate `target`.
    ///
    /// Searching one leg only keeps the answer on the part of the line the drone is racing,
    /// where the line crosses itself or passes close to an earlier leg.
    pub fn nearest_on_leg(&self, p: &Vector3<f64>, target: usize) -> usize {
        let legs = self.points.len() / SAMPLES_PER_SEGMENT;
        let first = (target + legs - 1) % legs * SAMPLES_PER_SEGMENT;
        (first..first + SAMPLES_PER_SEGMENT)
            .map(|k| ((self.points[k].position - p).norm_squared(), k))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(first, |(_, k)| k)
    }

    /// The point `distance` metres of arc after sample `from`, round the closed loop
    /// (interpolated between samples).
    pub fn ahead(&self, from: usize, distance: f64) -> Vector3<f64> {
        let s = (self.arc[from] + distance).rem_euclid(self.length);
        let k = self.arc.partition_point(|&a| a <= s).saturating_sub(1);
        let next = (k + 1) % self.points.len();
        let span = if next == 0 { self.length - self.arc[k] } else { self.arc[next] - self.arc[k] };
        let t = if span > 0.0 { (s - self.arc[k]) / span } else { 0.0 };
        self.points[k].position.lerp(&self.points[next].position, t)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::sync::Arc;

    /// A four-gate oval (the pilot's tests fly it too).
    pub(crate) fn oval() -> Arc<Track> {
        let g = |x, y, yaw_deg: f64| Gate::new(Vector3::new(x, y, 2.5), yaw_deg.to_radians());
        Arc::new(
            Track::new("oval", vec![g(0.0, -6.0, 0.0), g(9.0, 0.0, 90.0), g(0.0, 6.0, 180.0), g(-9.0, 0.0, -90.0)], None, Arena::default())
                .unwrap(),
        )
    }

    /// Through its own gates' openings the line keeps clear of their frames; a gate whose bar
    /// lies on the line is found at distance 0, and named.
    #[test]
    fn frame_clearance_finds_a_frame_on_the_line() {
        let track = oval();
        let line = RacingLine::new(&track);
        let own = line.frame_clearance(&track.gates);
        assert!(own.distance > 0.3 && own.distance <= 0.75 + 1e-9, "{own:?}");
        // A fifth gate beside the line's sample 100, shifted so that its nearest bar is on it.
        let on_line = line.points()[100].position;
        let centred = Gate::new(on_line, 0.3);
        let shift = centred.nearest_frame_point(&on_line) - on_line;
        let mut gates = track.gates.clone();
        gates.push(Gate::new(on_line - shift, 0.3));
        let hit = line.frame_clearance(&gates);
        assert!(hit.distance < 1e-9 && hit.gate == 4 && hit.target == line.points()[100].target, "{hit:?}");
    }

    /// Gate 1 of this generated test track (test-9000026) lies beside the way from gate 0 and
    /// must be entered from its far side: no single Hermite segment into it keeps clear of its
    /// frame. The line detours through a waypoint, keeps the planner's clearance from every
    /// frame, and still passes each gate centre along its normal with a leg's samples per leg.
    #[test]
    fn a_leg_no_single_segment_can_clear_detours_round_the_frame() {
        let g = |x, y, z, yaw_deg: f64| Gate::new(Vector3::new(x, y, z), yaw_deg.to_radians());
        let gates = vec![
            g(1.0427228129891275, -2.300954824440629, 3.5374120404904597, 37.596926880012326),
            g(3.4852791371524816, 0.28602631151845376, 2.6005356160013684, -97.33234907622831),
            g(4.777112074287759, -5.894984567536946, 5.0, 62.83177486810378),
            g(7.238632533763643, 4.327465080342394, 3.1204055151257424, 94.82402516651238),
            g(-1.4046256275530424, 6.199639128457562, 1.1071710862863182, -154.4652069798395),
            g(-8.70858514856067, -1.3303382918747704, 2.532738758941459, -80.07786576951582),
        ];
        let track = Track::new("test-9000026", gates, None, Arena::default()).unwrap();
        let (a, b) = (&track.gates[0], &track.gates[1]);
        let touching = |points: &[PathPoint]| {
            let close = points.iter().filter(|q| track.gates.iter().any(|g| g.frame_touches_sphere(&q.position, FRAME_CLEARANCE)));
            (close.count(), false)
        };
        let ((direct, _), _) = best_hermite(
            (&a.position, &a.normal()),
            (&b.position, &b.normal()),
            PathLimits::default().min_tangent,
            SAMPLES_PER_SEGMENT,
            &touching,
        );
        assert!(direct > 0, "a single segment clears this leg: the fixture no longer needs a detour");
        let line = RacingLine::new(&track);
        let clearance = line.frame_clearance(&track.gates);
        assert!(clearance.distance >= FRAME_CLEARANCE, "{clearance:?}");
        assert_eq!(line.points().len(), track.gates.len() * SAMPLES_PER_SEGMENT);
        for (i, gate) in track.gates.iter().enumerate() {
            let q = line.points()[i * SAMPLES_PER_SEGMENT];
            assert!((q.position - gate.position).norm() < 1e-12 && (q.direction - gate.normal()).norm() < 1e-12, "gate {i}");
        }
        // The track's mirror image (y → −y) gets the mirror image of the line, detour included.
        let reflect = |v: &Vector3<f64>| Vector3::new(v.x, -v.y, v.z);
        let mirrored =
            Track::new("mirrored", track.gates.iter().map(|g| Gate::new(reflect(&g.position), -g.yaw)).collect(), None, Arena::default())
                .unwrap();
        for (q, m) in line.points().iter().zip(RacingLine::new(&mirrored).points()) {
            assert!((reflect(&q.position) - m.position).norm() < 1e-9, "{q:?} against {m:?}");
        }
    }

    #[test]
    fn hermite_path_passes_through_every_gate_along_its_normal() {
        let track = oval();
        let path = PilotPath::through_gates(&track, &PathLimits::default());
        for (i, g) in track.gates.iter().enumerate() {
            let q = path.points[i * SAMPLES_PER_SEGMENT];
            assert!((q.position - g.position).norm() < 1e-12);
            assert!((q.tangent - g.normal()).norm() < 1e-12);
        }
        assert!(path.points.iter().all(|q| q.speed > 0.5 && q.speed <= 9.0));
    }

    #[test]
    fn the_racing_line_is_searched_on_the_target_leg_and_walked_by_arc_length() {
        let track = oval();
        let line = RacingLine::new(&track);
        let legs = track.gates.len();
        assert_eq!(line.points().len(), legs * SAMPLES_PER_SEGMENT);
        for target in 0..legs {
            // A point on the leg into `target` is found there, and nowhere else.
            let k = (target + legs - 1) % legs * SAMPLES_PER_SEGMENT + SAMPLES_PER_SEGMENT / 3;
            let p = line.points()[k].position + Vector3::new(0.0, 0.0, 0.2);
            assert_eq!(line.nearest_on_leg(&p, target), k);
            assert_eq!(line.points()[k].target, target);
            // Searching another leg answers on that leg.
            let other = track.next_index(target);
            assert_eq!(line.points()[line.nearest_on_leg(&p, other)].target, other);
        }
        // Walking ahead: zero metres is the sample itself, a whole loop comes back to it, and a
        // short step lands at that distance (chord ≈ arc on a smooth line).
        for k in [0, 57, line.points().len() - 1] {
            let q = line.points()[k].position;
            assert!((line.ahead(k, 0.0) - q).norm() < 1e-9);
            assert!((line.ahead(k, line.length) - q).norm() < 1e-6);
            let step = (line.ahead(k, 0.5) - q).norm();
            assert!((step - 0.5).abs() < 0.01, "0.5 m of arc from sample {k} is {step} m away");
        }
    }
}
