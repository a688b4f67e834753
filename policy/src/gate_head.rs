//! A training-only head on the vision CNN's embedding that predicts where the target gate and
//! the gate after it are (an auxiliary task for distillation). Imitation gives the CNN four
//! action numbers per image; the gates' geometry gives it 26, and they are exactly what the
//! state-based teacher acts on. The head never enters a weights blob: a student flies without it.
//!
//! What it predicts, per gate (target, then next): its 4 corners in the body frame divided by
//! the distance to the gate's centre — a direction, which a camera measures with the same
//! pixel precision near and far — and the log of that distance. A gate the camera does not
//! show (no pixel of its colour) is not scored: nothing in the image says where it is.

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sim::Track;
use sim::camera::{NEXT_COLOUR, TARGET_COLOUR};
use sim::nalgebra::{Matrix3, Vector3};

use crate::network::{ExportedParam, Mlp, check_shapes};
use crate::safetensors::{self, TensorFile};
use crate::vision::{EMBEDDING, VisionActorCritic, image_tensor};

/// Numbers predicted per gate: 4 corners × 3, then the log distance.
pub const PER_GATE: usize = 13;
/// Numbers predicted per image: the target gate's, then the next gate's.
pub const GATE_TARGETS: usize = 2 * PER_GATE;
/// Nearest distance (m) the directions are divided by: closer, the corners are off-image anyway.
const MIN_DISTANCE: f64 = 0.5;
/// `format` metadata of a saved head.
const FORMAT_NAME: &str = "dronerace-gate-head";

/// The head: one linear layer, embedding → [`GATE_TARGETS`].
#[derive(Module, Debug)]
pub struct GateHead {
    layer: Mlp,
}

impl GateHead {
    /// A fresh head (orthogonal weights of gain 1, zero bias; seeded).
    pub fn new(seed: u64, device: &Device) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        Self { layer: Mlp::new(&[EMBEDDING, GATE_TARGETS], 1.0, 0.0, &mut rng, device) }
    }

    /// Predictions `[batch, 26]` from embeddings `[batch, 128]`.
    pub fn forward(&self, embedding: Tensor<2>) -> Tensor<2> {
        self.layer.forward(embedding)
    }

    /// Predictions (`GATE_TARGETS` per observation) for camera observations (84 × 84 bytes
    /// per frame of `model`'s) seen through `model`'s CNN: for analyses of a trained student.
    #[allow(clippy::expect_used, reason = "float outputs")]
    pub fn predict(&self, model: &VisionActorCritic, images: &[u8], device: &Device) -> Vec<f32> {
        let images = image_tensor(images, model.frames(), device);
        self.forward(model.embed(images)).into_data().try_to_vec::<f32>().expect("float outputs")
    }

    /// The head as a safetensors file, parameter ids kept so that optimiser moments re-attach.
    #[allow(clippy::expect_used, reason = "ids serialise")]
    pub fn to_bytes(&self) -> Vec<u8> {
        let params = self.layer.export();
        let mut file = TensorFile::default();
        file.metadata.insert("format".into(), FORMAT_NAME.into());
        let ids: Vec<u64> = params.iter().map(|p| p.id).collect();
        file.metadata.insert("param_ids".into(), serde_json::to_string(&ids).expect("ids serialise"));
        for (name, p) in ["weight", "bias"].into_iter().zip(params) {
            file.tensors.insert(name.into(), safetensors::Tensor { shape: p.shape, data: safetensors::TensorData::F32(p.values) });
        }
        file.to_bytes()
    }

    /// Reads [`GateHead::to_bytes`]' output; errors say what is wrong.
    pub fn from_bytes(bytes: &[u8], device: &Device) -> Result<Self, String> {
        let file = TensorFile::from_bytes(bytes).map_err(|e| format!("gate head: {e}"))?;
        if file.meta("format").map_err(|e| e.to_string())? != FORMAT_NAME {
            return Err("not a gate head".into());
        }
        let ids: Vec<u64> =
            serde_json::from_str(file.meta("param_ids").map_err(|e| e.to_string())?).map_err(|e| format!("gate head ids: {e}"))?;
        let mut params = Vec::new();
        for (name, id) in ["weight", "bias"].into_iter().zip(ids) {
            let tensor = file.tensor(name).map_err(|e| e.to_string())?;
            let safetensors::TensorData::F32(values) = &tensor.data else {
                return Err(format!("gate head {name} is not F32"));
            };
            params.push(ExportedParam { id, shape: tensor.shape.clone(), values: values.clone() });
        }
        check_shapes(&Mlp::shapes(&[EMBEDDING, GATE_TARGETS]), &params).map_err(|e| format!("gate head: {e}"))?;
        Ok(Self { layer: Mlp::import(&params, 0.0, device) })
    }
}

/// What the head should predict for a drone at `position` with attitude `body_rotation`
/// (`R_WB`) racing to gate `target` of `track` (module docs).
pub fn gate_targets(track: &Track, target: usize, position: &Vector3<f64>, body_rotation: &Matrix3<f64>) -> [f32; GATE_TARGETS] {
    let mut out = [0.0; GATE_TARGETS];
    let to_body = body_rotation.transpose();
    for (gate, chunk) in [target, track.next_index(target)].into_iter().zip(out.chunks_exact_mut(PER_GATE)) {
        let gate = &track.gates[gate];
        let distance = (gate.position - position).norm().max(MIN_DISTANCE);
        for (corner, xyz) in gate.corners().iter().zip(chunk.chunks_exact_mut(3)) {
            let direction = to_body * (corner - position) / distance;
            for (o, v) in xyz.iter_mut().zip(direction.iter()) {
                *o = *v as f32;
            }
        }
        chunk[PER_GATE - 1] = distance.ln() as f32;
    }
    out
}

/// Per predicted number, 1 when the camera `image` shows its gate (a pixel of its colour) and
/// 0 otherwise: the weights of the head's squared errors.
pub fn shown_mask(image: &[u8]) -> [f32; GATE_TARGETS] {
    let shows = |colour: u8| if image.contains(&colour) { 1.0 } else { 0.0 };
    let (target, next) = (shows(TARGET_COLOUR), shows(NEXT_COLOUR));
    std::array::from_fn(|i| if i < PER_GATE { target } else { next })
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim::Gate;
    use sim::camera::IMAGE_PIXELS;
    use std::sync::Arc;

    fn track() -> Arc<Track> {
        let gates = vec![Gate::new(Vector3::new(6.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(12.0, 3.0, 2.0), 0.0)];
        Arc::new(Track::new("two", gates, None, sim::Arena::default()).unwrap())
    }

    #[test]
    fn targets_are_corner_directions_and_log_distances_in_the_body_frame() {
        let track = track();
        let position = Vector3::new(0.0, 0.0, 2.0);
        let level = gate_targets(&track, 0, &position, &Matrix3::identity());
        // Gate 0 is 6 m straight ahead: every corner direction has x = 6 / 6 and |y|, |z| equal.
        assert!((level[PER_GATE - 1] - 6f32.ln()).abs() < 1e-6);
        for xyz in level[..12].chunks(3) {
            assert!((xyz[0] - 1.0).abs() < 1e-6 && (xyz[1].abs() - xyz[2].abs()).abs() < 1e-6, "{xyz:?}");
        }
        // Yawed 90° left (body x = world y), the gate ahead lies to the body's right (−y).
        let yawed = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        let turned = gate_targets(&track, 0, &position, &yawed);
        for (a, b) in level[..12].chunks(3).zip(turned[..12].chunks(3)) {
            assert!((b[1] + a[0]).abs() < 1e-6 && (b[0] - a[1]).abs() < 1e-6, "{a:?} → {b:?}");
        }
        // The next gate's part is gate 1's, whichever gate is the target's.
        assert!((level[GATE_TARGETS - 1] - (12f32.powi(2) + 9.0).sqrt().ln()).abs() < 1e-5);
        assert_eq!(gate_targets(&track, 1, &position, &Matrix3::identity())[PER_GATE..], level[..PER_GATE]);
    }

    #[test]
    fn only_gates_the_image_shows_are_scored() {
        let mut image = vec![0u8; IMAGE_PIXELS];
        assert_eq!(shown_mask(&image), [0.0; GATE_TARGETS]);
        image[100] = NEXT_COLOUR;
        let mask = shown_mask(&image);
        assert_eq!((mask[..PER_GATE].iter().sum::<f32>(), mask[PER_GATE..].iter().sum::<f32>()), (0.0, PER_GATE as f32));
        image[7] = TARGET_COLOUR;
        assert_eq!(shown_mask(&image), [1.0; GATE_TARGETS]);
    }

    #[test]
    fn a_head_round_trips_with_its_ids_and_refuses_other_files() {
        let device = Device::flex();
        let head = GateHead::new(3, &device);
        let back = GateHead::from_bytes(&head.to_bytes(), &device).unwrap();
        assert_eq!(back.layer.param_ids(), head.layer.param_ids());
        let input = Tensor::<2>::ones([2, EMBEDDING], &device);
        assert_eq!(back.forward(input.clone()).into_data(), head.forward(input).into_data());
        assert!(GateHead::from_bytes(b"not a head", &device).is_err());
    }
}
