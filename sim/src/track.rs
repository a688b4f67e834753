//! Racetracks: gates, start pose and arena (SPEC §4, §6, §12.2–§12.3, §12.11).

use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Half width of the square gate opening, w_g (m).
pub const GATE_HALF_OPENING: f64 = 0.75;
/// Half of the outer gate size, opening plus frame bar (m).
pub const GATE_HALF_OUTER: f64 = 1.0;
/// Half of the gate depth along its normal (m).
pub const GATE_HALF_DEPTH: f64 = 0.05;
/// Distance of the default start behind gate 0 (m, thesis A.1).
pub const START_BEHIND_FIRST_GATE: f64 = 2.0;
/// Most gates a track may have; every parser, generator and entry point refuses more. Real races
/// have 6–20; the bound keeps the racing line's O(gates²) construction to milliseconds, so a
/// track from outside (a `RaceStart`, a file, Python) cannot buy seconds of work.
pub const MAX_GATES: usize = 64;
/// Largest coordinate magnitude of anything on a track, arena bounds included (m): a hall 2 km
/// across. Beyond it distances lose the precision the observation needs, and a hostile
/// coordinate of 1e308 would make observations infinite.
pub const MAX_COORDINATE: f64 = 1000.0;

/// Inner-opening corners in gate-local (y, z), in the order observations use (SPEC §4).
pub const GATE_CORNERS_LOCAL: [[f64; 2]; 4] = [
    [GATE_HALF_OPENING, GATE_HALF_OPENING],
    [-GATE_HALF_OPENING, GATE_HALF_OPENING],
    [-GATE_HALF_OPENING, -GATE_HALF_OPENING],
    [GATE_HALF_OPENING, -GATE_HALF_OPENING],
];

/// The four solid bars of a gate frame as gate-local boxes `(min, max)` (SPEC §12.2).
pub(crate) const FRAME_BARS: [([f64; 3], [f64; 3]); 4] = [
    ([-GATE_HALF_DEPTH, -GATE_HALF_OUTER, GATE_HALF_OPENING], [GATE_HALF_DEPTH, GATE_HALF_OUTER, GATE_HALF_OUTER]),
    ([-GATE_HALF_DEPTH, -GATE_HALF_OUTER, -GATE_HALF_OUTER], [GATE_HALF_DEPTH, GATE_HALF_OUTER, -GATE_HALF_OPENING]),
    ([-GATE_HALF_DEPTH, GATE_HALF_OPENING, -GATE_HALF_OUTER], [GATE_HALF_DEPTH, GATE_HALF_OUTER, GATE_HALF_OUTER]),
    ([-GATE_HALF_DEPTH, -GATE_HALF_OUTER, -GATE_HALF_OUTER], [GATE_HALF_DEPTH, -GATE_HALF_OPENING, GATE_HALF_OUTER]),
];

/// The point of the frame bars nearest to the gate-local point `l` (each bar's nearest point is
/// `l` clamped into its box).
fn nearest_frame_point_local(l: &Vector3<f64>) -> Vector3<f64> {
    let clamp_into =
        |(lo, hi): &([f64; 3], [f64; 3])| Vector3::new(l.x.clamp(lo[0], hi[0]), l.y.clamp(lo[1], hi[1]), l.z.clamp(lo[2], hi[2]));
    let nearer = |a: Vector3<f64>, b: Vector3<f64>| if (b - l).norm_squared() < (a - l).norm_squared() { b } else { a };
    FRAME_BARS[1..].iter().map(clamp_into).fold(clamp_into(&FRAME_BARS[0]), nearer)
}

/// A position and a heading.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position (m).
    pub position: Vector3<f64>,
    /// Heading about world z (rad).
    pub yaw: f64,
}

/// An axis-aligned box; the arena the drone must stay inside.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Arena {
    /// Lower corner (m).
    pub min: Vector3<f64>,
    /// Upper corner (m).
    pub max: Vector3<f64>,
}

impl Default for Arena {
    /// The generator bounds B of SPEC §6: x, y ∈ [-12, 12], z ∈ [0, 6].
    fn default() -> Self {
        Self { min: Vector3::new(-12.0, -12.0, 0.0), max: Vector3::new(12.0, 12.0, 6.0) }
    }
}

impl Arena {
    /// True when every coordinate lies within `[min, max]` (bounds included, SPEC §12.2).
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    /// Centre of the box.
    pub fn centre(&self) -> Vector3<f64> {
        (self.min + self.max) / 2.0
    }
}

/// A square racing gate: centre of the opening and yaw of its flight direction.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "GatePose", into = "GatePose")]
pub struct Gate {
    /// Centre of the opening (m).
    pub position: Vector3<f64>,
    /// Heading of the flight direction through the gate (rad).
    pub yaw: f64,
    cos_yaw: f64,
    sin_yaw: f64,
}

/// Serialised form of a gate.
#[derive(Clone, Copy, Serialize, Deserialize)]
struct GatePose {
    position: Vector3<f64>,
    yaw: f64,
}

impl From<GatePose> for Gate {
    fn from(g: GatePose) -> Self {
        Gate::new(g.position, g.yaw)
    }
}

impl From<Gate> for GatePose {
    fn from(g: Gate) -> Self {
        GatePose { position: g.position, yaw: g.yaw }
    }
}

/// Result of testing one step's segment against a gate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GateCrossing {
    /// Distance of the crossing point from the gate centre, e_t (m).
    pub error: f64,
}

impl Gate {
    /// A gate at `position` whose flight direction has heading `yaw` (rad).
    pub fn new(position: Vector3<f64>, yaw: f64) -> Self {
        Self { position, yaw, cos_yaw: yaw.cos(), sin_yaw: yaw.sin() }
    }

    /// World point → gate-local (x along the flight direction, y left, z up).
    pub fn to_local(&self, p: &Vector3<f64>) -> Vector3<f64> {
        let d = p - self.position;
        Vector3::new(self.cos_yaw * d.x + self.sin_yaw * d.y, -self.sin_yaw * d.x + self.cos_yaw * d.y, d.z)
    }

    /// Gate-local point → world.
    pub fn to_world(&self, l: &Vector3<f64>) -> Vector3<f64> {
        self.position + Vector3::new(self.cos_yaw * l.x - self.sin_yaw * l.y, self.sin_yaw * l.x + self.cos_yaw * l.y, l.z)
    }

    /// Unit normal: the flight direction through the gate.
    pub fn normal(&self) -> Vector3<f64> {
        Vector3::new(self.cos_yaw, self.sin_yaw, 0.0)
    }

    /// The four inner-opening corners in the world, in observation order (SPEC §4).
    pub fn corners(&self) -> [Vector3<f64>; 4] {
        GATE_CORNERS_LOCAL.map(|[y, z]| self.to_world(&Vector3::new(0.0, y, z)))
    }

    /// Whether the segment `from → to` passes through the opening from back to front
    /// (SPEC §4, §12.3); returns the traversal error when it does.
    pub fn crossing(&self, from: &Vector3<f64>, to: &Vector3<f64>) -> Option<GateCrossing> {
        let a = self.to_local(from);
        let b = self.to_local(to);
        if !(a.x < 0.0 && b.x >= 0.0) {
            return None;
        }
        let t = -a.x / (b.x - a.x);
        let y = a.y + t * (b.y - a.y);
        let z = a.z + t * (b.z - a.z);
        (y.abs() < GATE_HALF_OPENING && z.abs() < GATE_HALF_OPENING).then(|| GateCrossing { error: y.hypot(z) })
    }

    /// Whether a sphere of `radius` at `p` touches the gate frame (SPEC §12.2).
    pub fn frame_touches_sphere(&self, p: &Vector3<f64>, radius: f64) -> bool {
        let l = self.to_local(p);
        // Cheap rejection first: most substeps are far from most gates.
        if l.x.abs() > GATE_HALF_DEPTH + radius || l.y.abs() > GATE_HALF_OUTER + radius || l.z.abs() > GATE_HALF_OUTER + radius {
            return false;
        }
        (nearest_frame_point_local(&l) - l).norm_squared() <= radius * radius
    }

    /// The point of the gate frame nearest to `p`, in the world (`p` itself if inside a bar).
    pub fn nearest_frame_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.to_world(&nearest_frame_point_local(&self.to_local(p)))
    }

    /// Whether the outer frames (2.0 × 2.0 × 0.1 m boxes, yaw only) of two gates intersect.
    pub fn frame_overlaps(&self, other: &Gate) -> bool {
        if (self.position.z - other.position.z).abs() >= 2.0 * GATE_HALF_OUTER {
            return false;
        }
        // Separating-axis test of the two footprints (rectangles 0.1 × 2.0 m) in the plane.
        let half = Vector2::new(GATE_HALF_DEPTH, GATE_HALF_OUTER);
        let axes = |g: &Gate| [Vector2::new(g.cos_yaw, g.sin_yaw), Vector2::new(-g.sin_yaw, g.cos_yaw)];
        let (a_axes, b_axes) = (axes(self), axes(other));
        let d = (other.position - self.position).xy();
        let radius = |axes: &[Vector2<f64>; 2], n: &Vector2<f64>| half.x * axes[0].dot(n).abs() + half.y * axes[1].dot(n).abs();
        a_axes.iter().chain(b_axes.iter()).all(|n| d.dot(n).abs() < radius(&a_axes, n) + radius(&b_axes, n))
    }
}

/// A racetrack: gates in race order, start pose and arena.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Track {
    /// Human-readable name.
    pub name: String,
    /// Gates in the order they must be passed; at least two.
    pub gates: Vec<Gate>,
    /// Start pose of every episode (before randomisation).
    pub start: Pose,
    /// The box the drone must stay inside.
    pub arena: Arena,
}

/// Why a track is not valid; `field` names the offending entry as in a track file.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct TrackGeometryError {
    /// Field path, e.g. `gate[3].position`.
    pub field: String,
    /// What is wrong.
    pub message: String,
}

impl Track {
    /// Builds a track, placing the start 2 m behind gate 0 when `start` is `None`, and checks it.
    pub fn new(name: impl Into<String>, gates: Vec<Gate>, start: Option<Pose>, arena: Arena) -> Result<Self, TrackGeometryError> {
        let start = start.unwrap_or_else(|| match gates.first() {
            Some(g0) => Pose { position: g0.position - g0.normal() * START_BEHIND_FIRST_GATE, yaw: g0.yaw },
            None => Pose { position: arena.centre(), yaw: 0.0 },
        });
        let track = Self { name: name.into(), gates, start, arena };
        track.validate()?;
        Ok(track)
    }

    /// Checks the rules of SPEC §6 and §12.11.
    pub fn validate(&self) -> Result<(), TrackGeometryError> {
        let err = |field: String, message: String| Err(TrackGeometryError { field, message });
        let finite = |v: &Vector3<f64>| v.iter().all(|x| x.is_finite());
        if !finite(&self.arena.min) || !finite(&self.arena.max) {
            return err("arena".into(), "bounds must be finite numbers".into());
        }
        if self.arena.min.iter().chain(self.arena.max.iter()).any(|x| x.abs() > MAX_COORDINATE) {
            return err("arena".into(), format!("bounds must lie within ±{MAX_COORDINATE} m"));
        }
        if (0..3).any(|i| self.arena.min[i] >= self.arena.max[i]) {
            return err("arena".into(), "min must be below max on every axis".into());
        }
        if self.gates.len() < 2 {
            return err("gate".into(), format!("a track needs at least 2 gates, found {}", self.gates.len()));
        }
        if self.gates.len() > MAX_GATES {
            return err("gate".into(), format!("a track has at most {MAX_GATES} gates, found {}", self.gates.len()));
        }
        for (i, g) in self.gates.iter().enumerate() {
            if !finite(&g.position) {
                return err(format!("gate[{i}].position"), "must be finite numbers".into());
            }
            if !g.yaw.is_finite() {
                return err(format!("gate[{i}].yaw_deg"), "must be a finite number".into());
            }
            if !self.arena.contains(&g.position) {
                return err(format!("gate[{i}].position"), format!("{:?} is outside the arena", g.position.as_slice()));
            }
        }
        for i in 0..self.gates.len() {
            for j in i + 1..self.gates.len() {
                if self.gates[i].frame_overlaps(&self.gates[j]) {
                    return err(format!("gate[{j}].position"), format!("gate {j}'s frame overlaps gate {i}'s frame"));
                }
            }
        }
        if !finite(&self.start.position) || !self.start.yaw.is_finite() {
            return err("start".into(), "must be finite numbers".into());
        }
        if !self.arena.contains(&self.start.position) {
            return err("start.position".into(), format!("{:?} is outside the arena", self.start.position.as_slice()));
        }
        Ok(())
    }

    /// The gate after `index`, wrapping to gate 0 after the last.
    pub fn next_index(&self, index: usize) -> usize {
        (index + 1) % self.gates.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gate() -> Gate {
        Gate::new(Vector3::new(1.0, 2.0, 3.0), 0.5)
    }

    fn local(g: &Gate, x: f64, y: f64, z: f64) -> Vector3<f64> {
        g.to_world(&Vector3::new(x, y, z))
    }

    #[test]
    fn local_world_round_trip() {
        let g = gate();
        let p = Vector3::new(-3.0, 0.5, 7.0);
        assert!((g.to_world(&g.to_local(&p)) - p).norm() < 1e-12);
    }

    #[test]
    fn through_the_centre_passes_with_zero_error() {
        let g = gate();
        let c = g.crossing(&local(&g, -0.3, 0.0, 0.0), &local(&g, 0.3, 0.0, 0.0)).unwrap();
        assert!(c.error < 1e-12);
        let c = g.crossing(&local(&g, -0.2, 0.3, -0.4), &local(&g, 0.2, 0.3, -0.4)).unwrap();
        assert!((c.error - 0.5).abs() < 1e-12);
    }

    #[test]
    fn backwards_beside_or_short_of_the_gate_is_no_pass() {
        let g = gate();
        assert!(g.crossing(&local(&g, 0.3, 0.0, 0.0), &local(&g, -0.3, 0.0, 0.0)).is_none());
        assert!(g.crossing(&local(&g, -0.3, 1.5, 0.0), &local(&g, 0.3, 1.5, 0.0)).is_none());
        assert!(g.crossing(&local(&g, -0.3, 0.0, 0.8), &local(&g, 0.3, 0.0, 0.8)).is_none());
        assert!(g.crossing(&local(&g, -0.6, 0.0, 0.0), &local(&g, -0.1, 0.0, 0.0)).is_none());
        // Landing exactly on the plane counts (x ≥ 0 after).
        assert!(g.crossing(&local(&g, -0.6, 0.0, 0.0), &local(&g, 0.0, 0.0, 0.0)).is_some());
    }

    #[test]
    fn frame_contact_follows_the_bars() {
        let g = gate();
        let r = 0.15;
        assert!(!g.frame_touches_sphere(&local(&g, 0.0, 0.0, 0.0), r), "centre of the opening");
        assert!(!g.frame_touches_sphere(&local(&g, 0.0, 0.59, 0.0), r), "0.16 m from the side bar");
        assert!(g.frame_touches_sphere(&local(&g, 0.0, 0.61, 0.0), r), "0.14 m from the side bar");
        assert!(g.frame_touches_sphere(&local(&g, 0.0, 0.0, 0.9), r), "inside the top bar");
        assert!(g.frame_touches_sphere(&local(&g, 0.19, 0.0, 0.9), r), "in front of the top bar");
        assert!(!g.frame_touches_sphere(&local(&g, 0.21, 0.0, 0.9), r));
        assert!(!g.frame_touches_sphere(&local(&g, 0.0, 1.16, 0.0), r), "beside the gate");
        // Diagonal distance to the outer corner (y = z = 1): 0.1·√2 = 0.141 < 0.15.
        assert!(g.frame_touches_sphere(&local(&g, 0.0, 1.1, 1.1), r));
        assert!(!g.frame_touches_sphere(&local(&g, 0.0, 1.11, 1.11), r));
    }

    #[test]
    fn nearest_frame_point_is_the_contact_test_in_metres() {
        use rand::{Rng, SeedableRng};
        let g = Gate::new(Vector3::new(3.0, -2.0, 2.5), 0.7);
        let distance = |x, y, z| (g.nearest_frame_point(&local(&g, x, y, z)) - local(&g, x, y, z)).norm();
        // Centre of the opening: 0.75 m from each of the four inner edges.
        assert!((distance(0.0, 0.0, 0.0) - 0.75).abs() < 1e-12);
        // 2 m in front of the centre: to the nearest inner-edge point (0.05, 0, ±0.75) or (0.05, ±0.75, 0).
        assert!((distance(2.0, 0.0, 0.0) - 1.95f64.hypot(0.75)).abs() < 1e-12);
        // Above the gate: straight down to the top of the top bar.
        assert!((distance(0.0, 0.3, 3.0) - 2.0).abs() < 1e-12);
        // Inside a bar the point is its own nearest point.
        assert!(distance(0.0, 0.0, 0.9) < 1e-12);
        // The contact test of SPEC §12.2 is "nearest frame point within the radius", everywhere.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..2000 {
            let p = local(&g, rng.random_range(-1.0..1.0), rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5));
            let d = (g.nearest_frame_point(&p) - p).norm();
            assert_eq!(g.frame_touches_sphere(&p, 0.3), d <= 0.3, "at {p:?}, {d} m from the frame");
        }
    }

    #[test]
    fn frames_overlap_only_when_boxes_intersect() {
        let a = Gate::new(Vector3::new(0.0, 0.0, 2.0), 0.0);
        // SplitS-style stacking 2.36 m apart is fine; 1.9 m apart collides.
        assert!(!a.frame_overlaps(&Gate::new(Vector3::new(0.0, 0.0, 4.36), 3.0)));
        assert!(a.frame_overlaps(&Gate::new(Vector3::new(0.0, 0.0, 3.9), 0.0)));
        // Side by side along y: 2.0 m apart just touch, 2.05 m apart are separate.
        assert!(a.frame_overlaps(&Gate::new(Vector3::new(0.0, 1.99, 2.0), 0.0)));
        assert!(!a.frame_overlaps(&Gate::new(Vector3::new(0.0, 2.05, 2.0), 0.0)));
        // Crossing at right angles through each other.
        assert!(a.frame_overlaps(&Gate::new(Vector3::new(0.5, 0.0, 2.0), std::f64::consts::FRAC_PI_2)));
        // Parallel, one behind the other by 0.2 m.
        assert!(!a.frame_overlaps(&Gate::new(Vector3::new(0.2, 0.0, 2.0), 0.0)));
    }

    #[test]
    fn default_start_is_two_metres_behind_gate_zero() {
        let gates = vec![Gate::new(Vector3::new(0.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2), Gate::new(Vector3::new(5.0, 5.0, 2.0), 0.0)];
        let t = Track::new("t", gates, None, Arena::default()).unwrap();
        assert!((t.start.position - Vector3::new(0.0, -2.0, 2.0)).norm() < 1e-12);
        assert_eq!(t.start.yaw, std::f64::consts::FRAC_PI_2);
    }
}
