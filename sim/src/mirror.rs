//! The racing problem's mirror symmetry. Reflecting the whole scene — drone, gates, arena — in
//! a vertical plane gives another scene the same physics flies: gravity is vertical, the
//! quadrotor is symmetric about its x–z plane (rotors fr ↔ fl, br ↔ bl, which spin the other
//! way), and the SPEC §5 reward depends on distances only. So the mirrored state with the
//! mirrored action evolves into the mirror of what the original does, and a policy that is
//! right on one side of a turn is right on the other if it commutes with the reflection. The
//! pilot's racing line and the camera's view of the gates reflect with the track (the tests fly
//! both), and the vehicle randomisation draws each side alike.
//!
//! In the world and heading frames the plane is the frame's x–z plane (y → −y): a vector `u`
//! becomes `(u_x, −u_y, u_z)`; a pseudo-vector (body rates, and the attitude's second column,
//! which is the body y axis that the reflection also flips to keep the frame right-handed)
//! becomes `(−u_x, u_y, −u_z)`; a gate's corners swap left for right (SPEC §4 order 0 ↔ 1,
//! 2 ↔ 3). In the body frame the x–z plane tilts with the drone and is no symmetry of gravity,
//! so that frame has no mirror.

use crate::observation::{ObservationFrame, ObservationLayout, STATE_OBS_DIM};

/// Signs that mirror a normalised action `[collective thrust, roll, pitch, yaw rate]`: roll and
/// yaw rates change sign, thrust and pitch rate do not.
pub const ACTION_MIRROR_SIGNS: [f32; 4] = [1.0, -1.0, 1.0, -1.0];

/// A vector's signs under the reflection.
const VECTOR: [f32; 3] = [1.0, -1.0, 1.0];
/// A pseudo-vector's signs under the reflection.
const PSEUDO_VECTOR: [f32; 3] = [-1.0, 1.0, -1.0];
/// Where each of a gate's four corners comes from: left and right swap.
const CORNER_SOURCE: [usize; 4] = [1, 0, 3, 2];

/// How the reflection maps an observation row: `mirrored[i] = sign[i] · row[source[i]]`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObservationMirror {
    /// The index each mirrored number is read from.
    pub source: Vec<usize>,
    /// The sign it is read with.
    pub sign: Vec<f32>,
}

impl ObservationMirror {
    /// Writes the mirror of `row` into `out` (both the layout's length).
    pub fn apply(&self, row: &[f32], out: &mut [f32]) {
        for ((o, &s), &sign) in out.iter_mut().zip(&self.source).zip(&self.sign) {
            *o = sign * row[s];
        }
    }

    /// Appends `repeat` blocks that map onto themselves, each with `signs`.
    fn push_in_place(&mut self, signs: &[f32], repeat: usize) {
        for _ in 0..repeat {
            for &s in signs {
                self.source.push(self.source.len());
                self.sign.push(s);
            }
        }
    }

    /// Appends one gate's 4 corner vectors, left and right swapped.
    fn push_corners(&mut self) {
        let start = self.source.len();
        for corner in CORNER_SOURCE {
            for (k, &s) in VECTOR.iter().enumerate() {
                self.source.push(start + 3 * corner + k);
                self.sign.push(s);
            }
        }
    }
}

impl ObservationLayout {
    /// The reflection's action on this layout's rows; `None` in the body frame, which has no
    /// mirror (see the module's documentation).
    pub fn mirror(self) -> Option<ObservationMirror> {
        if self.frame == ObservationFrame::Body {
            return None;
        }
        let mut m = ObservationMirror { source: Vec::with_capacity(self.dim()), sign: Vec::with_capacity(self.dim()) };
        m.push_in_place(&VECTOR, 1); // attitude column 0: the body x axis
        m.push_in_place(&PSEUDO_VECTOR, 1); // attitude column 1: the body y axis, flipped
        m.push_in_place(&VECTOR, 1); // velocity
        m.push_in_place(&PSEUDO_VECTOR, 1); // body rates
        m.push_in_place(&ACTION_MIRROR_SIGNS, 1); // previous action
        m.push_corners(); // δp1
        m.push_corners(); // δp2: corner differences, corner for corner
        debug_assert_eq!(m.source.len(), STATE_OBS_DIM);
        m.push_in_place(&VECTOR, self.line_points);
        debug_assert_eq!(m.source.len(), self.dim());
        Some(m)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3, Vector4};

    use super::*;
    use crate::observation::{GateSight, write_state_observation};
    use crate::params::QuadrotorParams;
    use crate::quadrotor::{BodyState, Command, Quadrotor};
    use crate::racing_line::RacingLine;
    use crate::track::{Arena, Gate, Pose, Track};

    /// The reflection y → −y of the world.
    fn reflect(v: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(v.x, -v.y, v.z)
    }

    /// The mirrored drone: position and velocity reflected, attitude `M R M`, rates as a
    /// pseudo-vector in the mirrored body frame.
    fn mirror_body(b: &BodyState) -> BodyState {
        let m = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, 1.0));
        let rotation = Rotation3::from_matrix_unchecked(m * b.rotation() * m);
        BodyState {
            position: reflect(&b.position),
            attitude: *UnitQuaternion::from_rotation_matrix(&rotation).quaternion(),
            velocity: reflect(&b.velocity),
            body_rates: Vector3::new(-b.body_rates.x, b.body_rates.y, -b.body_rates.z),
        }
    }

    fn mirror_track(t: &Track) -> Track {
        let gates = t.gates.iter().map(|g| Gate::new(reflect(&g.position), -g.yaw)).collect();
        let start = Pose { position: reflect(&t.start.position), yaw: -t.start.yaw };
        let arena = Arena {
            min: Vector3::new(t.arena.min.x, -t.arena.max.y, t.arena.min.z),
            max: Vector3::new(t.arena.max.x, -t.arena.min.y, t.arena.max.z),
        };
        Track::new("mirrored", gates, Some(start), arena).unwrap()
    }

    fn scene() -> (Track, BodyState, [f64; 4]) {
        let gates = vec![
            Gate::new(Vector3::new(4.0, 1.0, 2.0), 0.3),
            Gate::new(Vector3::new(8.0, 5.0, 3.0), 1.2),
            Gate::new(Vector3::new(3.0, 8.0, 2.5), 2.9),
            Gate::new(Vector3::new(-4.0, 4.0, 1.5), -2.0),
            Gate::new(Vector3::new(-2.0, -3.0, 3.5), -0.4),
        ];
        let track = Track::new("t", gates, None, Arena::default()).unwrap();
        let mut body = BodyState::at_rest(Vector3::new(5.0, 2.5, 2.2), 0.7);
        body.attitude = *(UnitQuaternion::from_euler_angles(0.25, -0.4, 0.7)).quaternion();
        body.velocity = Vector3::new(3.0, -1.5, 0.8);
        body.body_rates = Vector3::new(1.1, -0.6, 0.4);
        (track, body, [0.3, -0.2, 0.5, 0.1])
    }

    /// Observing the mirrored scene gives the mirrored observation, number for number, in every
    /// frame that has a mirror and with every optional block.
    #[test]
    fn the_mirrored_scene_is_observed_as_the_mirrored_observation() {
        let (track, body, action) = scene();
        let (mirrored_track, mirrored_body) = (mirror_track(&track), mirror_body(&body));
        let mirrored_action = [action[0], -action[1], action[2], -action[3]];
        let (line, mirrored_line) = (RacingLine::new(&track), RacingLine::new(&mirrored_track));
        for frame in [ObservationFrame::World, ObservationFrame::Heading] {
            for gate_sight in [GateSight::All, GateSight::Camera] {
                let layout = ObservationLayout { frame, line_points: 3, gate_sight, ..ObservationLayout::default() };
                let mirror = layout.mirror().unwrap();
                for target in 0..track.gates.len() {
                    let (mut observed, mut of_mirror, mut mirrored) =
                        (vec![0f32; layout.dim()], vec![0f32; layout.dim()], vec![0f32; layout.dim()]);
                    write_state_observation(&body, &action, &track, Some(&line), target, layout, &mut observed);
                    write_state_observation(
                        &mirrored_body,
                        &mirrored_action,
                        &mirrored_track,
                        Some(&mirrored_line),
                        target,
                        layout,
                        &mut of_mirror,
                    );
                    mirror.apply(&observed, &mut mirrored);
                    assert!(observed.iter().any(|&x| x.abs() > 0.1), "a scene with something in view");
                    for (i, (a, b)) in of_mirror.iter().zip(&mirrored).enumerate() {
                        assert!((a - b).abs() < 1e-4, "{frame:?} {gate_sight:?} target {target}, number {i}: {a} vs {b}");
                    }
                }
            }
        }
        assert_eq!(ObservationLayout::spec(ObservationFrame::Body).mirror(), None);
    }

    /// Mirroring twice is the identity, so the reflection is its own inverse on the rows.
    #[test]
    fn the_mirror_is_an_involution() {
        let layout = ObservationLayout { frame: ObservationFrame::Heading, line_points: 4, ..ObservationLayout::default() };
        let mirror = layout.mirror().unwrap();
        let row: Vec<f32> = (0..layout.dim()).map(|i| i as f32 + 1.0).collect();
        let (mut once, mut twice) = (vec![0f32; row.len()], vec![0f32; row.len()]);
        mirror.apply(&row, &mut once);
        mirror.apply(&once, &mut twice);
        assert_ne!(once, row);
        assert_eq!(twice, row);
    }

    /// The quadrotor commutes with the reflection: flown with mirrored commands from the
    /// mirrored state (motor speeds swapped left for right), it stays the mirror of the original
    /// through a second of aggressive flight.
    #[test]
    fn the_quadrotor_flies_the_mirror_of_the_mirrored_commands() {
        let params = QuadrotorParams::default();
        let (_, body, _) = scene();
        let mut quad = Quadrotor::new(params, params, body);
        let mut mirrored = Quadrotor::new(params, params, mirror_body(&body));
        quad.motor_speeds = Vector4::new(900.0, 1100.0, 1000.0, 1200.0);
        // fr, bl, br, fl → their mirror images fl, br, bl, fr.
        mirrored.motor_speeds = Vector4::new(1200.0, 1000.0, 1100.0, 900.0);
        for step in 0..50 {
            let t = step as f64 * 0.02;
            let action = [(3.0 * t).sin() * 0.6, (5.0 * t).cos() * 0.8, (2.0 * t).sin() * 0.7, 0.5 - t];
            let mirrored_action: [f64; 4] = std::array::from_fn(|i| action[i] * f64::from(ACTION_MIRROR_SIGNS[i]));
            for _ in 0..8 {
                quad.substep(&Command::from_action(&action, quad.model()), 0.0025);
                mirrored.substep(&Command::from_action(&mirrored_action, mirrored.model()), 0.0025);
            }
            quad.normalize_attitude();
            mirrored.normalize_attitude();
        }
        let expected = mirror_body(&quad.body);
        assert!((quad.body.position - body.position).norm() > 1.0, "the drone moved");
        assert!((mirrored.body.position - expected.position).norm() < 1e-6);
        assert!((mirrored.body.velocity - expected.velocity).norm() < 1e-6);
        assert!((mirrored.body.body_rates - expected.body_rates).norm() < 1e-6);
        let q = |b: &BodyState| UnitQuaternion::new_normalize(Quaternion::from(b.attitude.coords));
        assert!(q(&mirrored.body).angle_to(&q(&expected)) < 1e-6);
    }
}
