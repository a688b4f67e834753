//! The student of a distillation: its actor regresses the teacher's labels on minibatches of
//! the data set — a vision student from a state-based policy, or a state-based one imitating
//! the reference pilot.

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Bytes, Device, Tensor, TensorData};
use learner::ppo::update::scalar;
use learner::{LearnerError, Network};
use policy::NetworkBlob;
use policy::vision::image_tensor;
use policy::{Agent, Architecture, ObsNormalizer, WeightsBlob};
use sim::ACTION_DIM;

use crate::dataset::DistillDataset;

/// A student under supervised training: its actor regresses the teacher's actions. Taught by a
/// state-based policy, it takes the teacher's critic (same state input, so that PPO can start
/// from the student) and its normaliser, frozen. Taught by a scripted teacher (the reference
/// pilot), it has a fresh critic and learns its normaliser from the states it is shown
/// ([`Student::observe`]), as PPO would.
pub struct Student {
    /// Always `Some` between calls; taken while burn's optimiser consumes and returns it.
    model: Option<Network>,
    optimizer: ModuleOptimizer,
    architecture: Architecture,
    normalizer: ObsNormalizer,
    /// True when the normaliser follows the states seen (no policy teacher to take it from).
    learns_normalizer: bool,
    version: u64,
    device: Device,
}

/// Adam for the regression (ε as SPEC §10; no weight decay).
fn student_adam() -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(1e-5).init()
}

impl Student {
    /// A student of `architecture` (its agent says which network): a fresh actor (seeded, log
    /// std `initial_log_std`), or `start`'s (a policy of the same architecture, e.g. a student
    /// distilled on one track) with a fresh optimiser. With a `teacher` — a state-based policy
    /// whose observation and hidden widths `architecture` shares — the critic and the
    /// normaliser are the teacher's; without one, a fresh critic and a normaliser to learn.
    pub fn new(
        architecture: &Architecture,
        teacher: Option<&WeightsBlob>,
        start: Option<&WeightsBlob>,
        initial_log_std: f64,
        seed: u64,
    ) -> Result<Self, LearnerError> {
        let device = Device::flex().autodiff();
        let architecture = architecture.clone();
        let start_error = |e: policy::BlobError| LearnerError::State(format!("starting student: {e}"));
        // A vision start whose actor does not read the previous action learns to: it is widened
        // with zero weights, so the student starts out acting exactly as the start did.
        let widened = match start {
            Some(blob) if architecture.vision_previous_action && !blob.architecture.vision_previous_action => {
                Some(blob.with_vision_previous_action().map_err(start_error)?)
            }
            _ => None,
        };
        let start = widened.as_ref().or(start);
        if let Some(blob) = start {
            // A vision student's CNN and actor read the image and the proprioception alone, and
            // its critic becomes the teacher's: a start taught in another layout fits.
            let mut expected = architecture.clone();
            if teacher.is_some() && architecture.agent == Agent::Vision {
                expected.set_observation_layout(blob.architecture.observation);
            }
            blob.check_architecture(&expected).map_err(start_error)?;
        }
        let mut model = match start {
            None => Network::new(&architecture, initial_log_std, seed, &device),
            Some(blob) => Network::from_blob(blob, &device).map_err(start_error)?,
        };
        let normalizer = match teacher {
            None => start.map_or_else(|| ObsNormalizer::new(architecture.observation_dim), |blob| blob.normalizer.clone()),
            Some(teacher) => {
                let teacher_error = |e: policy::BlobError| LearnerError::State(format!("teacher: {e}"));
                teacher.check_agent(Agent::State).map_err(teacher_error)?;
                teacher
                    .check_architecture(&Architecture { agent: Agent::State, vision_previous_action: false, ..architecture.clone() })
                    .map_err(teacher_error)?;
                let critic = teacher.model(&device).map_err(teacher_error)?.critic;
                match &mut model {
                    Network::State(m) => m.critic = critic,
                    Network::Vision(m) => m.critic = critic,
                }
                teacher.normalizer.clone()
            }
        };
        Ok(Self {
            model: Some(model),
            optimizer: student_adam(),
            architecture,
            normalizer,
            learns_normalizer: teacher.is_none(),
            version: 0,
            device,
        })
    }

    /// Restores a student from its weights blob and optimiser state ([`Student::weights`],
    /// [`Student::optimizer_state`]); `learns_normalizer` as it was created (no policy teacher).
    pub fn restore(weights: &[u8], optimizer: &[u8], learns_normalizer: bool) -> Result<Self, LearnerError> {
        let blob = WeightsBlob::from_bytes(weights).map_err(|e| LearnerError::State(e.to_string()))?;
        let device = Device::flex().autodiff();
        let model = Network::from_blob(&blob, &device).map_err(|e| LearnerError::State(e.to_string()))?;
        let optimizer = student_adam()
            .from_bytes(Bytes::from_bytes_vec(optimizer.to_vec()))
            .map_err(|e| LearnerError::State(format!("student optimiser: {e:?}")))?;
        Ok(Self {
            model: Some(model),
            optimizer,
            architecture: blob.architecture.clone(),
            normalizer: blob.normalizer,
            learns_normalizer,
            version: blob.version,
            device,
        })
    }

    #[allow(clippy::expect_used, reason = "the model is present between calls")]
    fn model(&self) -> &Network {
        self.model.as_ref().expect("the model is present between calls")
    }

    /// Gradient steps taken so far (the blob's version).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The student as a weights blob of its agent.
    pub fn weights(&self) -> WeightsBlob {
        self.model().blob(self.version, &self.architecture, &self.normalizer)
    }

    /// The optimiser's moments, for exact resume.
    #[allow(clippy::expect_used, reason = "optimiser state serialises")]
    pub fn optimizer_state(&self) -> Vec<u8> {
        self.optimizer.into_bytes().expect("optimiser state serialises").to_vec()
    }

    /// Shows the student raw states (rows of the observation): a student without a policy
    /// teacher folds them into its normaliser; one with a teacher keeps the teacher's.
    pub fn observe(&mut self, raw_states: &[f32]) {
        if self.learns_normalizer {
            self.normalizer.update(raw_states);
        }
    }

    /// One gradient step of the mean squared error between the student's action means and the
    /// teacher's labels on samples `rows` of `data`; returns the loss before the step.
    #[allow(clippy::expect_used, reason = "the model is present between calls; float outputs")]
    pub fn train_step(&mut self, data: &DistillDataset, rows: &[usize], learning_rate: f64) -> f64 {
        let n = rows.len();
        let dim = data.state_dim();
        let mut states = vec![0.0; n * dim];
        self.normalizer.normalize(&data.states(rows), &mut states);
        let states = Tensor::<2>::from_data(TensorData::new(states, [n, dim]), &self.device);
        let labels = Tensor::<2>::from_data(TensorData::new(data.labels(rows), [n, ACTION_DIM]), &self.device);
        let squared_error = |means: Tensor<2>| (means - labels).powi_scalar(2).mean();
        let (loss, model) = match self.model.take().expect("the model is present between calls") {
            Network::State(model) => {
                let loss = squared_error(model.action_means(states));
                let value = f64::from(scalar(loss.clone()));
                let grads = GradientsParams::from_grads(loss.backward(), &model);
                (value, Network::State(self.optimizer.step(learning_rate, model, grads)))
            }
            Network::Vision(model) => {
                let images = image_tensor(&data.images(rows), &self.device);
                let loss = squared_error(model.actor_mean(images, states));
                let value = f64::from(scalar(loss.clone()));
                let grads = GradientsParams::from_grads(loss.backward(), &model);
                (value, Network::Vision(self.optimizer.step(learning_rate, model, grads)))
            }
        };
        self.model = Some(model);
        self.version += 1;
        loss
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::two_gate_track as track;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use sim::camera::IMAGE_PIXELS;
    use sim::{Controller, EnvConfig, RaceEnv, STATE_OBS_DIM};

    #[test]
    fn regression_brings_the_students_actions_to_the_teachers() {
        // A tiny problem: 32 states on a two-gate track, labels from a fixed teacher.
        let arch = Architecture { hidden: vec![32, 32], ..Architecture::paper() };
        let teacher_net = policy::ActorCritic::new(&arch, -0.5, 7, &Device::flex());
        let teacher = WeightsBlob::from_model(1, &arch, &ObsNormalizer::new(arch.observation_dim), &teacher_net);
        let teacher_policy = policy::Policy::from_blob(&teacher).unwrap();
        let mut data = DistillDataset::new(64, arch.observation_dim);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        for _ in 0..32 {
            let state = env.observation_in(arch.observation);
            // Labels scaled up so that the student's initial near-zero head is far from them.
            let label: Vec<f32> = teacher_policy.deterministic_actions(&state).iter().map(|a| (a * 40.0).clamp(-1.0, 1.0)).collect();
            data.offer(&env, &state, &label, &mut rng);
            env.step(&[0.3, 0.2, -0.1, 0.2]);
        }
        let vision_arch = Architecture { agent: Agent::Vision, ..arch.clone() };
        let mut student = Student::new(&vision_arch, Some(&teacher), None, 0.0, 2).unwrap();
        let rows: Vec<usize> = (0..data.len()).collect();
        let first = student.train_step(&data, &rows, 1e-3);
        let mut last = first;
        for _ in 0..60 {
            last = student.train_step(&data, &rows, 1e-3);
        }
        assert!(first > 0.05, "the fresh student is far from the labels: {first}");
        assert!(last < 0.25 * first, "loss {first} → {last}");
        // The student's blob flies with the same actions the training saw.
        let blob = student.weights();
        assert_eq!((blob.version, blob.architecture.agent), (61, Agent::Vision));
        let vision = policy::VisionPolicy::from_blob(&blob).unwrap();
        let means = vision.mean_actions(&data.images(&rows), &data.states(&rows));
        let mse: f32 = means.iter().zip(data.labels(&rows)).map(|(m, l)| (m - l).powi(2)).sum::<f32>() / means.len() as f32;
        assert!(f64::from(mse) < 0.3 * first, "{mse}");
        // The critic is the teacher's: same values on the same states.
        let states = Tensor::<2>::from_data(TensorData::new(data.states(&rows[..4]), [4, STATE_OBS_DIM]), &Device::flex());
        let teacher_values = teacher_net.forward(states.clone()).1.into_data();
        let student_values = blob.vision_model(&Device::flex()).unwrap().critic.forward(states).squeeze_dim::<1>(1).into_data();
        assert_eq!(teacher_values, student_values);
        // A new student can start from this one: same actions, a fresh optimiser, version 0.
        let second = Student::new(&vision_arch, Some(&teacher), Some(&blob), 0.0, 99).unwrap();
        let again = policy::VisionPolicy::from_blob(&second.weights()).unwrap().mean_actions(&data.images(&rows), &data.states(&rows));
        assert_eq!((again, second.version()), (means, 0));
        // Exact resume: restored weights and moments take the same next step.
        let mut restored = Student::restore(&blob.to_bytes(), &student.optimizer_state(), false).unwrap();
        assert_eq!(restored.train_step(&data, &rows, 1e-3), student.train_step(&data, &rows, 1e-3));
        assert_eq!(restored.weights(), student.weights());
    }

    #[test]
    fn a_vision_student_starts_from_one_taught_in_another_layout_and_takes_the_new_teachers_critic() {
        let arch = Architecture { hidden: vec![16, 16], ..Architecture::paper() };
        let mut line_arch = arch.clone();
        line_arch.set_observation_layout(sim::ObservationLayout { line_points: 4, ..arch.observation });
        let teacher_of = |a: &Architecture, seed| {
            let net = policy::ActorCritic::new(a, -0.5, seed, &Device::flex());
            WeightsBlob::from_model(1, a, &ObsNormalizer::new(a.observation_dim), &net)
        };
        let (old_teacher, new_teacher) = (teacher_of(&arch, 1), teacher_of(&line_arch, 2));
        let vision = |a: &Architecture| Architecture { agent: Agent::Vision, ..a.clone() };
        let first = Student::new(&vision(&arch), Some(&old_teacher), None, 0.0, 3).unwrap().weights();
        let second = Student::new(&vision(&line_arch), Some(&new_teacher), Some(&first), 0.0, 4).unwrap().weights();
        assert_eq!(second.architecture, vision(&line_arch));
        // Same CNN and actor: the same actions on the same image and proprioception.
        let env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        let mut image = vec![0u8; IMAGE_PIXELS];
        env.render_camera(&mut image);
        let act =
            |blob: &WeightsBlob, layout| policy::VisionPolicy::from_blob(blob).unwrap().mean_actions(&image, &env.observation_in(layout));
        assert_eq!(act(&first, arch.observation), act(&second, line_arch.observation));
        // The critic is the new teacher's.
        let states = Tensor::<2>::from_data(TensorData::new(env.observation_in(line_arch.observation), [1, 52]), &Device::flex());
        let teacher_value = new_teacher.model(&Device::flex()).unwrap().forward(states.clone()).1.into_data();
        let student_value = second.vision_model(&Device::flex()).unwrap().critic.forward(states).squeeze_dim::<1>(1).into_data();
        assert_eq!(teacher_value, student_value);
        // A state student still needs its start's exact shape.
        assert!(Student::new(&line_arch, None, Some(&old_teacher), -0.5, 5).is_err());
    }

    #[test]
    fn a_state_student_imitates_the_pilot_and_learns_its_normaliser() {
        let arch = Architecture { hidden: vec![32, 32], ..Architecture::paper() };
        let layout = arch.observation;
        let mut env = RaceEnv::new(track(), EnvConfig::default(), 1, 0);
        let mut pilot = sim::ReferencePilot::default();
        pilot.reset(&env);
        let mut student = Student::new(&arch, None, None, -0.5, 3).unwrap();
        let mut data = DistillDataset::new(256, arch.observation_dim);
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut shown = Vec::new();
        for _ in 0..128 {
            let state = env.observation_in(layout);
            let label = pilot.act(&env);
            data.offer(&env, &state, &label, &mut rng);
            student.observe(&state);
            shown.extend(state);
            env.step(&label);
            if env.stats().crash.is_some() {
                env.reset();
                pilot.reset(&env);
            }
        }
        // The normaliser is the states' own: a teacher-less student learns it from what it sees.
        let mut expected = ObsNormalizer::new(arch.observation_dim);
        expected.update(&shown);
        let learnt = student.weights().normalizer;
        assert_eq!(learnt.count, expected.count);
        // Row by row and all at once agree up to rounding.
        for (a, b) in learnt.mean.iter().zip(&expected.mean).chain(learnt.var.iter().zip(&expected.var)) {
            assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "{a} vs {b}");
        }
        let rows: Vec<usize> = (0..data.len()).collect();
        let first = student.train_step(&data, &rows, 3e-3);
        let mut last = first;
        for _ in 0..150 {
            last = student.train_step(&data, &rows, 3e-3);
        }
        assert!(last < 0.25 * first, "loss {first} → {last}");
        // The blob is a state policy whose deterministic actions are the pilot's, roughly.
        let blob = student.weights();
        assert_eq!(blob.architecture.agent, Agent::State);
        let actions = policy::Policy::from_blob(&blob).unwrap().deterministic_actions(&data.states(&rows));
        let mse: f32 = actions.iter().zip(data.labels(&rows)).map(|(a, l)| (a - l).powi(2)).sum::<f32>() / actions.len() as f32;
        assert!(f64::from(mse) < 0.3 * first, "{mse} against {first}");
        // Exact resume, the normaliser still learning.
        let mut restored = Student::restore(&blob.to_bytes(), &student.optimizer_state(), true).unwrap();
        restored.observe(&shown[..40]);
        student.observe(&shown[..40]);
        assert_eq!(restored.train_step(&data, &rows, 1e-3), student.train_step(&data, &rows, 1e-3));
        assert_eq!(restored.weights(), student.weights());
    }
}
