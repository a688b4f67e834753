//! The vision agent's actor-critic (SPEC §5): a CNN reads the 84×84 camera image
//! (conv 32@8×8/4, 64@4×4/2, 64@3×3/1, LeakyReLU after each, flatten, linear → 128, LeakyReLU,
//! as Stable-Baselines3's NatureCNN ends in an activation), the actor MLP reads
//! `[embedding, R_WB columns 0–1, v, ω]`, and the critic MLP reads the 40-number state
//! observation — asymmetric: the critic exists only in training, where the state is known.

use burn::module::{Module, Param, ParamId};
use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::{Device, Tensor, TensorData};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sim::camera::IMAGE_PIXELS;

use kernels::dense::{dense, leaky_relu};
use policyfile::Architecture;
/// The vision agent's sizes (SPEC §5), which its policy files record.
pub use policyfile::shapes::{CONV_OUTPUT, EMBEDDING, IMAGE_SIDE, PROPRIOCEPTION, actor_state_len};
use policyfile::shapes::{CONVOLUTIONS, ExportedParam, ShapeMismatch, check_shapes, parameter_shapes};

use crate::network::{Mlp, exported, loaded, orthogonal, parameter};

/// Camera bytes as the network reads them: scaled to [0, 1].
pub fn pixels_to_unit(image: &[u8]) -> Vec<f32> {
    image.iter().map(|&p| f32::from(p) / 255.0).collect()
}

/// Camera images as the CNN reads them: `n` 84×84 images (bytes) → `[n, 1, 84, 84]` scaled to
/// [0, 1].
pub fn image_tensor(pixels: &[u8], device: &Device) -> Tensor<4> {
    let n = pixels.len() / IMAGE_PIXELS;
    assert_eq!(pixels.len(), n * IMAGE_PIXELS, "whole 84×84 images");
    Tensor::<4>::from_data(TensorData::new(pixels_to_unit(pixels), [n, 1, IMAGE_SIDE, IMAGE_SIDE]), device)
}

/// The vision actor-critic.
#[derive(Module, Debug)]
pub struct VisionActorCritic {
    /// The three convolutions.
    pub convolutions: Vec<Conv2d>,
    /// Flattened convolution output → embedding.
    pub embedding: burn::nn::Linear,
    /// `[embedding, proprioception]` → action mean.
    pub actor: Mlp,
    /// State observation → value.
    pub critic: Mlp,
    /// Log standard deviation per action dimension (state-independent).
    pub log_std: Param<Tensor<1>>,
    negative_slope: f64,
    /// How many of the state observation's first numbers the actor reads ([`actor_state_len`]).
    actor_state_len: usize,
}

impl VisionActorCritic {
    /// A freshly initialised network: orthogonal weights (gain √2 for the convolutions,
    /// the embedding and hidden layers; 0.01 policy head, 1 value head), zero biases. `arch`
    /// gives the MLPs' hidden widths, the state observation's length (critic) and the slope.
    pub fn new(arch: &Architecture, initial_log_std: f64, seed: u64, device: &Device) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let gain = std::f64::consts::SQRT_2;
        let mut channels = 1;
        let convolutions = CONVOLUTIONS
            .iter()
            .map(|&(out, kernel, stride)| {
                let fan_in = channels * kernel * kernel;
                let conv = Conv2d {
                    weight: parameter(orthogonal(out, fan_in, gain, &mut rng), [out, channels, kernel, kernel], device),
                    bias: Some(parameter(vec![0.0; out], [out], device)),
                    stride: [stride, stride],
                    kernel_size: [kernel, kernel],
                    dilation: [1, 1],
                    groups: 1,
                    padding: PaddingConfig2d::Valid,
                };
                channels = out;
                conv
            })
            .collect();
        let embedding = burn::nn::Linear {
            weight: parameter(orthogonal(CONV_OUTPUT, EMBEDDING, gain, &mut rng), [CONV_OUTPUT, EMBEDDING], device),
            bias: Some(parameter(vec![0.0; EMBEDDING], [EMBEDDING], device)),
        };
        let slope = arch.negative_slope;
        Self {
            convolutions,
            embedding,
            actor: Mlp::new(&arch.layer_dims(EMBEDDING + actor_state_len(arch), arch.action_dim), 0.01, slope, &mut rng, device),
            critic: Mlp::new(&arch.layer_dims(arch.observation_dim, 1), 1.0, slope, &mut rng, device),
            log_std: parameter(vec![initial_log_std as f32; arch.action_dim], [arch.action_dim], device),
            negative_slope: slope,
            actor_state_len: actor_state_len(arch),
        }
    }

    /// Embeddings `[batch, 128]` of images `[batch, 1, 84, 84]` scaled to [0, 1].
    pub fn embed(&self, images: Tensor<4>) -> Tensor<2> {
        self.embed_convolved(self.convolve(images))
    }

    /// The convolutions' output `[batch, 3136]`, flattened, of images as [`VisionActorCritic::embed`] reads them.
    pub fn convolve(&self, images: Tensor<4>) -> Tensor<2> {
        let mut x = images;
        for conv in &self.convolutions {
            x = leaky_relu(conv.forward(x), self.negative_slope);
        }
        let batch = x.dims()[0];
        x.reshape([batch, CONV_OUTPUT])
    }

    /// Embeddings `[batch, 128]` of convolution outputs ([`VisionActorCritic::convolve`]).
    #[allow(clippy::expect_used, reason = "every layer is built with a bias")]
    pub fn embed_convolved(&self, convolved: Tensor<2>) -> Tensor<2> {
        let bias = self.embedding.bias.as_ref().expect("built with a bias").val();
        dense(convolved, self.embedding.weight.val(), bias, Some(self.negative_slope))
    }

    /// Action means `[batch, action_dim]` and values `[batch]` from images `[batch, 1, 84, 84]`
    /// in [0, 1] and normalised state observations `[batch, 40]`: the actor reads the image and
    /// the state's first 12 numbers (its proprioception; 16 with the previous action), the
    /// critic the whole state.
    pub fn forward(&self, images: Tensor<4>, states: Tensor<2>) -> (Tensor<2>, Tensor<1>) {
        (self.actor_mean(images, states.clone()), self.critic.forward(states).squeeze_dim(1))
    }

    /// The actor's half of [`VisionActorCritic::forward`]: action means only.
    pub fn actor_mean(&self, images: Tensor<4>, states: Tensor<2>) -> Tensor<2> {
        self.actor_mean_of(self.embed(images), states)
    }

    /// Action means from embeddings already computed ([`VisionActorCritic::embed`]), e.g. when
    /// a training-only head reads them too.
    pub fn actor_mean_of(&self, embedding: Tensor<2>, states: Tensor<2>) -> Tensor<2> {
        let batch = states.dims()[0];
        let proprioception = states.slice([0..batch, 0..self.actor_state_len]);
        self.actor.forward(Tensor::cat(vec![embedding, proprioception], 1))
    }

    /// Every parameter's id and rank: convolutions (weight, bias), embedding, actor layers,
    /// critic layers, log std.
    pub fn param_ids(&self) -> Vec<(ParamId, usize)> {
        let mut ids: Vec<(ParamId, usize)> = Vec::new();
        for conv in &self.convolutions {
            ids.push((conv.weight.id, 4));
            ids.extend(conv.bias.as_ref().map(|b| (b.id, 1)));
        }
        ids.push((self.embedding.weight.id, 2));
        ids.extend(self.embedding.bias.as_ref().map(|b| (b.id, 1)));
        ids.extend(self.actor.param_ids());
        ids.extend(self.critic.param_ids());
        ids.push((self.log_std.id, 1));
        ids
    }

    /// Every parameter's values in [`VisionActorCritic::param_ids`] order.
    pub fn export(&self) -> Vec<ExportedParam> {
        let mut out = Vec::new();
        for conv in &self.convolutions {
            out.push(exported(&conv.weight));
            out.extend(conv.bias.as_ref().map(exported));
        }
        out.push(exported(&self.embedding.weight));
        out.extend(self.embedding.bias.as_ref().map(exported));
        out.extend(self.actor.export());
        out.extend(self.critic.export());
        out.push(exported(&self.log_std));
        out
    }

    /// Rebuilds a network of `arch` from [`VisionActorCritic::export`]'s output, keeping ids.
    pub fn import(arch: &Architecture, params: &[ExportedParam], device: &Device) -> Result<Self, ShapeMismatch> {
        check_shapes(&parameter_shapes(&Architecture { agent: policyfile::Agent::Vision, ..arch.clone() }), params)?;
        let (convs, rest) = params.split_at(2 * CONVOLUTIONS.len());
        let convolutions = convs
            .chunks(2)
            .zip(CONVOLUTIONS)
            .map(|(wb, (_, kernel, stride))| Conv2d {
                weight: loaded(&wb[0], device),
                bias: Some(loaded(&wb[1], device)),
                stride: [stride, stride],
                kernel_size: [kernel, kernel],
                dilation: [1, 1],
                groups: 1,
                padding: PaddingConfig2d::Valid,
            })
            .collect();
        let (embedding, rest) = rest.split_at(2);
        let mlp_params = 2 * (arch.hidden.len() + 1);
        let (actor, rest) = rest.split_at(mlp_params);
        let (critic, log_std) = rest.split_at(mlp_params);
        Ok(Self {
            convolutions,
            embedding: burn::nn::Linear { weight: loaded(&embedding[0], device), bias: Some(loaded(&embedding[1], device)) },
            actor: Mlp::import(actor, arch.negative_slope, device),
            critic: Mlp::import(critic, arch.negative_slope, device),
            log_std: loaded(&log_std[0], device),
            negative_slope: arch.negative_slope,
            actor_state_len: actor_state_len(arch),
        })
    }

    /// Multiply-adds of one forward pass of one sample (convolutions, embedding, both MLPs).
    pub fn macs_per_sample(arch: &Architecture) -> usize {
        let (mut side, mut channels, mut macs) = (IMAGE_SIDE, 1, 0);
        for (out, kernel, stride) in CONVOLUTIONS {
            side = (side - kernel) / stride + 1;
            macs += side * side * out * channels * kernel * kernel;
            channels = out;
        }
        let mlp = |input: usize, out: usize| {
            let mut d = vec![input];
            d.extend(&arch.hidden);
            d.push(out);
            d.windows(2).map(|w| w[0] * w[1]).sum::<usize>()
        };
        macs + CONV_OUTPUT * EMBEDDING + mlp(EMBEDDING + actor_state_len(arch), arch.action_dim) + mlp(arch.observation_dim, 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::NetworkBlob;
    use burn::tensor::TensorData;

    #[test]
    fn forward_shapes_and_the_convolution_output_length() {
        let arch = Architecture { hidden: vec![32, 32], ..Architecture::paper() };
        let device = Device::flex();
        let net = VisionActorCritic::new(&arch, -0.5, 0, &device);
        let batch = 3;
        let images = Tensor::<4>::from_data(
            TensorData::new(vec![0.5f32; batch * IMAGE_SIDE * IMAGE_SIDE], [batch, 1, IMAGE_SIDE, IMAGE_SIDE]),
            &device,
        );
        assert_eq!(net.embed(images.clone()).dims(), [batch, EMBEDDING]);
        let states = Tensor::<2>::zeros([batch, arch.observation_dim], &device);
        let (mean, value) = net.forward(images, states);
        assert_eq!(mean.dims(), [batch, arch.action_dim]);
        assert_eq!(value.dims(), [batch]);
        // 20×20×32×64 + 9×9×64×512 + 7×7×64×576 for the convolutions.
        let conv = 20 * 20 * 32 * 64 + 9 * 9 * 64 * 512 + 7 * 7 * 64 * 576;
        let mlps = CONV_OUTPUT * EMBEDDING + (140 * 32 + 32 * 32 + 32 * 4) + (40 * 32 + 32 * 32 + 32);
        assert_eq!(VisionActorCritic::macs_per_sample(&arch), conv + mlps);
    }

    #[test]
    fn a_vision_blob_round_trips_and_each_kind_refuses_the_other() {
        use crate::{ActorCritic, BlobError, ObsNormalizer, Policy, WeightsBlob};
        use policyfile::Agent;
        let arch = Architecture { hidden: vec![16, 8], ..Architecture::paper() };
        let device = Device::flex();
        let net = VisionActorCritic::new(&arch, -0.5, 3, &device);
        let blob = WeightsBlob::from_vision_model(4, &arch, &ObsNormalizer::new(arch.observation_dim), &net);
        assert_eq!(blob.architecture.agent, Agent::Vision);
        let back = WeightsBlob::from_bytes(&blob.to_bytes()).unwrap();
        assert_eq!(back, blob, "bit-exact round trip through the safetensors file");
        let names = WeightsBlob::tensor_names(&back.architecture);
        assert_eq!(&names[..3], ["cnn.0.weight", "cnn.0.bias", "cnn.1.weight"]);
        // The rebuilt network is the same network: same outputs, same parameter ids.
        let rebuilt = back.vision_model(&device).unwrap();
        assert_eq!(rebuilt.param_ids(), net.param_ids());
        let images =
            Tensor::<4>::from_data(TensorData::new(vec![0.3f32; 2 * IMAGE_SIDE * IMAGE_SIDE], [2, 1, IMAGE_SIDE, IMAGE_SIDE]), &device);
        let states = Tensor::<2>::ones([2, arch.observation_dim], &device);
        let (a, _) = net.forward(images.clone(), states.clone());
        let (b, _) = rebuilt.forward(images, states);
        assert_eq!(a.into_data(), b.into_data());
        // Each kind refuses the other, naming both.
        let err = back.model(&device).unwrap_err();
        assert_eq!(err, BlobError::Agent { found: Agent::Vision, expected: Agent::State });
        assert!(err.to_string().contains("vision-based") && err.to_string().contains("state-based"), "{err}");
        assert!(matches!(Policy::from_blob(&back), Err(BlobError::Agent { .. })));
        let state =
            WeightsBlob::from_model(4, &arch, &ObsNormalizer::new(arch.observation_dim), &ActorCritic::new(&arch, -0.5, 3, &device));
        assert_eq!(state.vision_model(&device).unwrap_err(), BlobError::Agent { found: Agent::State, expected: Agent::Vision });
    }

    #[test]
    fn the_vision_controller_renders_the_camera_and_acts_on_it() {
        use crate::{ObsNormalizer, VisionPolicy, VisionPolicyController, WeightsBlob};
        use sim::{Controller, EnvConfig, RaceEnv};
        let arch = Architecture {
            hidden: vec![16, 16],
            observation: sim::ObservationLayout::spec(sim::ObservationFrame::Heading),
            ..Architecture::paper()
        };
        let device = Device::flex();
        // A policy head with gain 1, so that the image visibly moves the action.
        let mut net = VisionActorCritic::new(&arch, -0.5, 5, &device);
        let mut params = net.export();
        let head = 2 * policyfile::shapes::CONVOLUTION_COUNT + 2 + 2 * arch.hidden.len();
        params[head].values.iter_mut().for_each(|v| *v *= 100.0);
        net = VisionActorCritic::import(&arch, &params, &device).unwrap();
        let blob = WeightsBlob::from_vision_model(1, &arch, &ObsNormalizer::new(arch.observation_dim), &net);
        let policy = std::sync::Arc::new(VisionPolicy::from_blob(&blob).unwrap());
        let track = std::sync::Arc::new(
            sim::Track::new(
                "two",
                vec![
                    sim::Gate::new(sim::nalgebra::Vector3::new(4.0, 0.0, 2.0), 0.0),
                    sim::Gate::new(sim::nalgebra::Vector3::new(-4.0, 0.0, 2.0), 3.0),
                ],
                None,
                sim::Arena::default(),
            )
            .unwrap(),
        );
        let env = RaceEnv::new(track, EnvConfig::evaluation(), 0, 0);
        let mut controller = VisionPolicyController::new(policy.clone());
        let action = controller.act(&env);
        // By hand: the camera image and the state, through the same network.
        let mut image = vec![0u8; sim::camera::IMAGE_PIXELS];
        env.render_camera(&mut image);
        assert!(image.contains(&sim::camera::TARGET_COLOUR), "gate 0 is in view from the start");
        let by_hand = policy.mean_actions(&image, &env.observation_in(arch.observation));
        assert_eq!(action.to_vec(), by_hand.iter().map(|a| a.clamp(-1.0, 1.0)).collect::<Vec<_>>());
        // A blank image gives another action: the controller really looks.
        let blank = policy.mean_actions(&vec![0u8; sim::camera::IMAGE_PIXELS], &env.observation_in(arch.observation));
        assert_ne!(blank, by_hand);
    }

    #[test]
    fn the_image_changes_the_action_and_not_the_value() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let device = Device::flex();
        let net = VisionActorCritic::new(&arch, -0.5, 1, &device);
        let image = |level: f32| {
            Tensor::<4>::from_data(TensorData::new(vec![level; IMAGE_SIDE * IMAGE_SIDE], [1, 1, IMAGE_SIDE, IMAGE_SIDE]), &device)
        };
        let states = Tensor::<2>::ones([1, arch.observation_dim], &device);
        let (m0, v0) = net.forward(image(0.0), states.clone());
        let (m1, v1) = net.forward(image(1.0), states);
        let diff: f32 = (m0 - m1).abs().into_data().try_into_vec::<f32>().unwrap().iter().sum();
        assert!(diff > 0.0, "the actor sees the image");
        assert_eq!(v0.into_data(), v1.into_data(), "the critic reads the state only");
    }

    /// SPEC's actor ignores the previous action (state numbers 12–15); a widened one acts as
    /// its source did until its new weights move, and then reads exactly those numbers.
    #[test]
    fn a_widened_actor_acts_as_before_and_then_reads_the_previous_action() {
        use crate::{ObsNormalizer, VisionPolicy, WeightsBlob};
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let device = Device::flex();
        let net = VisionActorCritic::new(&arch, -0.5, 2, &device);
        let mut params = net.export();
        let head = 2 * policyfile::shapes::CONVOLUTION_COUNT + 2 + 2 * arch.hidden.len();
        params[head].values.iter_mut().for_each(|v| *v *= 100.0);
        let spec = WeightsBlob::from_vision_model(
            1,
            &arch,
            &ObsNormalizer::new(arch.observation_dim),
            &VisionActorCritic::import(&arch, &params, &device).unwrap(),
        );
        let image: Vec<u8> = (0..IMAGE_SIDE * IMAGE_SIDE).map(|i| (i * 7 % 256) as u8).collect();
        let state: Vec<f32> = (0..arch.observation_dim).map(|i| (i as f32 * 0.37).sin()).collect();
        let mut other_previous = state.clone();
        other_previous[12..16].copy_from_slice(&[0.9, -0.9, 0.5, -0.5]);
        let act = |blob: &WeightsBlob, state: &[f32]| VisionPolicy::from_blob(blob).unwrap().mean_actions(&image, state);
        assert_eq!(act(&spec, &state), act(&spec, &other_previous), "SPEC's actor does not read the previous action");

        let widened = spec.with_vision_previous_action().unwrap();
        assert!(widened.architecture.vision_previous_action);
        let back = WeightsBlob::from_bytes(&widened.to_bytes()).unwrap();
        assert_eq!(back, widened, "the flag and the wider layer round-trip");
        assert_eq!(act(&back, &state), act(&spec, &state), "zero weights: the same actions");
        assert_eq!(act(&back, &other_previous), act(&spec, &state));

        let mut trained = back.clone();
        let first = 2 * policyfile::shapes::CONVOLUTION_COUNT + 2;
        let rows = trained.params[first].shape[0];
        assert_eq!(rows, EMBEDDING + PROPRIOCEPTION + sim::ACTION_DIM);
        let outputs = trained.params[first].shape[1];
        trained.params[first].values[(rows - 1) * outputs..].iter_mut().for_each(|w| *w = 0.5);
        assert_ne!(act(&trained, &state), act(&trained, &other_previous), "the widened actor reads the previous action");
        let mut beyond = state.clone();
        beyond[16..].iter_mut().for_each(|x| *x += 1.0);
        assert_eq!(act(&trained, &state), act(&trained, &beyond), "and nothing after it");
        assert_eq!(trained.with_vision_previous_action().unwrap(), trained, "widening twice changes nothing");
        assert!(matches!(
            WeightsBlob::from_model(1, &arch, &ObsNormalizer::new(40), &crate::ActorCritic::new(&arch, 0.0, 0, &device))
                .with_vision_previous_action(),
            Err(crate::BlobError::Agent { .. })
        ));
    }

    /// A vision policy given wider hidden layers acts and values exactly as before, round-trips,
    /// and reaches its new units once their outgoing weights move; narrower or deeper is refused.
    #[test]
    fn wider_hidden_layers_act_and_value_as_before_until_their_new_units_are_trained() {
        use crate::{ObsNormalizer, VisionPolicy, WeightsBlob};
        let arch = Architecture { hidden: vec![8, 6], ..Architecture::paper() };
        let device = Device::flex();
        let mut normalizer = ObsNormalizer::new(arch.observation_dim);
        normalizer.update(&(0..arch.observation_dim * 3).map(|i| (i as f32 * 0.3).cos()).collect::<Vec<_>>());
        let narrow = WeightsBlob::from_vision_model(4, &arch, &normalizer, &VisionActorCritic::new(&arch, -1.0, 5, &device));
        let images: Vec<u8> = (0..2 * IMAGE_SIDE * IMAGE_SIDE).map(|i| (i * 13 % 256) as u8).collect();
        let states: Vec<f32> = (0..2 * arch.observation_dim).map(|i| (i as f32 * 0.37).sin()).collect();
        let run = |blob: &WeightsBlob| {
            let policy = VisionPolicy::from_blob(blob).unwrap();
            (policy.mean_actions(&images, &states), policy.values(&states))
        };
        let wide = WeightsBlob::from_bytes(&narrow.with_hidden(&[12, 9], 3).unwrap().to_bytes()).unwrap();
        assert_eq!(wide.architecture.hidden, [12, 9]);
        let (before, after) = (run(&narrow), run(&wide));
        for (a, b) in before.0.iter().chain(&before.1).zip(after.0.iter().chain(&after.1)) {
            assert!((a - b).abs() < 1e-5, "{before:?} → {after:?}");
        }
        // The actor's output layer: rows 6..9 are the new second-layer units' outgoing weights.
        let mut trained = wide.clone();
        let output = 2 * policyfile::shapes::CONVOLUTION_COUNT + 2 + 2 * arch.hidden.len();
        assert_eq!(trained.params[output].shape, [9, arch.action_dim]);
        trained.params[output].values[8 * arch.action_dim] = 1.0;
        assert_ne!(run(&trained).0, after.0, "the new units feed the actor once their weights move");
        assert!(narrow.with_hidden(&[4, 6], 3).is_err(), "narrower");
        assert!(narrow.with_hidden(&[8, 6, 6], 3).is_err(), "deeper");
    }
}
