//! Networks into weights blobs and back: the one place burn's parameters meet the policy file.

use burn::tensor::Device;
use policyfile::{Agent, Architecture, BlobError, ObsNormalizer, WeightsBlob};

use crate::network::ActorCritic;
use crate::vision::VisionActorCritic;

/// A weights blob made from a network, or made into one (with the parameters' original ids).
pub trait NetworkBlob: Sized {
    /// Captures a state-based network with its normaliser.
    fn from_model(version: u64, architecture: &Architecture, normalizer: &ObsNormalizer, model: &ActorCritic) -> Self;
    /// Captures a vision agent with its normaliser (of the critic's state observations).
    fn from_vision_model(version: u64, architecture: &Architecture, normalizer: &ObsNormalizer, model: &VisionActorCritic) -> Self;
    /// The state-based network on `device`.
    fn model(&self, device: &Device) -> Result<ActorCritic, BlobError>;
    /// The vision network on `device`.
    fn vision_model(&self, device: &Device) -> Result<VisionActorCritic, BlobError>;
}

impl NetworkBlob for WeightsBlob {
    fn from_model(version: u64, architecture: &Architecture, normalizer: &ObsNormalizer, model: &ActorCritic) -> Self {
        Self { version, architecture: architecture.clone(), normalizer: normalizer.clone(), params: model.export() }
    }

    fn from_vision_model(version: u64, architecture: &Architecture, normalizer: &ObsNormalizer, model: &VisionActorCritic) -> Self {
        let architecture = Architecture { agent: Agent::Vision, ..architecture.clone() };
        Self { version, architecture, normalizer: normalizer.clone(), params: model.export() }
    }

    fn model(&self, device: &Device) -> Result<ActorCritic, BlobError> {
        self.check_agent(Agent::State)?;
        Ok(ActorCritic::import(&self.architecture, &self.params, device)?)
    }

    fn vision_model(&self, device: &Device) -> Result<VisionActorCritic, BlobError> {
        self.check_agent(Agent::Vision)?;
        Ok(VisionActorCritic::import(&self.architecture, &self.params, device)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_network_round_trips_bit_exactly_through_its_blob() {
        let arch = Architecture { hidden: vec![8, 8], ..Architecture::paper() };
        let model = ActorCritic::new(&arch, -0.5, 1, &Device::flex());
        let mut normalizer = ObsNormalizer::new(arch.observation_dim);
        normalizer.update(&(0..arch.observation_dim * 3).map(|i| i as f32 * 0.1).collect::<Vec<_>>());
        let blob = WeightsBlob::from_model(7, &arch, &normalizer, &model);
        let bytes = blob.to_bytes();
        let back = WeightsBlob::from_bytes(&bytes).unwrap();
        let again = WeightsBlob::from_model(7, &back.architecture, &back.normalizer, &back.model(&Device::flex()).unwrap());
        assert_eq!(again.to_bytes(), bytes);
        assert_eq!(again.params[0].values.len(), 40 * 8);
        assert!(again.params.last().unwrap().values.iter().all(|&v| v == -0.5), "initial log std");
        assert!(matches!(blob.vision_model(&Device::flex()), Err(BlobError::Agent { .. })), "a state policy is no vision network");
    }
}
