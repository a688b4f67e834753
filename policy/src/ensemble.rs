//! Several state-based policies flying as one: the mean of their mean actions.
//!
//! Policies of different seeds fail on different tracks (nine proxy policies each fly 34–63 of 100
//! validation tracks, together 93), which is what averaging the decisions of several models —
//! bagging — is for; measured, an ensemble flies about what a majority of its members fly, not
//! their union (docs/notebook/generalist-rejected.md, "Ensembles of seeds"). Each member reads the
//! observation in its own frame and through its own normaliser, so members need not share anything
//! but the action space.

use std::sync::Arc;

use sim::{Controller, RaceEnv};

use crate::blob::{BlobError, WeightsBlob};
use crate::inference::{ControllerFactory, Policy};

/// A controller whose action is the mean of its members' deterministic actions.
#[derive(Clone, Debug)]
pub struct EnsembleController {
    members: Arc<Vec<Policy>>,
}

impl EnsembleController {
    /// An ensemble of state-based policies (a vision blob is refused); at least one.
    pub fn from_blobs(blobs: &[WeightsBlob]) -> Result<Self, BlobError> {
        if blobs.is_empty() {
            return Err(BlobError::Malformed("an ensemble needs at least one policy".into()));
        }
        let members = blobs.iter().map(Policy::from_blob).collect::<Result<Vec<_>, _>>()?;
        Ok(Self { members: Arc::new(members) })
    }

    /// A factory of controllers sharing these members (what `sim::eval::evaluate` takes).
    pub fn factory(self) -> ControllerFactory {
        Box::new(move || Box::new(self.clone()))
    }
}

impl Controller for EnsembleController {
    fn reset(&mut self, _env: &RaceEnv) {}

    /// The mean of the members' deterministic actions.
    fn act(&mut self, env: &RaceEnv) -> [f32; 4] {
        let mut sum = [0.0f32; 4];
        for member in self.members.iter() {
            let action = member.deterministic_actions(&env.observation_in(member.observation_layout()));
            for (s, a) in sum.iter_mut().zip(action) {
                *s += a;
            }
        }
        let n = self.members.len() as f32;
        sum.map(|s| s / n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{ActorCritic, Architecture, ObsNormalizer, PolicyController};
    use burn::tensor::Device;
    use sim::nalgebra::Vector3;
    use sim::{Arena, EnvConfig, Gate, ObservationFrame, Track};

    fn blob(seed: u64, frame: ObservationFrame) -> WeightsBlob {
        let arch = Architecture { hidden: vec![16, 16], observation: sim::ObservationLayout::spec(frame), ..Architecture::paper() };
        // Large weights, so the members' actions differ clearly.
        let model = ActorCritic::new(&arch, -0.5, seed, &Device::default());
        let mut blob = WeightsBlob::from_model(seed, &arch, &ObsNormalizer::new(arch.observation_dim), &model);
        for p in &mut blob.params {
            p.values.iter_mut().for_each(|v| *v *= 30.0);
        }
        blob
    }

    fn env() -> RaceEnv {
        let gates = vec![Gate::new(Vector3::new(4.0, 1.0, 2.0), 0.5), Gate::new(Vector3::new(-4.0, 0.0, 2.0), 3.0)];
        let track = Track::new("two", gates, None, Arena::default()).unwrap();
        RaceEnv::new(Arc::new(track), EnvConfig::evaluation(), 0, 0)
    }

    fn alone(blob: &WeightsBlob, env: &RaceEnv) -> [f32; 4] {
        PolicyController::new(Arc::new(Policy::from_blob(blob).unwrap())).act(env)
    }

    #[test]
    fn the_ensemble_flies_the_mean_of_its_members_each_in_its_own_frame() {
        let env = env();
        let (a, b) = (blob(1, ObservationFrame::World), blob(2, ObservationFrame::Heading));
        let (x, y) = (alone(&a, &env), alone(&b, &env));
        assert!(x.iter().zip(&y).any(|(p, q)| (p - q).abs() > 0.05), "members must differ: {x:?} {y:?}");
        let mean = EnsembleController::from_blobs(&[a.clone(), b]).unwrap().act(&env);
        for i in 0..4 {
            assert!((mean[i] - (x[i] + y[i]) / 2.0).abs() < 1e-6, "{mean:?} against {x:?} and {y:?}");
        }
        assert_eq!(EnsembleController::from_blobs(&[a]).unwrap().act(&env), x, "one member is that policy");
    }

    #[test]
    fn an_empty_ensemble_is_refused() {
        assert!(EnsembleController::from_blobs(&[]).is_err());
    }
}
