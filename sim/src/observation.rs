//! The 40-dimensional state observation (SPEC §5, §12.9), in a choice of reference frames,
//! optionally followed by points of the reference pilot's racing line ahead.
//!
//! Observations are written raw (un-normalised) into caller-owned f32 rows; normalisation
//! belongs to the policy, which owns the running statistics.

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::quadrotor::BodyState;
use crate::racing_line::RacingLine;
use crate::track::Track;

/// Length of the state observation of SPEC §5.
pub const STATE_OBS_DIM: usize = 40;

/// Where the previous action sits in the state observation (SPEC §5 order), after the
/// attitude columns, v and ω.
pub const PREVIOUS_ACTION_RANGE: std::ops::Range<usize> = 12..16;

/// Where δp1 sits: the target gate's 4 corners relative to the drone.
pub const TARGET_CORNERS_RANGE: std::ops::Range<usize> = 16..28;

/// Where δp2 sits: the next gate's 4 corners relative to the target gate's.
pub const NEXT_CORNERS_RANGE: std::ops::Range<usize> = 28..STATE_OBS_DIM;

/// Numbers each racing-line point adds: its position relative to the drone.
pub const LINE_POINT_DIM: usize = 3;

/// Default arc length between the racing-line points (m): four points reach 7.5 m along the
/// line from the drone's nearest point on it.
pub const DEFAULT_LINE_SPACING: f64 = 2.5;

/// The frame in which the observation's vectors (attitude columns, v, δp1, δp2) are written.
///
/// SPEC §5 writes them in the world frame (the thesis does not say which). A generalist flies
/// tracks in every orientation, so in the world frame the same manoeuvre looks different on a
/// track rotated about z; the other two frames remove that symmetry from what it must learn.
/// Body rates and the previous action are body quantities in every frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObservationFrame {
    /// World frame, as SPEC §5 states it.
    #[default]
    World,
    /// Yaw-aligned: rotated about world z by the drone's heading, so z stays up and the body x
    /// axis projects onto +x. Attitude columns are those of `R_z(-ψ) R_WB` (roll and pitch).
    Heading,
    /// Body frame: v, δp1 and δp2 in body axes; attitude columns as in `Heading` (gravity's
    /// direction is what the body frame needs from the attitude).
    Body,
}

impl ObservationFrame {
    /// The frame's name as run configs spell it: `world`, `heading` or `body`.
    pub fn name(self) -> &'static str {
        match self {
            ObservationFrame::World => "world",
            ObservationFrame::Heading => "heading",
            ObservationFrame::Body => "body",
        }
    }

    /// The rotation that takes world vectors into this frame for a drone with attitude `body`.
    pub fn rotation_from_world(self, body: &BodyState) -> Matrix3<f64> {
        match self {
            ObservationFrame::World => Matrix3::identity(),
            ObservationFrame::Heading => heading_from_world(body),
            ObservationFrame::Body => body.rotation().transpose(),
        }
    }
}

/// Which of the target and next gates the observation's δp1 and δp2 show.
///
/// SPEC §5 shows both wherever they are. A vision policy sees a gate only while it is in the
/// camera's view, so a state-based teacher that knows more acts on what its student cannot
/// see, and the student can only average those actions (docs/notebook/vision.md, "A teacher
/// that sees only what the camera sees").
/// `Camera` writes a gate's 12 numbers only while the camera could see it
/// ([`crate::camera::gate_in_view`]) and zeros otherwise: δp1 when the target is in view, δp2
/// (the next gate's corners from the target's) when both are. A teacher trained so knows what
/// its vision student can learn to know, and must learn to look for a gate it cannot see.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GateSight {
    /// Both gates always (SPEC §5).
    #[default]
    All,
    /// A gate only while it is in the camera's view.
    Camera,
}

/// What a state observation holds: SPEC §5's 40 numbers in `frame` (with the target and next
/// gates shown as `gate_sight` says), then `line_points` points of the reference pilot's racing
/// line, `line_spacing` metres of arc apart.
///
/// The racing-line points are the pilot's line (which keeps clear of every frame where it can,
/// [`RacingLine`]) from the point nearest the drone on the leg into the target gate, then every
/// `line_spacing` metres of arc ahead. They show the policy a way round the gates it cannot
/// see, in numbers whose meaning does not depend on the track's layout. Beyond the thesis.
///
/// The one description of the layout: a run's `[env.observation]` and a policy file's
/// architecture hold it as it is.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ObservationLayout {
    /// Frame of the vectors.
    pub frame: ObservationFrame,
    /// How many racing-line points follow, the first the nearest on the line.
    pub line_points: usize,
    /// Arc length between them (m).
    pub line_spacing: f64,
    /// Which of the target and next gates δp1 and δp2 show.
    pub gate_sight: GateSight,
}

impl Default for ObservationLayout {
    /// SPEC §5's 40 numbers in the world frame (SPEC §5 as written).
    fn default() -> Self {
        Self { frame: ObservationFrame::World, line_points: 0, line_spacing: DEFAULT_LINE_SPACING, gate_sight: GateSight::All }
    }
}

impl ObservationLayout {
    /// SPEC §5's 40 numbers in `frame`, nothing more.
    pub fn spec(frame: ObservationFrame) -> Self {
        Self { frame, ..Self::default() }
    }

    /// Length of an observation row.
    pub fn dim(self) -> usize {
        STATE_OBS_DIM + LINE_POINT_DIM * self.line_points
    }

    /// What a row holds, in words, for a flight stack that must write it (an exported model's
    /// doc string, a served policy's description).
    pub fn describe(self) -> String {
        let line = match self.line_points {
            0 => String::new(),
            k => format!(
                ", then {k} points of the reference pilot's racing line every {} m of arc from its nearest point",
                self.line_spacing
            ),
        };
        let sight = match self.gate_sight {
            GateSight::All => "",
            GateSight::Camera => ", the two gates' corners zero while the camera cannot see them",
        };
        format!("raw {}-number state observation in the {} frame{sight}{line}", self.dim(), self.frame.name())
    }
}

/// `R_z(-ψ)`: world vectors into the yaw-aligned frame of the drone's heading ψ.
fn heading_from_world(body: &BodyState) -> Matrix3<f64> {
    Rotation3::from_axis_angle(&Vector3::z_axis(), -body.yaw()).into_inner()
}

/// Writes `[R col 0, col 1, v, w, a_prev, δp1, δp2, line points…]` into `out` (length
/// `layout.dim()`), with R, v and the relative positions in `layout.frame`.
///
/// The line points are `layout.line_points` points of `line` (required when there are any),
/// each minus the drone position in `layout.frame`: the sample nearest to the drone on the leg
/// into the target gate, and the points `k · line_spacing` metres of arc after it.
pub fn write_state_observation(
    body: &BodyState,
    previous_action: &[f64; 4],
    track: &Track,
    line: Option<&RacingLine>,
    target: usize,
    layout: ObservationLayout,
    out: &mut [f32],
) {
    assert_eq!(out.len(), layout.dim(), "state observation row has the wrong length");
    let frame = layout.frame;
    let to_frame = frame.rotation_from_world(body);
    let attitude = match frame {
        ObservationFrame::World => body.rotation(),
        ObservationFrame::Heading | ObservationFrame::Body => heading_from_world(body) * body.rotation(),
    };
    let target_corners = track.gates[target].corners();
    let next_corners = track.gates[track.next_index(target)].corners();
    let mut values = [0f64; STATE_OBS_DIM];
    values[0..3].copy_from_slice(attitude.column(0).as_slice());
    values[3..6].copy_from_slice(attitude.column(1).as_slice());
    values[6..9].copy_from_slice((to_frame * body.velocity).as_slice());
    values[9..12].copy_from_slice(body.body_rates.as_slice());
    values[PREVIOUS_ACTION_RANGE].copy_from_slice(previous_action);
    // Per corner: whether δp1's and δp2's are shown (δp2 is written from δp1, so needs it).
    let rotation = body.rotation();
    let shown: [(bool, bool); 4] = match layout.gate_sight {
        GateSight::All => [(true, true); 4],
        GateSight::Camera => {
            let seen = |g: usize| crate::camera::gate_in_view(&track.gates[g], &body.position, &rotation);
            let target_seen = seen(target);
            [(target_seen, target_seen && seen(track.next_index(target))); 4]
        }
    };
    for (c, (show_target, show_next)) in shown.into_iter().enumerate() {
        let to_target = to_frame * (target_corners[c] - body.position);
        let between = to_frame * (next_corners[c] - target_corners[c]);
        let (t, n) = (TARGET_CORNERS_RANGE.start + 3 * c, NEXT_CORNERS_RANGE.start + 3 * c);
        if show_target {
            values[t..t + 3].copy_from_slice(to_target.as_slice());
        }
        if show_next {
            values[n..n + 3].copy_from_slice(between.as_slice());
        }
    }
    for (o, v) in out.iter_mut().zip(values) {
        *o = v as f32;
    }
    if layout.line_points > 0 {
        let Some(line) = line else { panic!("a layout with racing-line points needs the racing line") };
        write_line_ahead(body, line, target, layout, to_frame, &mut out[STATE_OBS_DIM..]);
    }
}

/// The racing-line points of [`write_state_observation`] into `out`.
fn write_line_ahead(
    body: &BodyState,
    line: &RacingLine,
    target: usize,
    layout: ObservationLayout,
    to_frame: Matrix3<f64>,
    out: &mut [f32],
) {
    let nearest = line.nearest_on_leg(&body.position, target);
    for (k, row) in out.chunks_exact_mut(LINE_POINT_DIM).take(layout.line_points).enumerate() {
        let relative = to_frame * (line.ahead(nearest, k as f64 * layout.line_spacing) - body.position);
        for (o, v) in row.iter_mut().zip(relative.iter()) {
            *o = *v as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Arena, Gate};
    use nalgebra::Vector3;

    #[test]
    fn layout_follows_the_spec_order() {
        let gates = vec![Gate::new(Vector3::new(4.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(8.0, 3.0, 3.0), std::f64::consts::FRAC_PI_2)];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        let mut body = BodyState::at_rest(Vector3::new(1.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2);
        body.velocity = Vector3::new(0.1, 0.2, 0.3);
        body.body_rates = Vector3::new(-1.0, -2.0, -3.0);
        let mut out = [0f32; STATE_OBS_DIM];
        write_state_observation(&body, &[0.5, 0.6, 0.7, 0.8], &track, None, 1, ObservationLayout::spec(ObservationFrame::World), &mut out);
        // Yaw 90°: body x points to world +y, body y to world -x.
        let expect_prefix = [0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.1, 0.2, 0.3, -1.0, -2.0, -3.0, 0.5, 0.6, 0.7, 0.8];
        for (i, e) in expect_prefix.iter().enumerate() {
            assert!((f64::from(out[i]) - e).abs() < 1e-6, "index {i}: {} vs {e}", out[i]);
        }
        // Target gate 1 (yaw 90°): corner 0 is local (y, z) = (+0.75, +0.75) → world (-0.75, 0, +0.75).
        let c0 = Vector3::new(8.0 - 0.75, 3.0, 3.75) - body.position;
        for k in 0..3 {
            assert!((f64::from(out[16 + k]) - c0[k]).abs() < 1e-6);
        }
        // The gate after the last is gate 0: δp2 corner 0 = gate 0 corner 0 − gate 1 corner 0.
        let g0c0 = Vector3::new(4.0, 0.75, 2.75);
        let d = g0c0 - Vector3::new(8.0 - 0.75, 3.0, 3.75);
        for k in 0..3 {
            assert!((f64::from(out[28 + k]) - d[k]).abs() < 1e-6);
        }
    }

    #[test]
    fn camera_sight_shows_a_gate_only_while_the_camera_could_see_it() {
        // Gate 0 straight ahead along +x; gate 1 behind the start, to the drone's back.
        let gates = vec![Gate::new(Vector3::new(6.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(-6.0, 0.0, 2.0), std::f64::consts::PI)];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        let observe = |yaw: f64, target: usize, sight: GateSight| {
            let body = BodyState::at_rest(Vector3::new(0.0, 0.0, 2.0), yaw);
            let layout = ObservationLayout { gate_sight: sight, ..ObservationLayout::spec(ObservationFrame::Heading) };
            let mut out = [0f32; STATE_OBS_DIM];
            write_state_observation(&body, &[0.1; 4], &track, None, target, layout, &mut out);
            out
        };
        let (all, camera) = (observe(0.0, 0, GateSight::All), observe(0.0, 0, GateSight::Camera));
        // Facing gate 0: its corners are shown; gate 1 is behind the camera, so δp2 is zeros.
        assert_eq!(camera[..28], all[..28]);
        assert!(all[28..].iter().any(|&v| v != 0.0) && camera[28..].iter().all(|&v| v == 0.0));
        // Turned round to face gate 1 while gate 0 is the target: the target is out of view,
        // so neither block shows (δp2 needs both gates); everything else is as SPEC's.
        let (all, camera) = (observe(std::f64::consts::PI, 0, GateSight::All), observe(std::f64::consts::PI, 0, GateSight::Camera));
        assert_eq!(camera[..16], all[..16]);
        assert!(camera[16..].iter().all(|&v| v == 0.0));
        // Facing gate 1 as the target, with gate 0 (the next) behind: δp1 only.
        let (all, camera) = (observe(std::f64::consts::PI, 1, GateSight::All), observe(std::f64::consts::PI, 1, GateSight::Camera));
        assert_eq!(camera[..28], all[..28]);
        assert!(camera[28..].iter().all(|&v| v == 0.0));
    }

    /// Wherever the rendered image shows any of a gate, `gate_in_view` says it may be seen.
    #[test]
    fn a_gate_the_camera_renders_is_always_in_view() {
        use rand::{Rng, SeedableRng};
        let gates = vec![Gate::new(Vector3::new(3.0, 1.0, 2.0), 0.4), Gate::new(Vector3::new(-2.0, 4.0, 3.0), 2.0)];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut image = vec![0u8; crate::camera::IMAGE_PIXELS];
        let (mut painted, mut out_of_view) = (0, 0);
        for _ in 0..2000 {
            let position = Vector3::new(rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0), rng.random_range(0.5..5.0));
            let axis = nalgebra::Unit::new_normalize(Vector3::new(rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3), 1.0));
            let rotation = Rotation3::from_axis_angle(&axis, rng.random_range(-3.2..3.2)).into_inner();
            crate::camera::render(&track, 0, &position, &rotation, &mut image);
            let shows_target = image.contains(&crate::camera::TARGET_COLOUR);
            let in_view = crate::camera::gate_in_view(&track.gates[0], &position, &rotation);
            assert!(!shows_target || in_view, "gate 0 drawn but not in view from {position:?}");
            painted += usize::from(shows_target);
            out_of_view += usize::from(!in_view);
        }
        // Both cases occur, so the implication above was put to the test.
        assert!(painted > 100 && out_of_view > 100, "{painted} painted, {out_of_view} out of view");
    }

    /// The same scene rotated about world z by any angle gives the same heading- and
    /// body-frame observation; the world-frame one changes.
    #[test]
    fn heading_and_body_frames_are_invariant_to_rotating_the_whole_scene_about_z() {
        let rotate = |angle: f64, v: Vector3<f64>| Rotation3::from_axis_angle(&Vector3::z_axis(), angle) * v;
        let observe = |angle: f64, frame: ObservationFrame| {
            let gates = vec![
                Gate::new(rotate(angle, Vector3::new(4.0, 1.0, 2.0)), 0.3 + angle),
                Gate::new(rotate(angle, Vector3::new(8.0, 5.0, 3.0)), 1.2 + angle),
            ];
            let arena = Arena { min: Vector3::new(-20.0, -20.0, 0.0), max: Vector3::new(20.0, 20.0, 6.0) };
            let track = Track::new("t", gates, None, arena).unwrap();
            let tilt = nalgebra::UnitQuaternion::from_euler_angles(0.2, -0.1, 0.7 + angle);
            let body = BodyState {
                position: rotate(angle, Vector3::new(1.0, -1.0, 2.0)),
                attitude: *tilt.quaternion(),
                velocity: rotate(angle, Vector3::new(2.0, 0.5, -0.3)),
                body_rates: Vector3::new(0.1, 0.2, 0.3),
            };
            let mut out = [0f32; STATE_OBS_DIM];
            write_state_observation(&body, &[0.1, 0.2, 0.3, 0.4], &track, None, 0, ObservationLayout::spec(frame), &mut out);
            out
        };
        for frame in [ObservationFrame::Heading, ObservationFrame::Body] {
            let (a, b) = (observe(0.0, frame), observe(2.1, frame));
            for i in 0..STATE_OBS_DIM {
                assert!((a[i] - b[i]).abs() < 1e-5, "{frame:?} index {i}: {} vs {}", a[i], b[i]);
            }
        }
        let (a, b) = (observe(0.0, ObservationFrame::World), observe(2.1, ObservationFrame::World));
        assert!((a[6] - b[6]).abs() > 0.1, "world-frame velocity turns with the scene");
    }

    #[test]
    fn body_frame_puts_a_gate_ahead_of_a_level_drone_on_body_x() {
        let gates = vec![Gate::new(Vector3::new(0.0, 5.0, 2.0), std::f64::consts::FRAC_PI_2), Gate::new(Vector3::new(5.0, 5.0, 2.0), 0.0)];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        // Facing +y (yaw 90°), 5 m before gate 0: its centre is 5 m along body x.
        let body = BodyState::at_rest(Vector3::new(0.0, 0.0, 2.0), std::f64::consts::FRAC_PI_2);
        let mut out = [0f32; STATE_OBS_DIM];
        write_state_observation(&body, &[0.0; 4], &track, None, 0, ObservationLayout::spec(ObservationFrame::Body), &mut out);
        let centre: Vec<f32> = (0..3).map(|k| (0..4).map(|c| out[16 + 3 * c + k]).sum::<f32>() / 4.0).collect();
        assert!((centre[0] - 5.0).abs() < 1e-5 && centre[1].abs() < 1e-5 && centre[2].abs() < 1e-5, "{centre:?}");
        // Level and heading-aligned: attitude columns are the identity's.
        assert!((out[0] - 1.0).abs() < 1e-6 && (out[4] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn line_points_follow_the_racing_line_from_its_nearest_point_on_the_target_leg() {
        let gates = (0..4)
            .map(|k| {
                let a = std::f64::consts::FRAC_PI_2 * f64::from(k);
                Gate::new(Vector3::new(6.0 * a.cos(), 6.0 * a.sin(), 2.0), a + std::f64::consts::FRAC_PI_2)
            })
            .collect();
        let track = Track::new("square", gates, None, Arena::default()).unwrap();
        let line = RacingLine::new(&track);
        let layout = ObservationLayout { frame: ObservationFrame::Heading, line_points: 3, line_spacing: 2.0, ..Default::default() };
        assert_eq!(layout.dim(), STATE_OBS_DIM + 9);
        // A drone just off the line on the leg into gate 2, facing +x (heading frame = world).
        let k = line.points().len() / 4 + 60;
        let body = BodyState::at_rest(line.points()[k].position + Vector3::new(0.0, 0.0, 0.3), 0.0);
        let mut out = vec![f32::NAN; layout.dim()];
        write_state_observation(&body, &[0.0; 4], &track, Some(&line), 2, layout, &mut out);
        for j in 0..3 {
            let expected = line.ahead(k, 2.0 * j as f64) - body.position;
            for c in 0..3 {
                let got = f64::from(out[STATE_OBS_DIM + 3 * j + c]);
                assert!((got - expected[c]).abs() < 1e-5, "point {j}, axis {c}: {got} against {}", expected[c]);
            }
        }
        // The first point is the nearest on the line: straight below the drone.
        assert!((f64::from(out[STATE_OBS_DIM + 2]) + 0.3).abs() < 1e-5);
        // SPEC's 40 numbers do not change with the points.
        let mut spec = [0f32; STATE_OBS_DIM];
        write_state_observation(&body, &[0.0; 4], &track, None, 2, ObservationLayout::spec(ObservationFrame::Heading), &mut spec);
        assert_eq!(&out[..STATE_OBS_DIM], &spec[..]);
    }
}
