//! Stacked camera frames (beyond SPEC §5, whose vision actor sees the current image alone): a
//! vision policy may also see the images of some earlier steps, so that it remembers a gate
//! that has left the image. Gates stand still, so an earlier image still says where the gate
//! is, given how the drone has moved since (which the proprioception tells).
//!
//! The history keeps camera poses, not images: the renderer is deterministic, so the frames
//! are rendered from them when they are needed, and a history is ~60 bytes a step.

use std::collections::VecDeque;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::{IMAGE_PIXELS, render};
use crate::race::RaceEnv;
use crate::track::Track;

/// Which camera frames a vision policy sees: the current one and `frames − 1` earlier ones,
/// `stride` steps apart (SPEC §5: one frame).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameStack {
    /// Frames seen, the current one included (≥ 1).
    pub frames: usize,
    /// Steps between consecutive frames (≥ 1).
    pub stride: usize,
}

impl Default for FrameStack {
    /// SPEC §5: the current frame alone.
    fn default() -> Self {
        Self { frames: 1, stride: 1 }
    }
}

impl FrameStack {
    /// True for SPEC's single frame.
    pub fn is_single(&self) -> bool {
        self.frames == 1
    }

    /// Steps from the oldest frame seen to the current one.
    pub fn span(&self) -> usize {
        (self.frames - 1) * self.stride
    }

    /// Bytes of one stacked observation: `frames` images, the current one first.
    pub fn image_len(&self) -> usize {
        self.frames * IMAGE_PIXELS
    }

    /// An error naming what is wrong, when `frames` or `stride` is 0.
    pub fn check(&self) -> Result<(), String> {
        if self.frames == 0 || self.stride == 0 {
            return Err(format!("frame_stack: frames {} and stride {} must each be ≥ 1", self.frames, self.stride));
        }
        Ok(())
    }
}

/// Where the camera was at one step and which gate was the target (its brightest).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    /// Target gate.
    pub target: u32,
    /// Position (m, world).
    pub position: [f64; 3],
    /// Body attitude quaternion (w, x, y, z).
    pub attitude: [f64; 4],
}

impl CameraPose {
    /// The camera pose of `env`'s current state.
    pub fn of(env: &RaceEnv) -> Self {
        let body = env.body();
        let a = body.attitude;
        Self { target: env.target_gate() as u32, position: body.position.into(), attitude: [a.w, a.i, a.j, a.k] }
    }

    /// Renders the image seen from this pose on `track` into `out` (`IMAGE_PIXELS` bytes).
    pub fn render(&self, track: &Track, out: &mut [u8]) {
        let (position, rotation) = self.position_and_rotation();
        render(track, self.target as usize, &position, &rotation, out);
    }

    /// Position and `R_WB`.
    pub fn position_and_rotation(&self) -> (Vector3<f64>, nalgebra::Matrix3<f64>) {
        let [w, x, y, z] = self.attitude;
        let rotation = UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z)).to_rotation_matrix().into_inner();
        (Vector3::from(self.position), rotation)
    }
}

/// The camera poses of one flight's last `span + 1` steps, newest first: what a stacked-frame
/// policy sees. Before the flight has lasted that long, the earliest pose stands in for the
/// steps before it (the drone waited there).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraHistory {
    stack: FrameStack,
    poses: VecDeque<CameraPose>,
}

impl CameraHistory {
    /// An empty history of `stack`; the first pose recorded fills it.
    pub fn new(stack: FrameStack) -> Self {
        Self { stack, poses: VecDeque::with_capacity(stack.span() + 1) }
    }

    /// Which frames it keeps.
    pub fn stack(&self) -> FrameStack {
        self.stack
    }

    /// Starts a new flight at `pose`.
    pub fn restart(&mut self, pose: CameraPose) {
        self.poses.clear();
        self.record(pose);
    }

    /// Adds the pose of the step just reached (the first pose after a restart fills the
    /// history).
    pub fn record(&mut self, pose: CameraPose) {
        if self.poses.is_empty() {
            self.poses.extend(std::iter::repeat_n(pose, self.stack.span() + 1));
            return;
        }
        self.poses.pop_back();
        self.poses.push_front(pose);
    }

    /// The poses of the frames seen, the current one first (`frames` of them; none before the
    /// first pose is recorded).
    pub fn frames(&self) -> Vec<CameraPose> {
        self.poses.iter().step_by(self.stack.stride).copied().collect()
    }

    /// Renders the frames seen on `track` into `out` (`stack.image_len()` bytes, the current
    /// image first).
    pub fn render(&self, track: &Track, out: &mut [u8]) {
        render_frames(&self.frames(), track, out);
    }
}

/// Renders `frames` (current first) on `track` into `out`, one image after another.
pub fn render_frames(frames: &[CameraPose], track: &Track, out: &mut [u8]) {
    assert_eq!(out.len(), frames.len() * IMAGE_PIXELS, "one image per frame");
    for (pose, image) in frames.iter().zip(out.chunks_exact_mut(IMAGE_PIXELS)) {
        pose.render(track, image);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Arena, Gate};
    use crate::{EnvConfig, RandomizationParams};
    use std::sync::Arc;

    fn pose(x: f64) -> CameraPose {
        CameraPose { target: 0, position: [x, 0.0, 2.0], attitude: [1.0, 0.0, 0.0, 0.0] }
    }

    #[test]
    fn the_history_shows_every_stride_th_pose_newest_first_and_fills_from_the_first() {
        let mut history = CameraHistory::new(FrameStack { frames: 3, stride: 2 });
        assert!(history.frames().is_empty());
        history.record(pose(0.0));
        assert_eq!(history.frames(), vec![pose(0.0); 3], "the first pose stands in for the steps before it");
        for x in 1..=3 {
            history.record(pose(f64::from(x)));
        }
        // Poses 3, 2, 1, 0, 0 kept: frames 3, 1, 0.
        assert_eq!(history.frames(), vec![pose(3.0), pose(1.0), pose(0.0)]);
        history.record(pose(4.0));
        assert_eq!(history.frames(), vec![pose(4.0), pose(2.0), pose(0.0)]);
        history.restart(pose(9.0));
        assert_eq!(history.frames(), vec![pose(9.0); 3], "a new flight forgets the last one");
        assert_eq!(CameraHistory::new(FrameStack::default()).stack().span(), 0);
    }

    #[test]
    fn a_frame_renders_what_the_environment_showed_at_that_step() {
        let gates = vec![Gate::new(Vector3::new(4.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(-4.0, 0.0, 2.0), 3.0)];
        let track = Arc::new(Track::new("two", gates, None, Arena::default()).unwrap());
        let config = EnvConfig { randomization: RandomizationParams::none(), ..EnvConfig::evaluation() };
        let mut env = RaceEnv::new(track.clone(), config, 0, 0);
        let stack = FrameStack { frames: 2, stride: 3 };
        let mut history = CameraHistory::new(stack);
        history.restart(CameraPose::of(&env));
        let mut shown = Vec::new();
        for _ in 0..3 {
            let mut image = vec![0u8; IMAGE_PIXELS];
            env.render_camera(&mut image);
            shown.push(image);
            env.step(&[0.3, 0.2, -0.1, 0.0]);
            history.record(CameraPose::of(&env));
        }
        let mut now = vec![0u8; IMAGE_PIXELS];
        env.render_camera(&mut now);
        let mut stacked = vec![0u8; stack.image_len()];
        history.render(&track, &mut stacked);
        assert_eq!(&stacked[..IMAGE_PIXELS], &now[..], "the current frame first");
        assert_eq!(&stacked[IMAGE_PIXELS..], &shown[0][..], "then the frame of 3 steps before");
        assert_ne!(shown[0], now, "the drone moved, so the frames differ");
        assert!(FrameStack { frames: 0, stride: 1 }.check().unwrap_err().contains("frame_stack"));
    }
}
